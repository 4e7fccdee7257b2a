"""Benchmark lodbuilder against the simplifiers people already use, on the same inputs in one run.

Methods (each gives levels of 1 %, 5 % and 10 % of the input's points):

* ``random``: uniform random subset (NumPy).
* ``voxel``: voxel-grid subsampling, one point per occupied voxel (the point nearest the voxel's
  centre, so the level is a subset); the voxel size is bisected to hit the target size (+-1 %).
* ``fpsample``: Euclidean FPS, ``fpsample.bucket_fps_kdline_sampling(pts, k, h=7)``, per level.
* ``poisson``: ``point_cloud_utils.downsample_point_cloud_poisson_disk`` with a target size.
* ``open3d_fps``: ``open3d`` ``farthest_point_down_sample`` when open3d is importable.
* ``lodbuilder``: one full band-geodesic FastFPS ordering (``lodbuilder.fastfps``); a level is a
  prefix. Its time is the ordering's, once for every level; slicing a level is reported apart.
* ``lodbuilder_weighted``: curvature-weighted ordering (surface variation, k=16, adaptivity 0.8,
  ``lodbuilder.sampling.adaptive.build_orderings``), timed with the map; a level is a prefix.

Metrics per level (:func:`lodbuilder.quality.evaluate_level`): covering radius (and, for
lodbuilder, whether it meets the archive's claimed rho), two-sided Hausdorff, Chamfer, minimum
spacing, uniformity, point-to-plane error; on the folded sheet also the geodesic covering radius
(exact: the sheet unfolds to a flat rectangle).

Inputs: igea, frag_115, bun_zipper, bun000 (a raw range scan), the 10 bunny range scans merged
with their poses (``bunny_posed``) from ../shared/data, a synthetic
wavy scan (``--synthetic-points``, default 200k; ``--big`` makes it 1M) and a sheet folded over
itself with its layers 0.02 (``folded``) and 0.01 (``folded_thin``) apart.

    python tools/bench_peers.py [--big] [--only igea,folded] [--markdown docs/benchmarks.md]
                                [--json OUT.json] > results.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

import numpy as np
from benchdoc import load_run, write_section
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
FRACTIONS = (0.01, 0.05, 0.10)
REAL = {
    "igea": "igea.ply",
    "frag_115": "frag_115.ply",
    "bun_zipper": "bun_zipper.ply",
    "bun000": "bun000.ply",
}
FOLD = {"length": 1.0, "width": 0.6}
GAPS = {"folded": 0.02, "folded_thin": 0.01}
ADAPTIVITY = 0.8


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# ---- inputs --------------------------------------------------------------------------------


def load_inputs(args) -> dict[str, dict]:
    from lodbuilder.datasets import folded_sheet, wavy_sheet
    from lodbuilder.io import read_scan

    wanted = set(args.only.split(",")) if args.only else None
    out: dict[str, dict] = {}
    for name, fn in REAL.items():
        if wanted and name not in wanted:
            continue
        path = DATA / fn
        if not path.exists():
            log(f"skip {name}: {path} not found")
            continue
        out[name] = {"points": read_scan(path).points, "source": fn, "kind": "real scan"}
    if not wanted or "bunny_posed" in wanted:
        from lodbuilder.build.inputs import expand_inputs
        from lodbuilder.io.pose import apply_pose

        conf = DATA / "bun.conf"
        if conf.exists():
            parts = [apply_pose(read_scan(s.path).points, s.pose) for s in expand_inputs(manifest=conf)]
            out["bunny_posed"] = {
                "points": np.vstack(parts),
                "source": "the 10 bunny range scans merged with their bun.conf poses",
                "kind": "real scans, merged (overlapping registrations)",
            }
    n_syn = 1_000_000 if args.big else args.synthetic_points
    if not wanted or "synthetic" in wanted:
        pts, _ = wavy_sheet(n_syn, seed=3, noise=0.0005)
        out["synthetic"] = {
            "points": pts,
            "source": f"wavy_sheet({n_syn}, seed=3, noise=0.0005)",
            "kind": "synthetic",
        }
    for name, gap in GAPS.items():
        if wanted and name not in wanted:
            continue
        pts, _ = folded_sheet(args.folded_points, seed=5, gap=gap, **FOLD)
        out[name] = {
            "points": pts,
            "source": f"folded_sheet({args.folded_points}, seed=5, gap={gap})",
            "kind": f"synthetic, sheet folded over itself, layers {gap} apart",
            "unfolded": unfold(pts, gap),
        }
    return out


def unfold(pts: np.ndarray, gap: float) -> np.ndarray:
    """(N, 2) coordinates of the folded sheet laid flat: geodesic distance = Euclidean there."""
    length = FOLD["length"]
    r = gap / 2
    arc = math.pi * r
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    s = np.where(z < r, x, length + arc + (length - x))
    mid = x > length
    t = np.arctan2(x[mid] - length, r - z[mid])
    s[mid] = length + r * t
    return np.column_stack([s, y])


# ---- methods -------------------------------------------------------------------------------


def m_random(pts, sizes, ctx):
    rng = np.random.default_rng(0)
    for k in sizes:
        t = time.perf_counter()
        idx = rng.choice(pts.shape[0], size=k, replace=False)
        yield k, idx, time.perf_counter() - t, None, {}


def voxel_subsample(pts: np.ndarray, h: float) -> np.ndarray:
    lo = pts.min(axis=0)
    q = np.floor((pts - lo) / h).astype(np.int64)
    centre = lo + (q + 0.5) * h
    d = ((pts - centre) ** 2).sum(axis=1)
    dims = q.max(axis=0) + 1
    key = (q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2]
    order = np.lexsort((d, key))
    first = np.ones(order.size, dtype=bool)
    first[1:] = key[order[1:]] != key[order[:-1]]
    return order[first]


def m_voxel(pts, sizes, ctx):
    diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
    for k in sizes:
        t = time.perf_counter()
        lo, hi = diag * 1e-6, diag
        best, best_h = voxel_subsample(pts, hi), hi
        for _ in range(60):
            h = math.sqrt(lo * hi)
            idx = voxel_subsample(pts, h)
            if abs(idx.size - k) < abs(best.size - k):
                best, best_h = idx, h
            if abs(idx.size - k) <= 0.01 * k or hi / lo < 1.0001:
                break
            if idx.size > k:
                lo = h
            else:
                hi = h
        yield k, best, time.perf_counter() - t, None, {"voxel_size": best_h}


def m_fpsample(pts, sizes, ctx):
    import fpsample

    for k in sizes:
        t = time.perf_counter()
        idx = fpsample.bucket_fps_kdline_sampling(pts, k, h=7, start_idx=ctx["seed"])
        yield k, np.asarray(idx, dtype=np.int64), time.perf_counter() - t, None, {}


def m_poisson(pts, sizes, ctx):
    import point_cloud_utils as pcu

    for k in sizes:
        t = time.perf_counter()
        idx = pcu.downsample_point_cloud_poisson_disk(
            pts, -1.0, target_num_samples=k, random_seed=1
        )
        yield k, np.asarray(idx, dtype=np.int64), time.perf_counter() - t, None, {}


def m_open3d(pts, sizes, ctx):
    import open3d as o3d  # noqa: F401  (ImportError -> skipped)

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    tree = cKDTree(pts)
    for k in sizes:
        t = time.perf_counter()
        sub = pcd.farthest_point_down_sample(k)
        dt_ = time.perf_counter() - t
        _, idx = tree.query(np.asarray(sub.points), k=1)
        yield k, np.asarray(idx, dtype=np.int64), dt_, None, {}


def _prefix_levels(ordering, sizes, order_s, extra):
    for k in sizes:
        t = time.perf_counter()
        idx = ordering.order[:k].copy()
        slice_s = time.perf_counter() - t
        claim = float(ordering.radius[k]) if k < len(ordering) else 0.0
        yield k, idx, order_s, claim, extra | {"slice_s": slice_s, "order_once": True}


def m_lodbuilder(pts, sizes, ctx):
    import lodbuilder

    t = time.perf_counter()
    o = lodbuilder.fastfps(pts)
    order_s = time.perf_counter() - t
    stats = {k: o.stats[k] for k in ("engine", "band_voxels", "pops") if k in o.stats}
    yield from _prefix_levels(o, sizes, order_s, {"engine": stats})


def m_lodbuilder_weighted(pts, sizes, ctx):
    from lodbuilder.features import surface_variation
    from lodbuilder.sampling.adaptive import build_orderings

    t = time.perf_counter()
    sv, params = surface_variation(pts, k=16)
    maps_s = time.perf_counter() - t
    o = build_orderings(pts, {"curvature": (sv, params)}, ADAPTIVITY, None)["weighted"]
    order_s = time.perf_counter() - t
    # weighted radii are not Euclidean covering radii: no rho is claimed
    for k, idx, s, _, extra in _prefix_levels(o, sizes, order_s, {"maps_s": maps_s}):
        yield k, idx, s, None, extra | {"adaptivity": ADAPTIVITY}


METHODS = {
    "random": m_random,
    "voxel": m_voxel,
    "fpsample": m_fpsample,
    "poisson": m_poisson,
    "open3d_fps": m_open3d,
    "lodbuilder": m_lodbuilder,
    "lodbuilder_weighted": m_lodbuilder_weighted,
}


# ---- run -----------------------------------------------------------------------------------


def run_input(name, inp, methods):
    from lodbuilder.quality import evaluate_level
    from lodbuilder.sampling.fastfps import default_seed

    pts = np.ascontiguousarray(inp["points"], dtype=np.float64)
    n = pts.shape[0]
    sizes = [max(1, int(round(f * n))) for f in FRACTIONS]
    tree = cKDTree(pts)
    ctx = {"seed": default_seed(pts)}
    unfolded = inp.get("unfolded")
    nn = tree.query(pts[:: max(1, n // 20000)], k=2, workers=-1)[0][:, 1]
    res = {
        "source": inp["source"],
        "kind": inp["kind"],
        "n_points": n,
        "diagonal": float(np.linalg.norm(np.ptp(pts, axis=0))),
        "median_nn_spacing": float(np.median(nn)),
        "sizes": sizes,
        "methods": {},
    }
    for mname in methods:
        log(f"{name} ({n:,} points): {mname}")
        try:
            levels = []
            for k, idx, secs, claim, extra in METHODS[mname](pts, sizes, ctx):
                rep = evaluate_level(pts, pts[idx], rho=claim, input_tree=tree).as_dict()
                rep.update(target_size=k, seconds=secs, eval_seconds=rep.pop("seconds"))
                rep.update(extra)
                if unfolded is not None:
                    u = unfolded
                    rep["geodesic_covering_radius"] = float(
                        cKDTree(u[idx]).query(u, k=1, workers=-1)[0].max()
                    )
                levels.append(rep)
            res["methods"][mname] = {"levels": levels}
        except ImportError as exc:
            log(f"  skipped: {exc}")
            res["methods"][mname] = {"skipped": f"not installed: {exc.name or exc}"}
        except Exception as exc:  # a peer failing on an input is a result, not a crash
            log(f"  failed: {exc!r}")
            res["methods"][mname] = {"failed": repr(exc)[:300]}
    return res


def machine() -> dict:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    vers = {}
    for pkg in ("numpy", "scipy", "numba", "fpsample", "point-cloud-utils", "open3d", "lodbuilder"):
        try:
            vers[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            vers[pkg] = None
    try:
        commit = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=False,
        ).stdout.strip()
    except OSError:
        commit = ""
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError):
        mem = None
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gib": round(mem, 1) if mem else None,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "versions": vers,
        "git_commit": commit,
        "load_average_at_start": os.getloadavg(),
    }


# ---- markdown ------------------------------------------------------------------------------


def _g(v, digits=3):
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "**NO**"
    if v == 0:
        return "0"
    return f"{v:.{digits}g}"


def markdown(doc: dict) -> str:
    m = doc["machine"]
    v = m["versions"]
    lines = [
        f"Measured {doc['date']} by `python tools/bench_peers.py{doc['flags']}` "
        f"(commit {m['git_commit'] or '?'}); the run took {doc['total_s']:.0f} s.",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores, {m['memory_gib']} GiB, {m['platform']}, "
        f"Python {m['python']}; load average at start {', '.join(f'{x:.1f}' for x in m['load_average_at_start'])} "
        "(the machine was shared with other work, so times carry noise).",
        "Versions: "
        + ", ".join(f"{k} {val}" for k, val in v.items() if val)
        + "; not installed: "
        + (", ".join(k for k, val in v.items() if not val) or "none")
        + ".",
        "",
        "How to read the tables:",
        "",
        "- Every level is a subset of the input. *time* is the time to produce that level. lodbuilder "
        "computes one ordering for all levels: its *time* is that ordering (once, shared by every "
        "level; *slice* is the time to cut a level from it); the peers recompute every level.",
        "- *cover* is the covering radius (largest distance from an input point to the level), "
        "*rho ok* whether it is within the density the lodbuilder level claims (the weighted "
        "ordering's radii are not Euclidean, so it claims none), *Hausdorff* the two-sided "
        "Hausdorff distance (equal to cover for subsets), *Chamfer* the mean of both directions' "
        "mean nearest-neighbour distance, *min sp.* the smallest distance between two level points, "
        "*unif.* = min sp. / cover (1 or more for an exact farthest point level, near 0 for random), "
        "*plane RMS/max* the distance of the input points to the PCA plane of their 8 nearest level "
        "points. All distances are in the input's units and divided by the median "
        "nearest-neighbour spacing of the input (column header says so), so inputs compare.",
        "- On the folded sheets, *geo cover* is the covering radius measured along the sheet "
        "(exact: the sheet unfolds to a flat rectangle); Euclidean methods may cover one layer "
        "from the other, which the band metric does not.",
        "",
    ]
    for name, res in doc["inputs"].items():
        s = res["median_nn_spacing"]
        lines += [
            f"### {name}: {res['n_points']:,} points ({res['kind']}; {res['source']})",
            "",
            f"Median nearest-neighbour spacing {s:.4g}, bounding-box diagonal {res['diagonal']:.4g}. "
            "Distances below are in units of that spacing.",
            "",
        ]
        geo = name in GAPS
        head = "| method | size | time (s) | cover | rho ok | Hausdorff | Chamfer | min sp. | unif. | plane RMS | plane max |"
        sep = "|---|---:|---:|---:|:---:|---:|---:|---:|---:|---:|---:|"
        if geo:
            head += " geo cover |"
            sep += "---:|"
        lines += [head, sep]
        for mname, mres in res["methods"].items():
            if "levels" not in mres:
                why = mres.get("skipped") or mres.get("failed")
                lines.append(f"| {mname} | - | {why} |" + " |" * (9 if not geo else 10))
                continue
            for lv in mres["levels"]:
                t = lv["seconds"]
                tcell = f"{t:.3g}"
                if lv.get("order_once"):
                    tcell = f"{t:.3g} once (slice {1e3 * lv['slice_s']:.2g} ms)"
                row = (
                    f"| {mname} | {lv['size']:,} | {tcell} | {_g(lv['covering_radius'] / s)} | "
                    f"{_g(lv['meets_rho'])} | {_g(lv['hausdorff'] / s)} | {_g(lv['chamfer'] / s)} | "
                    f"{_g((lv['min_spacing'] or 0) / s)} | {_g(lv['uniformity'])} | "
                    f"{_g(lv['surface_error']['rms'] / s)} | {_g(lv['surface_error']['max'] / s)} |"
                )
                if geo:
                    row += f" {_g(lv['geodesic_covering_radius'] / s)} |"
                lines.append(row)
        lines.append("")
    lines += ["### Summary (computed from the tables above)", ""] + [f"- {x}" for x in summary(doc)]
    lines.append("")
    if doc.get("notes"):
        lines += ["### Notes", ""] + [f"- {n}" for n in doc["notes"]] + [""]
    return "\n".join(lines)


def summary(doc: dict) -> list[str]:
    """A few comparisons computed from the results (so they stay true when the run is redone)."""
    out = []
    ok = total = 0
    for res in doc["inputs"].values():
        for lv in res["methods"].get("lodbuilder", {}).get("levels", []):
            total += 1
            ok += lv["meets_rho"] is True
    out.append(
        f"lodbuilder levels whose measured covering radius meets their claimed rho: {ok} of {total}."
    )
    for name, res in doc["inputs"].items():
        meth = res["methods"]
        lb = meth.get("lodbuilder", {}).get("levels")
        fp = meth.get("fpsample", {}).get("levels")
        if not lb or not fp:
            continue
        ratios = ", ".join(
            f"{100 * f:g} %: {a['covering_radius'] / b['covering_radius']:.2f}"
            for f, a, b in zip(doc["fractions"], lb, fp, strict=False)
        )
        fp_time = sum(b["seconds"] for b in fp)
        line = (
            f"{name}: covering radius of lodbuilder / fpsample at {ratios}; lodbuilder's one ordering "
            f"took {lb[0]['seconds']:.3g} s, fpsample {fp_time:.3g} s for its three levels"
        )
        if "geodesic_covering_radius" in lb[0]:
            geo = []
            for m, mres in meth.items():
                if "levels" in mres:
                    geo.append((mres["levels"][0]["geodesic_covering_radius"], m))
            geo.sort()
            s_ = res["median_nn_spacing"]
            line += "; geodesic covering radius at 1 % (spacings): " + ", ".join(
                f"{m} {g / s_:.3g}" for g, m in geo
            )
        out.append(line + ".")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--big", action="store_true", help="1M-point synthetic scan (slow)")
    ap.add_argument("--synthetic-points", type=int, default=200_000)
    ap.add_argument("--folded-points", type=int, default=100_000)
    ap.add_argument(
        "--only",
        help="comma-separated inputs (igea,frag_115,bun_zipper,bun000,bunny_posed,synthetic,folded,folded_thin)",
    )
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods")
    ap.add_argument("--markdown", help="write the markdown report here (e.g. docs/benchmarks.md)")
    ap.add_argument("--json", help="also write the JSON here")
    ap.add_argument("--from-json", help="only rewrite --markdown from the JSON of an earlier run")
    args = ap.parse_args()
    if args.from_json:
        if not args.markdown:
            ap.error("--from-json needs --markdown")
        write_section(
            Path(args.markdown), "peers", markdown(load_run(args.from_json))
        )
        return 0
    methods = [m for m in args.methods.split(",") if m]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        ap.error(f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}")

    t0 = time.perf_counter()
    doc = {
        "benchmark": "peers",
        "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "flags": "".join(
            f" {a}"
            for a in sys.argv[1:]
            if not a.endswith((".md", ".json")) and a not in ("--markdown", "--json")
        ),
        "fractions": FRACTIONS,
        "machine": machine(),
        "inputs": {},
    }
    for name, inp in load_inputs(args).items():
        doc["inputs"][name] = run_input(name, inp, methods)
    doc["total_s"] = time.perf_counter() - t0
    text = json.dumps(doc, indent=1, default=float)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    if args.markdown:
        write_section(Path(args.markdown), "peers", markdown(doc))
        log(f"wrote the peers section of {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
