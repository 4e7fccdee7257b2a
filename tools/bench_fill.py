"""Benchmark gap filling (issues 14, 21): holes punched in scans, their levels filled.

    python tools/bench_fill.py                               # both parts: 3 real scans, 1M sheet
    python tools/bench_fill.py --only real --scan ../shared/data/bun_zipper.ply --rho 0.002
    python tools/bench_fill.py --only synthetic --n 1000000 --markdown docs/benchmarks.md

Real part (issue 21): in a real scan, every point inside balls of radius 1.5-5 rho (holes 3-10 rho
wide; 10 per seed, 8 seeds: 80 per scan) is removed. Centres are random scan points where the scan
surrounds the ball all round (points in 8 sectors of the local plane up to 3 rho beyond the ball: a
hole of the scan's own can still lie beside it, or join it to the scan's border through a crack)
and at least 2 rho from another ball; nothing else is asked of the surface
(curved, steep and thin places included). The archive is built and its level at rho filled. A hole
is *found and filled* when synthetic points lie in its ball and the filled level covers its
removed points within 1.5 rho. Figures per scan: holes found and filled (%), the covering radius of
the ORIGINAL scan (before punching) by the unfilled and the filled level, and the distance of every
synthetic point over a ball's punched surface (within r + rho of its centre, over the original
surface: :func:`over_surface`) to the original surface (point to triangle, to the mesh when the PLY has
faces or triangle strips, else to the local plane of the 8 nearest original points): max, p95,
p99, mean, by depth in the hole. Synthetic points elsewhere (the scan's own holes, where the
original has no surface) are counted apart. Beside the fill, per hole, an *oracle*: the plane,
quadric and cubic fitted by least squares to the REMOVED points themselves, points placed on them
and measured the same way (:func:`oracle_errors`), and the bounds of tools/fill_bounds.py (the
truth read at rho resolution, the quartic through the hole's true points, rim polynomials): where
the truth at rho resolution meets 0.25 rho and no smooth fit does, the hole holds detail that its
rim does not show. Per scan, the filled holes over 0.25 rho by radius and sagitta.

Synthetic part: a *synthetic* wavy sheet of N random points (side 1) with round holes covering 1 %
of its area, ordered with lodbuilder.fastfps; time of ``fill_level`` at rho (warm, in process) and
of ``lodbuilder slice --rho R [--fill]`` (wall, process start included), the same coverage figures,
and the vertical distance of the synthetic points to the exact sheet.

Targets (issues 14, 21): >= 95 % of the holes found and filled; the filled level covers the
original scan within 1.5 rho; every synthetic point within 0.25 rho of the original surface;
filling a level of a 1M-point scan with 1 % of its area in holes <= 2 s.

Prints one JSON document (date, commit, command, load average); ``--markdown`` writes the 'fill'
section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from benchdoc import load_run, measured, publish, stamp, write_section
from fill_bounds import hole_distribution, near_mesh, refusal_bound, truth_errors
from scipy.spatial import cKDTree

HERE = Path(__file__).resolve().parent


# --- punching holes --------------------------------------------------------------------------


def surrounded(
    points: np.ndarray, tree: cKDTree, centre: np.ndarray, inner: float, outer: float
) -> bool:
    """The scan covers the annulus inner..outer around ``centre`` all round (8 sectors of its
    local plane), so a hole of radius ``inner`` there is enclosed by the scan: no border and no
    hole of the scan's own within it. Nothing else is asked of the surface (it may be curved,
    steep or thin: a ball through a thin part cuts a hole on either side)."""
    idx = tree.query_ball_point(centre, outer)
    near = points[idx]
    d = np.linalg.norm(near - centre, axis=1)
    ring = near[(d > inner) & (d <= outer)]
    if ring.shape[0] < 32:
        return False
    c = near - near.mean(axis=0)
    _, vec = np.linalg.eigh(c.T @ c)
    off = ring - centre
    ang = np.arctan2(off @ vec[:, 1], off @ vec[:, 2])
    sectors = np.floor((ang + np.pi) / (np.pi / 4)).astype(int) % 8
    return bool(np.unique(sectors).size == 8)


#: hole radii punched, in rho (holes 3-10 rho wide)
RADII = (1.5, 5.0)
#: least distance between two punched balls, in rho (neighbouring holes 2 rho apart occur)
GAP = 2.0


def punch(points: np.ndarray, rho: float, n_holes: int, seed: int, radii=RADII, apart: float = GAP):
    """(keep mask, centres, radii): every point within a ball of radius in ``radii`` x rho of a
    centre removed; centres at random scan points, at least ``apart`` rho apart (ball to ball; a
    negative ``apart`` lets balls overlap), each
    ball enclosed by the scan (:func:`surrounded`)."""
    rng = np.random.default_rng(seed)
    tree = cKDTree(points)
    centres: list[np.ndarray] = []
    rs: list[float] = []
    for i in rng.permutation(points.shape[0]):
        c = points[i]
        r = rho * rng.uniform(*radii)
        if any(
            np.linalg.norm(c - c2) < r + r2 + apart * rho
            for c2, r2 in zip(centres, rs, strict=True)
        ):
            continue
        if not surrounded(points, tree, c, r + 0.5 * rho, r + 3 * rho):
            continue
        centres.append(c)
        rs.append(r)
        if len(centres) == n_holes:
            break
    keep = np.ones(points.shape[0], dtype=bool)
    for c, r in zip(centres, rs, strict=True):
        keep[tree.query_ball_point(c, r)] = False
    return keep, np.array(centres), np.array(rs)


def punch_area(points_xy: np.ndarray, rho: float, fraction: float, seed: int, radii=(3.0, 5.0)):
    """Round holes in a unit square sheet until they cover ``fraction`` of its area."""
    rng = np.random.default_rng(seed)
    centres: list[np.ndarray] = []
    rs: list[float] = []
    area = 0.0
    while area < fraction:
        c = rng.uniform(0.1, 0.9, 2)
        r = rho * rng.uniform(*radii)
        if any(np.hypot(*(c - c2)) < r + r2 + 4 * rho for c2, r2 in zip(centres, rs, strict=True)):
            continue
        centres.append(c)
        rs.append(r)
        area += math.pi * r * r
    keep = np.ones(points_xy.shape[0], dtype=bool)
    for c, r in zip(centres, rs, strict=True):
        keep &= np.hypot(points_xy[:, 0] - c[0], points_xy[:, 1] - c[1]) > r
    return keep, np.array(centres), np.array(rs), area


# --- measuring -------------------------------------------------------------------------------


def surface_distance(query: np.ndarray, original: np.ndarray, faces: np.ndarray | None):
    """Distance of ``query`` points to the original surface: to the nearest point of the mesh's
    triangles when there are faces (point-cloud-utils), else to the plane of the 8 nearest
    original points."""
    if query.shape[0] == 0:
        return np.zeros(0), "none"
    if faces is not None:
        try:
            import point_cloud_utils as pcu

            d, _, _ = pcu.closest_points_on_mesh(
                np.ascontiguousarray(query, dtype=np.float64),
                np.ascontiguousarray(original, dtype=np.float64),
                np.ascontiguousarray(faces, dtype=np.int64),
            )
            return np.asarray(d), "mesh"
        except ImportError:
            pass
    _, nb = cKDTree(original).query(query, k=8)
    nbhd = original[nb]
    cen = nbhd.mean(axis=1)
    c = nbhd - cen[:, None, :]
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", c, c))
    return np.abs(np.einsum("ni,ni->n", query - cen, vec[:, :, 0])), "local plane of 8 points"


#: polynomial degrees of the oracle (:func:`oracle_errors`)
ORACLE = {"plane": 1, "quadric": 2, "cubic": 3}


def _poly(uv: np.ndarray, deg: int) -> np.ndarray:
    return np.column_stack(
        [uv[:, 0] ** (d - i) * uv[:, 1] ** i for d in range(deg + 1) for i in range(d + 1)]
    )


def oracle_errors(original, faces, normals, removed, centre_normal, rho) -> dict:
    """What no fill from the rim can beat: for each class of :data:`ORACLE`, the largest error
    (distance to the original surface, in rho) of points placed on the least-squares surface of
    that class fitted to the REMOVED points themselves (those of the hole's face: normal within
    72 degrees of the centre's), over their plane, at their own places (every removed point: more
    places than a fill's). No bound on a fill: one polynomial over a plane misses a surface that
    folds over it (a bunny hole: cubic 1.25 rho off, its fill 0.25); fill_bounds.truth_errors
    gives the bounds, at a fill's density."""
    same = np.abs(normals[removed] @ centre_normal) > 0.3
    x = original[removed[same]]
    if x.shape[0] < 10:
        return {}
    cen = x.mean(axis=0)
    _, vec = np.linalg.eigh((x - cen).T @ (x - cen))
    uv, h = (x - cen) @ vec[:, 1:] / rho, (x - cen) @ vec[:, 0] / rho
    out = {}
    for name, deg in ORACLE.items():
        a = _poly(uv, deg)
        fit = a @ np.linalg.lstsq(a, h, rcond=None)[0]
        placed = cen + rho * (uv @ vec[:, 1:].T + fit[:, None] * vec[:, 0])
        err, _ = surface_distance(placed, original, faces)
        out[f"oracle_{name}_max_rho"] = round(float(err.max() / rho), 3)
    return out


def over_surface(syn: np.ndarray, original: np.ndarray, normals: np.ndarray, rho: float):
    """Mask of the synthetic points ``syn`` over the original surface: within rho/2 of one of
    their 8 nearest original points along its tangent plane (``normals``: the original's unit
    normals), however far off that plane (the error is what is measured). A fill that reaches
    from a ball into the scan's own hole beside it puts points over surface the original does
    not have: their distance to the original (to the edge of its hole) is no error, and they
    are counted elsewhere."""
    if syn.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    k = min(8, original.shape[0])
    _, nb = cKDTree(original).query(syn, k=k)
    nb = np.asarray(nb).reshape(syn.shape[0], k)
    off = syn[:, None, :] - original[nb]
    n = normals[nb]
    along = off - np.einsum("nki,nki->nk", off, n)[:, :, None] * n
    return (np.einsum("nki,nki->nk", along, along) <= (0.5 * rho) ** 2).any(axis=1)


def pca_normals(points: np.ndarray, k: int = 10) -> np.ndarray:
    """Unit normals (unoriented) of the plane of each point's k nearest."""
    _, nb = cKDTree(points).query(points, k=k)
    c = points[nb] - points[nb].mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("nki,nkj->nij", c, c))[1][:, :, 0]


def coverage(original: np.ndarray, level_pts: np.ndarray, rho: float, masks: dict) -> dict:
    d = cKDTree(level_pts).query(original, workers=-1)[0] / rho
    out = {"all": round(float(d.max()), 3)}
    for name, m in masks.items():
        if m.any():
            out[name] = round(float(d[m].max()), 3)
    return out


def read_faces(path: Path) -> np.ndarray | None:
    if path.suffix.lower() != ".ply":
        return None
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    if "face" not in ply and "tristrips" not in ply:
        return None
    if "face" in ply:
        names = ply["face"].data.dtype.names
        key = "vertex_indices" if "vertex_indices" in names else names[0]
        rows = ply["face"].data[key]
        if not all(len(r) == 3 for r in rows[:1000]):
            return None
        return np.stack(rows).astype(np.int64)
    # triangle strips (igea.ply): one index list, strips separated by -1
    strips = np.concatenate([np.asarray(r, dtype=np.int64) for r in ply["tristrips"].data[0]])
    tris = []
    for strip in np.split(strips, np.flatnonzero(strips < 0)):
        strip = strip[strip >= 0]
        if strip.size >= 3:
            tris.append(np.stack([strip[:-2], strip[1:-1], strip[2:]], axis=1))
    if not tris:
        return None
    t = np.concatenate(tris)
    # (a strip's orientation alternates: irrelevant to distances) no degenerate triangles
    return t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]


def build(points: np.ndarray, attributes: dict, name: str, path: Path) -> float:
    import lodbuilder
    from lodbuilder.archive.writer import ScanRecord, update_archive
    from lodbuilder.io.base import Scan

    t = time.perf_counter()
    scan = Scan(points=points, attributes=attributes, name=name)
    update_archive(path, [ScanRecord(scan, lodbuilder.fastfps(points))], overwrite=True)
    return time.perf_counter() - t


def fill_times(path: Path, rho: float, repeat: int):
    import lodbuilder
    from lodbuilder.fill import fill_level, find_gaps

    with lodbuilder.open_archive(path) as arc:
        view = arc.scan()
        ts, tc, tg, tl = [], [], [], []
        for _ in range(repeat):
            t = time.perf_counter()
            view.level(rho=rho)
            tl.append(time.perf_counter() - t)
            t, c = time.perf_counter(), time.process_time()
            filled = fill_level(view, rho)
            ts.append(time.perf_counter() - t)
            tc.append(time.process_time() - c)
            t = time.perf_counter()
            find_gaps(view, rho)
            tg.append(time.perf_counter() - t)
        level = view.level(rho=rho, attributes=False)
    times = {
        "fill_level_s_min": round(min(ts), 3),
        "fill_level_s_median": round(statistics.median(ts), 3),
        # CPU time of the process (every thread: the k-d tree queries use both cores)
        "fill_level_cpu_s_min": round(min(tc), 3),
        "find_gaps_s_median": round(statistics.median(tg), 3),
        "plain_level_s_median": round(statistics.median(tl), 4),
    }
    return filled, level, times


def cli_wall(path: Path, rho: float, out: Path, fill: bool, repeat: int) -> float:
    exe = shutil.which("lodbuilder")
    cmd = [exe] if exe else [sys.executable, "-m", "lodbuilder.cli.main"]
    cmd += ["slice", str(path), "--rho", repr(rho), "-o", str(out)] + (["--fill"] if fill else [])
    ts = []
    for _ in range(repeat):
        out.unlink(missing_ok=True)
        t = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True)
        ts.append(time.perf_counter() - t)
        if r.returncode != 0:
            raise RuntimeError(r.stderr)
    return round(min(ts), 3)


def report_regions(filled) -> list[dict]:
    return [
        {
            "status": g.status,
            "area": g.area,
            "max_distance_rho": round(g.max_distance / g.rho, 3),
            "n_synthetic": g.n_synthetic,
            "residual_rho": round(g.residual / g.rho, 3),
            "reason": g.reason,
        }
        for g in filled.report.gaps
    ]


# --- the two parts ---------------------------------------------------------------------------


#: a hole is found and filled when synthetic points lie in it and the filled level covers its
#: removed points within this many rho
FOUND_COVER = 1.5

#: depth bins (distance of a synthetic point to the punched scan, in rho) for its error
DEPTHS = ((0.0, 1.5), (1.5, 2.5), (2.5, 3.5), (3.5, 99.0))


def real_part(
    scan_path: Path,
    rho: float,
    n_holes: int,
    seeds: list[int],
    work: Path,
    repeat: int,
    radii_rho: tuple[float, float] = RADII,
    apart: float = GAP,
) -> dict:
    from lodbuilder.io import read_scan

    scan = read_scan(scan_path)
    original = scan.points
    faces = read_faces(scan_path)
    normals = pca_normals(original)
    tree = cKDTree(original)
    runs = []
    errors = []  # of the synthetic points in the punched balls, every seed
    depths = []  # their distance to the punched scan, in rho
    for seed in seeds:
        keep, centres, radii = punch(original, rho, n_holes, seed, radii_rho, apart)
        # the archive depends on the punch only: a --workdir keeps it for the next run
        tag = f"{rho:g}_{n_holes}_{seed}" + (
            ""
            if (radii_rho, apart) == (RADII, GAP)
            else f"_{radii_rho[0]:g}-{radii_rho[1]:g}_{apart:g}"
        )
        path = work / f"real_{scan_path.stem}_{tag}.h5"
        attrs = {k: v[keep] for k, v in scan.attributes.items()}
        t_build = None if path.exists() else build(original[keep], attrs, scan.name, path)
        filled, level, times = fill_times(path, rho, repeat)
        lev = filled.level
        syn = lev.points[lev.attributes["synthetic"] == 1]
        in_ball = np.zeros(syn.shape[0], dtype=bool)
        holes = np.zeros(original.shape[0], dtype=bool)
        per_hole = []
        for c, r in zip(centres, radii, strict=True):
            in_ball |= np.linalg.norm(syn - c, axis=1) < r + rho
            holes |= np.linalg.norm(original - c, axis=1) < r
        punched = over_surface(syn, original, normals, rho)
        n_beside = int((in_ball & ~punched).sum())
        in_ball &= punched
        err, how = surface_distance(syn, original, faces)
        err = err / rho
        errors.append(err[in_ball])
        # how deep in its hole each synthetic point lies: distance to the nearest point left
        depth = cKDTree(original[keep]).query(syn[in_ball])[0] / rho
        depths.append(depth)
        cov_un = coverage(original, level.points, rho, {"punched": holes})
        cov_f = coverage(original, lev.points, rho, {"punched": holes})
        for c, r in zip(centres, radii, strict=True):
            m = np.linalg.norm(original - c, axis=1) < r
            s = (np.linalg.norm(syn - c, axis=1) < r + rho) & punched
            nc = normals[np.argmin(np.linalg.norm(original - c, axis=1))]
            cover = coverage(original[m], lev.points, rho, {})["all"]
            part = near_mesh(original, faces, c, r + 8 * rho)
            per_hole.append(
                {
                    "radius_rho": round(float(r / rho), 2),
                    "cover_unfilled_rho": coverage(original[m], level.points, rho, {})["all"],
                    "cover_filled_rho": cover,
                    "n_synthetic": int(s.sum()),
                    "synthetic_error_max_rho": round(float(err[s].max()), 3) if s.any() else None,
                    # found and filled: synthetic points in it, its surface covered within 1.5 rho
                    "filled": bool(s.any() and cover <= FOUND_COVER),
                    **oracle_errors(original, faces, normals, np.flatnonzero(m), nc, rho),
                    **hole_fit(filled.report, c, r, rho),
                    **truth_errors(
                        original,
                        keep,
                        normals,
                        c,
                        r,
                        rho,
                        lambda q, part=part: surface_distance(q, *part)[0],
                        tree,
                    ),
                }
            )
        runs.append(
            {
                "seed": seed,
                "removed_points": int((~keep).sum()),
                "hole_radii_rho": [round(float(r / rho), 2) for r in radii],
                "build_s": None if t_build is None else round(t_build, 2),
                "level_size": level.size,
                "n_synthetic": int(syn.shape[0]),
                "n_synthetic_in_punched_balls": int(in_ball.sum()),
                # within a ball's reach but over the scan's own hole beside it: counted elsewhere
                "n_synthetic_beside_punched_balls": n_beside,
                "cover_original_unfilled_rho": cov_un,
                "cover_original_filled_rho": cov_f,
                "synthetic_error_in_balls_rho": {
                    "max": round(float(err[in_ball].max()), 3) if in_ball.any() else None,
                    "p99": round(float(np.percentile(err[in_ball], 99)), 3)
                    if in_ball.any()
                    else None,
                    "mean": round(float(err[in_ball].mean()), 3) if in_ball.any() else None,
                    "share_within_0.25": round(float((err[in_ball] <= 0.25).mean()), 3)
                    if in_ball.any()
                    else None,
                },
                "synthetic_error_elsewhere_rho": {
                    "max": round(float(err[~in_ball].max()), 3) if (~in_ball).any() else None,
                    "note": "the scan's own holes (beside a ball too: farther than rho from every "
                    "removed point): the original has no surface there",
                },
                "error_measured_to": how,
                "holes": per_hole,
                "gaps": report_regions(filled),
                **times,
            }
        )
        print(json.dumps({"real": scan_path.name, **runs[-1]}), file=sys.stderr, flush=True)
    e, dep = np.concatenate(errors), np.concatenate(depths)
    holes = [h for run in runs for h in run["holes"]]
    every = {
        "n": int(e.size),
        "max": round(float(e.max()), 3) if e.size else None,
        "p95": round(float(np.percentile(e, 95)), 3) if e.size else None,
        "p99": round(float(np.percentile(e, 99)), 3) if e.size else None,
        "mean": round(float(e.mean()), 3) if e.size else None,
        "share_within_0.25": round(float((e <= 0.25).mean()), 3) if e.size else None,
        # the error grows with the depth in the hole (distance to the nearest point left)
        "max_by_depth": {
            f"{lo:g}-{hi:g} rho": round(float(e[(dep >= lo) & (dep < hi)].max()), 3)
            for lo, hi in DEPTHS
            if ((dep >= lo) & (dep < hi)).any()
        },
    }
    n_filled = sum(h["filled"] for h in holes)
    return {
        "scan": scan_path.name,
        "n_points": int(original.shape[0]),
        "rho": rho,
        "holes": len(holes),
        "holes_filled": n_filled,
        "holes_filled_percent": round(100.0 * n_filled / max(len(holes), 1), 1),
        "cover_original_filled_rho_max": max(r["cover_original_filled_rho"]["all"] for r in runs),
        "cover_original_unfilled_rho_max": max(
            r["cover_original_unfilled_rho"]["all"] for r in runs
        ),
        "synthetic_error_in_balls_every_seed_rho": every,
        "oracle": oracle_summary(holes),
        "refusing_by_fit_residual": refusal_tradeoff(holes),
        "holes_over_0.25": hole_distribution(holes),
        "refusal_bound": refusal_bound(holes),
        "runs": runs,
    }


def hole_fit(report, centre: np.ndarray, radius: float, rho: float) -> dict:
    """How the hole was filled: the surface of the filled gap with the most synthetic points
    within ``radius + rho`` of its ``centre`` (a height field's spline, or ``implicit``) and
    its cross-validated residual (the fit predicting the inner ring of each sixth of the ring
    from the other five, RMS, in rho)."""
    best, most = None, 0
    for g in report.gaps:
        n = int((np.linalg.norm(g.candidates - centre, axis=1) < radius + rho).sum())
        if g.n_synthetic and n > most:
            best, most = g, n
    if best is None:
        return {}
    fit = "implicit" if best.implicit else best.surface.kernel
    return {"fit": fit, "fit_residual_rho": round(float(best.residual / rho), 3)}


#: residual thresholds (rho) of :func:`refusal_tradeoff`
REFUSE_AT = (0.1, 0.15, 0.2, 0.25)


def refusal_tradeoff(holes: list[dict]) -> dict:
    """What refusing every hole whose fit residual exceeds a threshold would give: the share
    of all holes still filled and the largest synthetic error of those (in rho)."""
    out = {}
    for t in REFUSE_AT:
        kept = [
            h
            for h in holes
            if h["filled"] and h.get("fit_residual_rho") is not None and h["fit_residual_rho"] <= t
        ]
        errs = [h["synthetic_error_max_rho"] for h in kept]
        out[f"{t:g}"] = {
            "holes_filled_percent": round(100.0 * len(kept) / max(len(holes), 1), 1),
            "synthetic_error_max_rho": max(errs) if errs else None,
        }
    return out


def oracle_summary(holes: list[dict]) -> dict:
    """Per class of :data:`ORACLE` and for the fill: the share of the holes whose largest error
    is within 0.25 rho (of the filled holes, for the fill), and the largest error."""
    out = {}
    for name in [*ORACLE, "fill"]:
        key = "synthetic_error_max_rho" if name == "fill" else f"oracle_{name}_max_rho"
        v = [h[key] for h in holes if h.get(key) is not None]
        if v:
            out[name] = {
                "holes": len(v),
                "share_within_0.25": round(sum(x <= 0.25 for x in v) / len(v), 3),
                "max": max(v),
            }
    return out


def synthetic_part(
    n: int, spacings: float, fraction: float, seed: int, work: Path, repeat: int
) -> dict:
    from lodbuilder.datasets import wavy_sheet

    pts, _ = wavy_sheet(n, seed=seed)
    rho = spacings / math.sqrt(n)
    keep, centres, radii, area = punch_area(pts[:, :2], rho, fraction, seed + 1)
    path = work / f"synthetic_{n}_{seed}_{spacings:g}.h5"
    rng = np.random.default_rng(seed)
    attrs = {
        "intensity": rng.random(int(keep.sum())).astype(np.float32),
        "red": np.round(255 * pts[keep, 0]).astype(np.uint8),
    }
    t_build = build(pts[keep], attrs, f"wavy{n}", path) if not path.exists() else None
    filled, level, times = fill_times(path, rho, repeat)
    lev = filled.level
    syn = lev.points[lev.attributes["synthetic"] == 1]
    k = 2 * np.pi * 2.0
    exact = 0.08 * np.sin(k * syn[:, 0]) * np.cos(k * syn[:, 1])
    holes = np.zeros(n, dtype=bool)
    for c, r in zip(centres, radii, strict=True):
        holes |= np.hypot(pts[:, 0] - c[0], pts[:, 1] - c[1]) < r
    return {
        "surface": "synthetic wavy sheet z = 0.08 sin(4 pi x) cos(4 pi y), random points",
        "n_points": n,
        "rho": rho,
        "rho_in_spacings": spacings,
        "holes": len(radii),
        "hole_radii_rho": [round(float(r / rho), 2) for r in radii],
        "hole_area_fraction": round(area, 4),
        "build_s": None if t_build is None else round(t_build, 1),
        "level_size": level.size,
        "n_synthetic": int(syn.shape[0]),
        "cover_original_unfilled_rho": coverage(pts, level.points, rho, {"holes": holes}),
        "cover_original_filled_rho": coverage(pts, lev.points, rho, {"holes": holes}),
        "synthetic_vertical_error_max_rho": round(float(np.abs(syn[:, 2] - exact).max() / rho), 4)
        if syn.size
        else None,
        "gaps": report_regions(filled),
        **times,
        "cli_slice_wall_s": cli_wall(path, rho, work / "out.npy", False, 2),
        "cli_slice_fill_wall_s": cli_wall(path, rho, work / "out.npy", True, 2),
    }


#: the bounds of fill_bounds.refusal_bound, as the page names them
BOUND_NAMES = {
    "truth_local": "truth at rho resolution (quadric through the original within 1.5 rho)",
    "truth_quartic": "quartic through the hole's true points",
    "rim_best": "best rim polynomial (rims 1-4 rho, degree 2-4) chosen knowing the truth",
    "rim_cv": "the rim polynomial chosen by sector cross-validation",
}


def markdown(result: dict) -> str:
    lines = [
        f"{measured(result)} (2 shared cores: times carry noise).",
        "",
    ]
    for real in result.get("real", []):
        radii = [r for run in real["runs"] for r in run["hole_radii_rho"]]
        lines += [
            f"**Real scan {real['scan']}** ({real['n_points']:,} points), rho = {real['rho']:g} "
            f"(error measured to the {real['runs'][0]['error_measured_to']}): "
            f"every point inside {len(radii)} balls of radius {min(radii):g}-{max(radii):g} rho "
            "removed, the archive built, the level at "
            "rho filled. Covering radius of the ORIGINAL scan (in rho; 'punched' = the removed "
            "points) and distance of the synthetic points to the original surface (in rho).",
            "",
            "| seed | hole radii (rho) | level | synthetic (in balls) | cover unfilled all / punched | "
            "cover filled all / punched | synthetic error in balls max / p99 / mean / share <= 0.25 | "
            "fill s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in real["runs"]:
            cu, cf = r["cover_original_unfilled_rho"], r["cover_original_filled_rho"]
            e = r["synthetic_error_in_balls_rho"]
            lines.append(
                f"| {r['seed']} | {', '.join(f'{x:g}' for x in r['hole_radii_rho'])} | "
                f"{r['level_size']:,} | {r['n_synthetic']} ({r['n_synthetic_in_punched_balls']}) | "
                f"{cu['all']} / {cu.get('punched', '-')} | {cf['all']} / {cf.get('punched', '-')} | "
                f"{e['max']} / {e.get('p99', '-')} / {e['mean']} / {e.get('share_within_0.25', '-')} | "
                f"{r['fill_level_s_median']} |"
            )
        every = real.get("synthetic_error_in_balls_every_seed_rho")
        if every:
            lines += [
                "",
                f"Every seed: {real['holes_filled']} of {real['holes']} holes found and filled "
                f"({real['holes_filled_percent']} %); filled level covers the original within "
                f"{real['cover_original_filled_rho_max']} rho; "
                f"{every['n']} synthetic points in the balls, error max {every['max']} / "
                f"p95 {every['p95']} / p99 {every['p99']} / mean {every['mean']} rho, "
                f"{every['share_within_0.25']} of "
                "them within 0.25 rho; largest error by depth in the hole (distance to the nearest "
                "point left): "
                + ", ".join(f"{k} {v}" for k, v in every.get("max_by_depth", {}).items())
                + ".",
            ]
        oracle = real.get("oracle")
        if oracle:
            lines += [
                "",
                "Oracle (the least-squares surface of each class fitted to the removed points "
                "themselves, points placed on it at every removed point; a fill beats it where "
                "the surface folds over the hole's plane): holes within 0.25 rho / largest "
                "error: "
                + ", ".join(
                    f"{k} {100 * v['share_within_0.25']:.0f} % / {v['max']}"
                    for k, v in oracle.items()
                )
                + ".",
            ]
        trade = real.get("refusing_by_fit_residual")
        if trade:
            lines += [
                "",
                "Refusing the holes whose fit residual (cross-validated on the ring, RMS) exceeds "
                "t rho would leave, t: holes filled / largest synthetic error: "
                + ", ".join(
                    f"{k}: {v['holes_filled_percent']} % / {v['synthetic_error_max_rho']}"
                    for k, v in trade.items()
                )
                + ".",
            ]
        dist, bound = real.get("holes_over_0.25"), real.get("refusal_bound")
        if dist and bound:
            lines += [
                "",
                f"Filled holes missed by more than 0.25 rho: {dist['all']['over_0.25']} of "
                f"{dist['all']['filled']}; by radius: "
                + ", ".join(
                    f"{k} {v['over_0.25']} of {v['filled']}" for k, v in dist["by_radius"].items()
                )
                + "; by sagitta (plane oracle's error): "
                + ", ".join(
                    f"{k} {v['over_0.25']} of {v['filled']}" for k, v in dist["by_sagitta"].items()
                )
                + f". A rule refusing exactly those would keep {bound['holes_kept_percent']} % of "
                "the holes. Holes over 0.25 rho / largest error at points thinned to rho/2 (of "
                "every hole): "
                + ", ".join(
                    f"{BOUND_NAMES[k]} {v['over']} of {v['holes']} / {v['max']}"
                    for k, v in bound["over_0.25"].items()
                )
                + ".",
            ]
        lines.append("")
    syn = result.get("synthetic") or []
    if isinstance(syn, dict):
        syn = [syn]
    if syn:
        s0 = syn[0]
        lines += [
            f"**Synthetic** {s0['surface']}, {s0['n_points']:,} points, round holes of 3-5 rho "
            f"covering about {100 * s0['hole_area_fraction']:.1f} % of the area; fill_level in "
            "process (warm), `lodbuilder slice` wall time (process start included).",
            "",
            "| rho (spacings) | holes (rho) | level + synthetic | fill_level s (min / median; "
            "CPU min) | "
            "find_gaps s | plain level s | slice wall s | slice --fill wall s | "
            "cover unfilled / filled, holes (rho) | synthetic error (rho) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for s in syn:
            lines.append(
                f"| {s['rho']:.4g} ({s['rho_in_spacings']:g}) | "
                f"{', '.join(f'{x:g}' for x in s['hole_radii_rho'])} | "
                f"{s['level_size']:,} + {s['n_synthetic']} | {s['fill_level_s_min']} / "
                f"{s['fill_level_s_median']}; {s.get('fill_level_cpu_s_min', '-')} | "
                f"{s['find_gaps_s_median']} | "
                f"{s['plain_level_s_median']} | {s['cli_slice_wall_s']} | "
                f"{s['cli_slice_fill_wall_s']} | {s['cover_original_unfilled_rho'].get('holes')} / "
                f"{s['cover_original_filled_rho'].get('holes')} | "
                f"{s['synthetic_vertical_error_max_rho']} |"
            )
        lines.append("")
    lines.append(
        "Targets (issues 14, 21): >= 95 % of the holes found and filled; filled covers the "
        "original within 1.5 rho (unfilled >= 3 rho); synthetic points within 0.25 rho of the "
        "original surface; fill of a 1M-point level with 1 % of its area in holes <= 2 s."
    )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=("real", "synthetic"))
    data = HERE.parent.parent / "shared" / "data"
    p.add_argument(
        "--scan",
        nargs="+",
        default=[str(data / n) for n in ("bun_zipper.ply", "igea.ply", "frag_115.ply")],
    )
    p.add_argument(
        "--rho", type=float, nargs="+", default=[0.002, 0.003, 0.012], help="rho per --scan"
    )
    p.add_argument("--holes", type=int, default=10, help="holes per seed")
    p.add_argument(
        "--radii", type=float, nargs=2, default=list(RADII), help="hole radii range, in rho"
    )
    p.add_argument(
        "--apart",
        type=float,
        default=GAP,
        help="least ball-to-ball distance, in rho (< 0: overlap)",
    )
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6, 7, 8])
    p.add_argument("--n", type=int, default=1_000_000, help="synthetic sheet size")
    p.add_argument(
        "--spacings",
        type=float,
        nargs="+",
        default=[8.0, 4.0],
        help="synthetic rho in point spacings (one run each)",
    )
    p.add_argument("--fraction", type=float, default=0.01, help="synthetic hole area fraction")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--workdir", help="keep the archives here (default: a temporary directory)")
    p.add_argument("--markdown", help="update the 'fill' section of this file")
    p.add_argument("--from-json", help="re-render a saved JSON result into --markdown")
    args = p.parse_args(argv)
    if args.from_json:
        result = load_run(args.from_json)
        if args.markdown:
            write_section(Path(args.markdown), "fill", markdown(result))
        return 0
    if len(args.rho) not in (1, len(args.scan)):
        p.error("give one --rho, or one per --scan")
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_fill_"))
    work.mkdir(parents=True, exist_ok=True)
    inputs = []
    if args.only in (None, "real"):
        inputs.append(f"real scans {', '.join(Path(s).name for s in args.scan)}, holes punched")
    if args.only in (None, "synthetic"):
        inputs.append(f"a synthetic wavy sheet of {args.n:,} points with round holes")
    result = stamp("bench_fill", argv, inputs="; ".join(inputs), synthetic=args.only != "real")
    try:
        if args.only in (None, "real"):
            rhos = args.rho * len(args.scan) if len(args.rho) == 1 else args.rho
            result["real"] = [
                real_part(
                    Path(s),
                    r,
                    args.holes,
                    args.seeds,
                    work,
                    args.repeat,
                    tuple(args.radii),
                    args.apart,
                )
                for s, r in zip(args.scan, rhos, strict=True)
            ]
        if args.only in (None, "synthetic"):
            result["synthetic"] = [
                synthetic_part(args.n, sp, args.fraction, 0, work, args.repeat)
                for sp in args.spacings
            ]
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    publish(result, section="fill", render=markdown, markdown=args.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
