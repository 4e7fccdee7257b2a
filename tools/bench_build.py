"""Benchmark the full FastFPS ordering (JSON on stdout).

Inputs: scan-like synthetic surfaces (a wavy sheet sampled on a jittered grid, like a range scan) of
100k, 1M and 4M points, and the 10 Stanford bunny range scans merged with their poses from
../shared/data/bun.conf. For each: N, voxel size h, band radius r, band voxels, pops per voxel,
wall time per phase, peak RSS of a fresh process; and, when fpsample is installed, the time of
fpsample's full Euclidean ordering (bucket_fps_kdline_sampling asking for all N points) and the ratio.

    python tools/bench_build.py                      # 100k, 1M, 4M, bunny
    python tools/bench_build.py --sizes 100000 --no-bunny --no-fpsample
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from benchdoc import write_section

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"


def range_scan_sheet(n: int, seed: int = 0) -> np.ndarray:
    """About n points of a wavy sheet on a jittered grid (unit square, amplitude 0.08)."""
    rng = np.random.default_rng(seed)
    side = int(round(np.sqrt(n)))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2).astype(float)
    g = (g + rng.uniform(-0.3, 0.3, g.shape)) / side
    z = 0.08 * np.sin(4 * np.pi * g[:, 0]) * np.cos(4 * np.pi * g[:, 1])
    return np.c_[g, z]


def bunny_points() -> np.ndarray:
    from lodbuilder.collection.inputs import apply_pose, expand_inputs
    from lodbuilder.io import read_scan

    parts = []
    for src in expand_inputs(manifest=SHARED / "bun.conf"):
        parts.append(apply_pose(read_scan(src.path).points, src.pose))
    return np.vstack(parts)


def load(spec: str) -> np.ndarray:
    if spec == "bunny":
        return bunny_points()
    return range_scan_sheet(int(spec))


def run_one(spec: str, with_fpsample: bool) -> dict:
    """Run in this process (a fresh one per input, so peak RSS is this input's)."""
    import lodbuilder

    pts = load(spec)
    n = len(pts)
    lodbuilder.fastfps(pts[:2000])  # compile / load the cached kernels outside the timing
    t0 = time.perf_counter()
    o = lodbuilder.fastfps(pts)
    wall = time.perf_counter() - t0
    st = o.stats
    out = {
        "input": "bunny 10 range scans merged" if spec == "bunny" else f"range-scan sheet {spec}",
        "n": n,
        "h": o.voxel_size,
        "r": o.band_radius,
        "band_voxels": st["band_voxels"],
        "voxels_per_point": st["band_voxels"] / n,
        "pops": st["pops"],
        "pops_per_voxel": st["pops_per_voxel"],
        "grid_points": st["grid_points"],
        "time_s": wall,
        "time_band_s": st["time_band"],
        "time_grid_s": st["time_grid"],
        "time_tail_s": st["time_tail"],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    out["peak_rss_bytes_per_point"] = out["peak_rss_mb"] * 2**20 / n
    if with_fpsample:
        try:
            import fpsample
        except ImportError:
            out["fpsample"] = "not installed"
        else:
            fpsample.bucket_fps_kdline_sampling(pts[:2000], 2000, h=7)
            t0 = time.perf_counter()
            fpsample.bucket_fps_kdline_sampling(pts, n, h=7)
            out["fpsample_time_s"] = time.perf_counter() - t0
            out["ratio_to_fpsample"] = wall / out["fpsample_time_s"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[100_000, 1_000_000, 4_000_000])
    ap.add_argument("--no-bunny", action="store_true")
    ap.add_argument("--no-fpsample", action="store_true")
    ap.add_argument(
        "--fpsample-max", type=int, default=1_100_000,
        help="time fpsample only up to this many points (its full 4M ordering takes many minutes)",
    )
    ap.add_argument("--markdown", help="also write the 'build' section of this markdown file")
    ap.add_argument("--from-json", help="render the markdown section from a saved JSON report")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.from_json:
        report = json.loads(Path(args.from_json).read_text())
        write_section(Path(args.markdown or ROOT / "docs" / "benchmarks.md"), "build", markdown(report))
        return
    if args.one:
        print(json.dumps(run_one(args.one, not args.no_fpsample)))
        return
    specs = [str(s) for s in args.sizes] + ([] if args.no_bunny or not SHARED.is_dir() else ["bunny"])
    results = []
    for spec in specs:
        skip = args.no_fpsample or (spec != "bunny" and int(spec) > args.fpsample_max)
        cmd = [sys.executable, __file__, "--one", spec] + (["--no-fpsample"] if skip else [])
        res = subprocess.run(cmd, capture_output=True, text=True, check=True)
        results.append(json.loads(res.stdout.strip().splitlines()[-1]))
        print(json.dumps(results[-1]), file=sys.stderr)
    import numba

    report = {
        "benchmark": "bench_build",
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "numba": numba.__version__,
            "load_avg_at_end": os.getloadavg(),
        },
        "results": results,
    }
    by_n = {r["n"]: r for r in results if r["input"].startswith("range")}
    for n in by_n:
        for m in by_n:
            if 3.9 * n <= m <= 4.1 * n:  # e.g. 1M and 4M (a side of the grid is rounded)
                report[f"time_ratio_{m}_vs_{n}"] = by_n[m]["time_s"] / by_n[n]["time_s"]
    print(json.dumps(report, indent=2))
    if args.markdown:
        write_section(Path(args.markdown), "build", markdown(report))


def markdown(report: dict) -> str:
    m = report["machine"]
    lines = [
        "## Full ordering (tools/bench_build.py)",
        "",
        f"{m['cpus']} cores, Python {m['python']}, numpy {m['numpy']}, numba {m['numba']}; "
        f"load average at the end {', '.join(f'{x:.2f}' for x in m['load_avg_at_end'])}.",
        "",
        "| input | N | h | band voxels / point | pops / voxel | band s | grid s | tail s | total s "
        "| fpsample s | ratio | peak RSS B/point |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["results"]:
        fps = r.get("fpsample_time_s")
        ratio = r.get("ratio_to_fpsample")
        lines.append(
            f"| {r['input']} | {r['n']:,} | {r['h']:.3g} | {r['voxels_per_point']:.2f} | "
            f"{r['pops_per_voxel']:.1f} | {r['time_band_s']:.1f} | {r['time_grid_s']:.1f} | "
            f"{r['time_tail_s']:.1f} | {r['time_s']:.1f} | "
            f"{'-' if fps is None else f'{fps:.1f}'} | {'-' if ratio is None else f'{ratio:.2f}'} | "
            f"{r['peak_rss_bytes_per_point']:.0f} |"
        )
    for k, v in report.items():
        if k.startswith("time_ratio"):
            lines += ["", f"{k}: {v:.2f}"]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
