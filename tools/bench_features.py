"""Benchmark: does feature-sensitive ordering lower the surface error at equal size?

For each scan and each level size (2 %, 5 %, 10 % of the points), the mean distance from every input
point to the plane fitted (PCA) to its 8 nearest kept points, for the uniform ordering and for
curvature-weighted (and, on coloured scans, colour-weighted) orderings at a few adaptivities,
and density-floor orderings (uniform up to the 1 % level, then weighted with a = 1). Prints JSON.

    python tools/bench_features.py [--data DIR] [--files igea.ply frag_115.ply] [--adaptive 0.5 1]
        [--floor-fraction 0.01] [--markdown docs/benchmarks.md] [--from-json RUN.json]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from benchdoc import load_run, machine, measured, publish, stamp, write_section

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lodbuilder import fastfps  # noqa: E402
from lodbuilder.features import (  # noqa: E402
    combine_maps,
    compute_importance,
    cost_from_weights,
)
from lodbuilder.io import read_scan  # noqa: E402
from lodbuilder.quality.surface import surface_error  # noqa: E402
from lodbuilder.sampling.adaptive import (  # noqa: E402
    density_floor_ordering,
    weighted_ordering,
)

FRACTIONS = (0.02, 0.05, 0.10)


def errors_of(points: np.ndarray, order: np.ndarray, sizes: list[int]) -> dict[str, dict]:
    out = {}
    for f, n in zip(FRACTIONS, sizes, strict=True):
        err = surface_error(points, points[order[:n]], k=8, method="plane")
        out[f"{round(f * 100)}%"] = {
            "size": n,
            "mean": float(err.mean()),
            "rms": float(np.sqrt(np.mean(err * err))),
            "p95": float(np.percentile(err, 95)),
        }
    return out


def bench_file(path: Path, adaptivities: list[float], floor_fraction: float) -> dict:
    scan = read_scan(path)
    pts = scan.points
    n = len(pts)
    sizes = [max(8, round(f * n)) for f in FRACTIONS]
    names = ["curvature"]
    if all(c in scan.attributes for c in ("red", "green", "blue")):
        names.append("colour")
    t = time.perf_counter()
    maps = compute_importance(scan, names, k=16)
    t_maps = time.perf_counter() - t
    res: dict = {
        "file": path.name,
        "points": n,
        "maps": {m: maps[m][1] for m in maps},
        "time_maps_s": round(t_maps, 3),
        "runs": {},
    }
    t = time.perf_counter()
    uni = fastfps(pts)
    res["runs"]["uniform"] = {
        "time_s": round(time.perf_counter() - t, 3),
        "errors": errors_of(pts, uni.order, sizes),
    }
    combos = [[m] for m in names] + ([names] if len(names) > 1 else [])
    for combo in combos:
        w = combine_maps({m: maps[m] for m in combo}, n)
        for a in adaptivities:
            key = f"{'+'.join(combo)} a={a:g}"
            cost = cost_from_weights(w, a)
            t = time.perf_counter()
            o = weighted_ordering(pts, cost)
            res["runs"][key] = {
                "time_s": round(time.perf_counter() - t, 3),
                "errors": errors_of(pts, o.order, sizes),
            }
    # density floor: uniform until the radius of the uniform level of floor_fraction * N points,
    # then weighted (a = 1): every level here keeps that uniform level
    k0 = max(2, round(floor_fraction * n))
    rho0 = float(uni.radius[k0])
    res["floor"] = {"fraction": floor_fraction, "rho0": rho0, "n_floor": uni.size_for_rho(rho0)}
    for combo in [[m] for m in names]:
        w = combine_maps({m: maps[m] for m in combo}, n)
        key = f"{'+'.join(combo)} floor a=1"
        t = time.perf_counter()
        o = density_floor_ordering(pts, cost_from_weights(w, 1.0), rho0, uniform=uni)
        res["runs"][key] = {
            "time_s": round(time.perf_counter() - t, 3),
            "errors": errors_of(pts, o.order, sizes),
        }
    base = res["runs"]["uniform"]["errors"]
    for run in res["runs"].values():
        for lvl, e in run["errors"].items():
            e["mean_vs_uniform"] = round(e["mean"] / base[lvl]["mean"], 3)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--files", nargs="+", default=["igea.ply", "frag_115.ply"])
    ap.add_argument("--adaptive", nargs="+", type=float, default=[0.25, 0.5, 0.75, 1.0])
    ap.add_argument(
        "--floor-fraction",
        type=float,
        default=0.01,
        help="density floor rho0 = radius of the uniform level of this fraction",
    )
    ap.add_argument("--markdown", help="also write the 'features' section of this markdown file")
    ap.add_argument("--from-json", help="render the markdown section from a saved JSON run")
    args = ap.parse_args()
    if args.from_json:
        saved = load_run(args.from_json)
        write_section(Path(args.markdown or ROOT / "docs" / "benchmarks.md"), "features", markdown(saved))
        return
    out = stamp("bench_features", None, inputs="real scans " + ", ".join(args.files), synthetic=False)
    out |= {
        "about": "feature-sensitive ordering: point-to-plane error at equal size",
        "metric": "mean distance from input points to the PCA plane of their 8 nearest kept points",
        "machine": machine(),
        "cost": "F = max(0.1, (1 - a) + a * w), w = maps normalised by their 5-95 percentiles",
        "results": [
            bench_file(Path(args.data) / f, args.adaptive, args.floor_fraction) for f in args.files
        ],
    }
    publish(out, section="features", render=markdown, markdown=args.markdown)


def markdown(out: dict) -> str:
    lines = [
        (f"{measured(out)}. " if "date" in out else "")
        + f"Metric: {out['metric']}, as a ratio to the uniform ordering at the same size "
        f"(below 1 is better). Cost: {out['cost']}.",
        "",
    ]
    for item in out["results"]:
        sizes = list(next(iter(item["runs"].values()))["errors"])
        lines += [
            f"### {item['file']}: {item['points']:,} points (maps {item['time_maps_s']:.2f} s)",
            "",
            "| ordering | time (s) | " + " | ".join(sizes) + " |",
            "|---|---:|" + "---:|" * len(sizes),
        ]
        for name, run in item["runs"].items():
            cells = " | ".join(f"{run['errors'][k]['mean_vs_uniform']:.3f}" for k in sizes)
            lines.append(f"| {name} | {run['time_s']:.2f} | {cells} |")
        uni = item["runs"]["uniform"]["errors"]
        lines += ["", "Uniform mean error: " + ", ".join(f"{k} {uni[k]['mean']:.3g}" for k in sizes), ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
