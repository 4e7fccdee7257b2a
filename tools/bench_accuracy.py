"""Accuracy of the band metric against analytic geodesics, and surface-faithful covering (JSON).

Sections (all inputs synthetic, generated here with fixed seeds):

* ``metric``: band distance from one input point (``lodbuilder.sampling.band.band_distance``,
  default parameters) to every point of a plane, a sphere, a cylinder and a folded sheet, against
  the exact geodesic (plane: Euclidean; sphere: great circle; cylinder and folded sheet: unrolled).
  The sampling is chosen so that the default voxel size h gives R = 10, 20, 40 (and 80 with
  ``--big``) voxels for the sphere's and the cylinder's radius and the plane's half-width. Per case:
  mean and max relative error |d - g| / g over the points with g >= ``--min-geo`` voxels (default
  1, so nearly every point), the signed mean, and the largest absolute error in voxels.
* ``covering``: the full default ordering of a sheet folded over itself
  (``lodbuilder.datasets.folded_sheet``, two unit squares, random points) at
  gap 0.02 / 200k points and gap 0.01 / 400k points; for every level rho (a geometric series from
  0.24 down to 3 point spacings) the geodesic covering radius of the prefix (exact: the sheet
  unfolds to a rectangle) divided by rho, and the same for Euclidean FPS (fpsample) at equal size.
* ``limit``: the largest geodesic covering ratio over those levels for layers 2.5 ... 8 point
  spacings apart (100k points), to state the thinnest gap the defaults handle.

    python tools/bench_accuracy.py [--big] [--sections metric,covering,limit] [--json OUT]
                                   [--markdown docs/benchmarks.md] > accuracy.json
    python tools/bench_accuracy.py --from-json OUT --markdown docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the analytic references live beside the tests
sys.path.append(str(ROOT / "tools"))  # benchdoc (after tests: both have a surfaces module)

from surfaces import (  # noqa: E402
    cylinder_points,
    geodesic_cylinder,
    geodesic_folded,
    geodesic_plane,
    geodesic_sphere,
    plane_patch,
    sphere_points,
    unfold_folded,
)

SPACING_PER_VOXEL = 0.5  # the default voxel is two point spacings
_a, _b = 0.5, 0.3
TILT = np.array([[1, 0, 0], [0, np.cos(_a), -np.sin(_a)], [0, np.sin(_a), np.cos(_a)]]) @ np.array(
    [[np.cos(_b), 0, np.sin(_b)], [0, 1, 0], [-np.sin(_b), 0, np.cos(_b)]]
)  # a rotation that puts the plane at a generic angle to the grid


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def header(args: argparse.Namespace) -> dict:
    from benchdoc import machine, stamp

    doc = stamp("bench_accuracy", None, inputs="synthetic surfaces (tests/surfaces.py)", synthetic=True)
    doc["machine"] = machine()
    return doc


# ---- metric ------------------------------------------------------------------------------------


def metric_case(kind: str, scale: float, min_geo: float, seed: int = 0) -> dict:
    """Band distance vs geodesic on one surface whose size is ``scale`` default voxels."""
    from lodbuilder.datasets import folded_sheet
    from lodbuilder.sampling.band import band_distance

    rng = np.random.default_rng(seed)
    s = 1.0 / (scale / SPACING_PER_VOXEL)  # size 1, spacing so that 1 = scale voxels
    if kind == "plane":
        pts = plane_patch(1.0, s, rng) @ TILT.T  # not aligned with the grid
        src = int(np.argmin(np.linalg.norm(pts, axis=1)))
        geo = geodesic_plane(pts, src)
    elif kind == "sphere":
        pts = sphere_points(1.0, s, rng)
        src = 0
        geo = geodesic_sphere(pts, src, 1.0)
    elif kind == "cylinder":
        pts = cylinder_points(1.0, 4.0, s, rng)
        src = int(np.argmin(np.linalg.norm(pts - [1.0, 0.0, 2.0], axis=1)))
        geo = geodesic_cylinder(pts, src, 1.0)
    elif kind == "folded":
        # layers 10 voxels apart: far enough for the default band, a tight fold (radius 5 h)
        gap = 10.0 / scale
        n = int(round((2 + np.pi * gap / 2) * 1.0 / s**2))
        pts, _ = folded_sheet(n, seed=seed, length=1.0, width=1.0, gap=gap)
        pts = pts[np.lexsort(pts.T)]  # points in no particular order
        src = int(np.argmin(np.linalg.norm(pts - [0.3, 0.5, 0.0], axis=1)))
        geo = geodesic_folded(pts, src, gap, 1.0)
    else:
        raise ValueError(kind)
    t = time.perf_counter()
    d = band_distance(pts, [src])
    secs = time.perf_counter() - t
    from lodbuilder.sampling.band import choose_parameters

    h, r = choose_parameters(pts, None, None)
    keep = geo >= min_geo * h
    rel = (d[keep] - geo[keep]) / geo[keep]
    far = geo >= 0.5 * geo.max()
    return {
        "surface": kind,
        "n": int(len(pts)),
        "h": h,
        "r": r,
        "size_in_voxels": 1.0 / h,
        "points_compared": int(keep.sum()),
        "mean_abs_rel_error": float(np.abs(rel).mean()),
        "max_abs_rel_error": float(np.abs(rel).max()),
        "mean_rel_error": float(rel.mean()),
        "max_abs_error_voxels": float(np.abs(d[keep] - geo[keep]).max() / h),
        "mean_rel_error_far_half": float(((d[far] - geo[far]) / geo[far]).mean()),
        "seconds": secs,
    }


def section_metric(args) -> list[dict]:
    scales = [10, 20, 40] + ([80] if args.big else [])
    out = []
    for kind in ("plane", "sphere", "cylinder", "folded"):
        for sc in scales:
            log(f"metric {kind} R = {sc} h")
            out.append(metric_case(kind, sc, args.min_geo))
            log(f"  {json.dumps({k: out[-1][k] for k in ('mean_abs_rel_error', 'max_abs_rel_error')})}")
    return out


# ---- covering ----------------------------------------------------------------------------------


def rho_levels(top: float, spacing: float) -> list[float]:
    out = []
    rho = top
    while rho >= 3 * spacing:
        out.append(rho)
        rho /= math.sqrt(2)
    return out


def covering_case(n: int, gap: float, with_fps: bool, seed: int = 5) -> dict:
    from scipy.spatial import cKDTree

    import lodbuilder
    from lodbuilder.datasets import folded_sheet

    pts, _ = folded_sheet(n, seed=seed, length=1.0, width=1.0, gap=gap)
    spacing = math.sqrt((2 + math.pi * gap / 2) / n)
    uv = unfold_folded(pts, gap, 1.0)
    t = time.perf_counter()
    o = lodbuilder.fastfps(pts)
    secs = time.perf_counter() - t
    levels = []
    fps_order = None
    if with_fps:
        try:
            import fpsample

            fps_order = np.asarray(
                fpsample.bucket_fps_kdline_sampling(pts, n, h=7, start_idx=int(o.order[0])),
                dtype=np.int64,
            )
        except ImportError:
            fps_order = None
    for rho in rho_levels(0.24, spacing):
        k = o.size_for_rho(rho)
        geo = float(cKDTree(uv[o.order[:k]]).query(uv, k=1, workers=-1)[0].max())
        euc = float(cKDTree(pts[o.order[:k]]).query(pts, k=1, workers=-1)[0].max())
        lv = {"rho": rho, "size": k, "geodesic_cover": geo, "ratio": geo / rho, "euclidean_cover": euc}
        if fps_order is not None:
            g2 = float(cKDTree(uv[fps_order[:k]]).query(uv, k=1, workers=-1)[0].max())
            lv["fpsample_geodesic_cover"] = g2
            lv["fpsample_ratio"] = g2 / rho
        levels.append(lv)
    return {
        "n": n,
        "gap": gap,
        "spacing": spacing,
        "gap_in_spacings": gap / spacing,
        "h": o.voxel_size,
        "r": o.band_radius,
        "seconds": secs,
        "stats": {k: v for k, v in o.stats.items() if isinstance(v, (int, float, str))},
        "max_ratio": max(lv["ratio"] for lv in levels),
        "max_fpsample_ratio": max((lv.get("fpsample_ratio", 0.0) for lv in levels), default=None),
        "levels": levels,
    }


def section_covering(args) -> list[dict]:
    out = []
    for n, gap in ((200_000, 0.02), (400_000, 0.01)):
        log(f"covering folded sheet gap {gap}, {n} points")
        out.append(covering_case(n, gap, not args.no_fpsample))
        log(f"  max ratio {out[-1]['max_ratio']:.3f} ({out[-1]['seconds']:.1f} s)")
    return out


def section_limit(args) -> list[dict]:
    out = []
    n = args.limit_points
    for g in (2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 6.0, 8.0):
        # gap = g spacings; spacing = sqrt(area / n), area = 2 + pi gap / 2 (solve approximately)
        s = math.sqrt(2.0 / n)
        for _ in range(5):
            s = math.sqrt((2 + math.pi * g * s / 2) / n)
        log(f"limit: gap {g} spacings")
        res = covering_case(n, g * s, False)
        res.pop("levels")
        out.append(res)
        log(f"  max ratio {res['max_ratio']:.3f}")
    return out


def markdown(doc: dict) -> str:
    from benchdoc import measured

    lines = [
        f"{measured(doc)}. Inputs synthetic.",
    ]
    if doc.get("metric"):
        lines += [
            "",
            "Band distance from one sample against the exact geodesic, default parameters (h = 2 "
            "spacings); *size* is the sphere's or cylinder's radius, the plane's half-width or the "
            "folded sheet's length in voxels (its fold has a radius of 5 voxels); relative errors over "
            "every point at least one voxel away.",
            "",
            "| surface | size (voxels) | points | mean abs. rel. error | max abs. rel. error | mean signed | max abs. error (voxels) |",
            "|---|---|---|---|---|---|---|",
        ]
        for c in doc["metric"]:
            lines.append(
                f"| {c['surface']} | {c['size_in_voxels']:.0f} | {c['n']:,} | {100 * c['mean_abs_rel_error']:.2f} % | "
                f"{100 * c['max_abs_rel_error']:.2f} % | {100 * c['mean_rel_error']:+.2f} % | {c['max_abs_error_voxels']:.2f} |"
            )
    if doc.get("covering"):
        lines += [
            "",
            "A sheet folded over itself (two unit squares, random points), full default ordering: the "
            "geodesic covering radius of every level rho (measured along the sheet, exact by unfolding) "
            "divided by rho, and the same for Euclidean FPS (fpsample) at the same sizes.",
            "",
            "| gap | points | gap (spacings) | thin points | ordering s | max ratio | fpsample max ratio | ratio per level (rho: ratio / size) |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for c in doc["covering"]:
            per = ", ".join(f"{lv['rho']:.3g}: {lv['ratio']:.3f} / {lv['size']:,}" for lv in c["levels"])
            fps = c.get("max_fpsample_ratio")
            lines.append(
                f"| {c['gap']} | {c['n']:,} | {c['gap_in_spacings']:.1f} | {c['stats'].get('thin_points', 0):,} | "
                f"{c['seconds']:.1f} | {c['max_ratio']:.3f} | {'-' if not fps else f'{fps:.3f}'} | {per} |"
            )
    if doc.get("limit"):
        lines += [
            "",
            "The thinnest gap the defaults handle (100k points): the largest geodesic covering ratio "
            "over the levels, by gap in point spacings.",
            "",
            "| gap (spacings) | " + " | ".join(f"{c['gap_in_spacings']:.1f}" for c in doc["limit"]) + " |",
            "|---|" + "---|" * len(doc["limit"]),
            "| max ratio | " + " | ".join(f"{c['max_ratio']:.3f}" for c in doc["limit"]) + " |",
        ]
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sections", default="metric,covering,limit")
    ap.add_argument("--big", action="store_true", help="also R = 80 h in the metric section")
    ap.add_argument("--min-geo", type=float, default=1.0, help="compare points this many voxels away")
    ap.add_argument("--limit-points", type=int, default=100_000)
    ap.add_argument("--no-fpsample", action="store_true")
    ap.add_argument("--json", help="also write the JSON here")
    ap.add_argument("--markdown", help="write the 'accuracy' section of this markdown file")
    ap.add_argument("--from-json", help="only render --markdown from an earlier run's JSON")
    args = ap.parse_args()
    from benchdoc import finish, load_run, write_section

    if args.from_json:
        write_section(Path(args.markdown or ROOT / "docs" / "benchmarks.md"), "accuracy",
                      markdown(load_run(args.from_json)))
        return 0
    doc = header(args)
    t0 = time.perf_counter()
    for sec in args.sections.split(","):
        doc[sec] = {"metric": section_metric, "covering": section_covering, "limit": section_limit}[sec](args)
    doc["total_s"] = time.perf_counter() - t0
    finish(doc)
    text = json.dumps(doc, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    if args.markdown:
        write_section(Path(args.markdown), "accuracy", markdown(doc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
