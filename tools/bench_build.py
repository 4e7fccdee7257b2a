"""Benchmark the full FastFPS ordering (JSON on stdout).

Inputs: scan-like synthetic surfaces (a wavy sheet sampled on a jittered grid, like a range scan) of
100k, 1M and 4M points, and the 10 Stanford bunny range scans merged with their poses from
../shared/data/bun.conf. For each: N, voxel size h, band radius r, band voxels, pops per voxel,
wall and CPU time per phase, peak RSS of a fresh process; and, when fpsample is installed, the time
of fpsample's full Euclidean ordering (bucket_fps_kdline_sampling asking for all N points) and the
ratio (both in the same process, one after the other).

Optional sections:
  --real [--baseline TREE] [--also NAME=TREE] [--only NAME,...]
                             every real scan in ../shared/data (one fresh process per scan and tree,
                             alternating): the ordering alone (fastfps, after a warm-up that loads
                             every kernel from the cache), smallest wall and smallest CPU time of
                             --repeat runs; with a baseline source tree (e.g. an older checkout) the
                             ratios new / baseline (and NAME / baseline for every --also tree);
                             --only: just these files (e.g. bun_zipper_res4.ply,simple.las)
  --cli-rss                  peak RSS of ``lodbuilder build`` on a 1M-point sheet written as a PLY
                             file (whole process), with the RSS before the engine and its own peak
  --cold [--repeat K]        ``lodbuilder demo`` with an empty numba cache (first-run compile),
                             then again with the filled cache (this tree and the baseline
                             alternating, medians of K runs)

    python tools/bench_build.py                      # 100k, 1M, 4M, bunny
    python tools/bench_build.py --sizes 100000 --no-bunny --no-fpsample
    python tools/bench_build.py --sizes --no-bunny --real --baseline /tmp/old_tree --cli-rss --cold
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
from benchdoc import load_run, write_section

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
    from lodbuilder.build.inputs import expand_inputs
    from lodbuilder.io import read_scan
    from lodbuilder.io.pose import apply_pose

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
    c0 = time.process_time()
    o = lodbuilder.fastfps(pts)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
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
        "cpu_s": cpu,
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
            c0 = time.process_time()
            fpsample.bucket_fps_kdline_sampling(pts, n, h=7)
            out["fpsample_time_s"] = time.perf_counter() - t0
            out["fpsample_cpu_s"] = time.process_time() - c0
            out["ratio_to_fpsample"] = wall / out["fpsample_time_s"]
            out["cpu_ratio_to_fpsample"] = cpu / out["fpsample_cpu_s"]
    return out


REAL_SUFFIXES = (".ply", ".las", ".laz", ".e57")

_REAL_CODE = r"""
import json, sys, time
from lodbuilder.io import read_scan
import lodbuilder
pts = read_scan(sys.argv[1]).points
lodbuilder.fastfps(pts[:500])
try:  # load every kernel from numba's cache outside the timing, also those the 500 points missed
    from lodbuilder._kernels.warm import _prototypes, compile_group
except ImportError:  # an older tree: the warm-up above used all of its kernels
    pass
else:
    for group in _prototypes():
        compile_group(group)
t = time.perf_counter(); c = time.process_time()
o = lodbuilder.fastfps(pts)
print(json.dumps({"n": len(pts), "wall": time.perf_counter() - t, "cpu": time.process_time() - c,
                  "thin_points": o.stats.get("thin_points", 0)}))
"""


def real_scans(
    baseline: str | None, repeat: int, also: dict[str, str] | None = None, only: list[str] | None = None
) -> list[dict]:
    """Time the ordering (``fastfps`` alone, after a warm-up that loads every kernel from numba's
    cache) of every real scan in fresh processes: this tree, the ``also`` trees and (if given) a
    baseline tree, alternating; per tree the smallest wall time and, separately, the smallest CPU
    time (user + system, all threads) of ``repeat`` runs, and their ratios to the baseline's."""
    trees = {"new": str(ROOT)} | (also or {}) | ({"baseline": baseline} if baseline else {})
    out = []
    for path in sorted(p for p in SHARED.iterdir() if p.suffix.lower() in REAL_SUFFIXES):
        if only and path.name not in only:
            continue
        row: dict = {"scan": path.name}
        for _ in range(repeat):
            for name, tree in trees.items():
                env = dict(os.environ, PYTHONPATH=tree)
                res = subprocess.run([sys.executable, "-c", _REAL_CODE, str(path)], env=env,
                                     cwd=tree, capture_output=True, text=True)  # cwd: '' is on sys.path
                if res.returncode:
                    row[name] = {"failed": res.stderr.strip().splitlines()[-1][:200]}
                    continue
                r = json.loads(res.stdout.strip().splitlines()[-1])
                best = row.get(name)
                if best is None or "failed" in best:
                    row[name] = r
                else:
                    best["wall"] = min(best["wall"], r["wall"])
                    best["cpu"] = min(best["cpu"], r["cpu"])
        base = row.get("baseline", {})
        for name in trees:
            if name == "baseline" or "wall" not in row.get(name, {}) or "wall" not in base:
                continue
            prefix = "" if name == "new" else f"{name}_"
            row[f"{prefix}wall_ratio"] = row[name]["wall"] / base["wall"]
            row[f"{prefix}cpu_ratio"] = row[name]["cpu"] / base["cpu"]
        row["load_avg"] = os.getloadavg()
        out.append(row)
        print(json.dumps(row), file=sys.stderr)
    return out


_RSS_CODE = r"""
import json, os, sys, threading, time
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
marks = {}
peak = [0]
def sample():
    while True:
        peak[0] = max(peak[0], rss()); time.sleep(0.002)
threading.Thread(target=sample, daemon=True).start()
import lodbuilder.sampling.fastfps as F
run = F._run_engine
def wrapped(*a, **k):
    marks["before_engine"] = rss(); peak[0] = rss()
    r = run(*a, **k)
    marks["engine_peak"] = peak[0]
    return r
F._run_engine = wrapped
from lodbuilder.cli.main import main
main(["build", sys.argv[1], "-o", sys.argv[2], "--no-progress"])
import resource
marks["process_peak"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps(marks))
"""


def cli_rss(n: int, tree: str) -> dict:
    """Peak RSS of ``lodbuilder build`` (source ``tree``) on an n-point range-scan sheet written as
    a PLY file."""
    import tempfile

    from lodbuilder.io import write_points

    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "sheet.ply"
        write_points(src, range_scan_sheet(n).astype(np.float32).astype(np.float64))
        env = dict(os.environ, PYTHONPATH=tree)
        warm = [sys.executable, "-c", "import numpy, lodbuilder; lodbuilder.fastfps(numpy.random.rand(500, 3))"]
        subprocess.run(warm, env=env, cwd=tree, check=True)
        res = subprocess.run([sys.executable, "-c", _RSS_CODE, str(src), str(Path(tmp) / "a.h5")],
                             env=env, cwd=tree, capture_output=True, text=True, check=True)
    m = json.loads(res.stdout.strip().splitlines()[-1])
    n_pts = len(range_scan_sheet(n))
    return {
        "input": f"range-scan sheet {n} (PLY, float32 coordinates), synthetic",
        "n": n_pts,
        "process_peak_mib": m["process_peak"] / 2**20,
        "process_peak_bytes_per_point": m["process_peak"] / n_pts,
        "rss_before_engine_mib": m["before_engine"] / 2**20,
        "engine_peak_mib": m["engine_peak"] / 2**20,
        "engine_share_bytes_per_point": (m["engine_peak"] - m["before_engine"]) / n_pts,
    }


def cold_start(trees: dict[str, str], repeat: int) -> dict:
    """``lodbuilder demo`` of each source tree with an empty numba cache, then with the cache it
    filled: the trees alternate, ``repeat`` times; medians and every run (wall and CPU seconds of
    the demo process and its children, the load average before each run). The first-run compile
    uses a child process only when a core is free (see lodbuilder/_kernels/warm.py)."""
    import statistics
    import tempfile

    runs: dict = {name: {"cold_s": [], "warm_s": [], "cold_cpu_s": [], "warm_cpu_s": [], "load1": []} for name in trees}

    def cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_CHILDREN)
        return r.ru_utime + r.ru_stime

    for _ in range(repeat):
        for name, tree in trees.items():
            with tempfile.TemporaryDirectory() as tmp:
                env = dict(os.environ, PYTHONPATH=tree, NUMBA_CACHE_DIR=str(Path(tmp) / "numba"))
                runs[name]["load1"].append(os.getloadavg()[0])
                for label in ("cold", "warm"):
                    t, c = time.perf_counter(), cpu()
                    subprocess.run([sys.executable, "-m", "lodbuilder.cli.main", "demo", "-o",
                                    str(Path(tmp) / label), "--no-progress"], env=env, cwd=tree,
                                   check=True, capture_output=True)
                    runs[name][f"{label}_s"].append(time.perf_counter() - t)
                    runs[name][f"{label}_cpu_s"].append(cpu() - c)
    return {
        name: {k: statistics.median(v) for k, v in r.items() if k != "load1"} | {"runs": r}
        for name, r in runs.items()
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[100_000, 1_000_000, 4_000_000])  # none: skip
    ap.add_argument("--no-bunny", action="store_true")
    ap.add_argument("--no-fpsample", action="store_true")
    ap.add_argument(
        "--fpsample-max", type=int, default=1_100_000,
        help="time fpsample only up to this many points (its full 4M ordering takes many minutes)",
    )
    ap.add_argument("--real", action="store_true", help="time every real scan in ../shared/data")
    ap.add_argument("--baseline", help="with --real: a source tree to compare with (its PYTHONPATH)")
    ap.add_argument("--only", help="with --real: only these files of ../shared/data (comma-separated)")
    ap.add_argument("--also", action="append", default=[], metavar="NAME=TREE",
                    help="with --real: one more source tree timed in the same alternation (repeatable)")
    ap.add_argument("--repeat", type=int, default=2,
                    help="with --real: best of this many runs; with --cold: median of this many")
    ap.add_argument("--cli-rss", action="store_true", help="peak RSS of lodbuilder build on 1M points")
    ap.add_argument("--cold", action="store_true", help="first-run compile time of lodbuilder demo")
    ap.add_argument("--markdown", help="also write the 'build' section of this markdown file")
    ap.add_argument("--from-json", help="render the markdown section from a saved JSON report")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.from_json:
        report = load_run(args.from_json)
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
        "command": " ".join(["python", "tools/bench_build.py", *sys.argv[1:]]),
        "git_commit": subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                                     capture_output=True, text=True).stdout.strip(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load_avg_at_start": os.getloadavg(),
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
    if args.real:
        also = dict(a.split("=", 1) for a in args.also)
        only = args.only.split(",") if args.only else None
        report["real_scans"] = real_scans(args.baseline, args.repeat, also, only)
    trees = {"new": str(ROOT)} | ({"baseline": args.baseline} if args.baseline else {})
    if args.cli_rss:
        report["cli_build_rss"] = {name: cli_rss(1_000_000, tree) for name, tree in trees.items()}
        print(json.dumps(report["cli_build_rss"]), file=sys.stderr)
    if args.cold:
        report["cold_start_demo"] = cold_start(trees, args.repeat)
        print(json.dumps(report["cold_start_demo"]), file=sys.stderr)
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
    if report.get("real_scans"):
        lines += [
            "",
            "Real scans in ../shared/data (the ordering alone, fresh process per scan, smallest wall and "
            "smallest CPU time of the runs; *baseline* is the source tree given to --baseline, timed "
            "alternately in the same run):",
            "",
            "| scan | N | thin points | wall s | CPU s | baseline wall s | wall ratio | CPU ratio |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for row in report["real_scans"]:
            new, base = row.get("new", {}), row.get("baseline", {})
            if "wall" not in new:
                lines.append(f"| {row['scan']} | - | - | failed: {new.get('failed', '?')} | | | | |")
                continue
            lines.append(
                f"| {row['scan']} | {new['n']:,} | {new.get('thin_points', 0):,} | {new['wall']:.2f} | "
                f"{new['cpu']:.2f} | {base.get('wall', float('nan')):.2f} | "
                f"{row.get('wall_ratio', float('nan')):.2f} | {row.get('cpu_ratio', float('nan')):.2f} |"
            )
    for name, r in (report.get("cli_build_rss") or {}).items():
        lines += [
            "",
            f"`lodbuilder build` of a 1M-point sheet ({name}): process peak RSS "
            f"{r['process_peak_mib']:.1f} MiB = {r['process_peak_bytes_per_point']:.0f} B/point; "
            f"{r['rss_before_engine_mib']:.1f} MiB before the engine, engine peak "
            f"{r['engine_peak_mib']:.1f} MiB (its own share {r['engine_share_bytes_per_point']:.0f} B/point).",
        ]
    for name, r in (report.get("cold_start_demo") or {}).items():
        lines += [
            "",
            f"`lodbuilder demo` with an empty numba cache ({name}): {r['cold_s']:.1f} s; "
            f"with the cache it filled: {r['warm_s']:.1f} s"
            + (f" (medians of {len(r['runs']['cold_s'])} runs, trees alternating)." if "runs" in r else "."),
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
