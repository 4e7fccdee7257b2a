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
from bench_inputs import range_scan_sheet
from benchdoc import load_run, write_section

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
TREE = os.environ.get("LODBUILDER_BENCH_TREE", str(ROOT))  # the source tree --set times (--tree)


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
import json, os, resource, sys, time
# Peaks from the kernel's high-water mark (VmHWM), reset at the engine's start through
# /proc/self/clear_refs: exact, and no sampling thread whose CPU time the process would include
# (a 20 ms /proc sampler took about 0.1 CPU-s of a 1M-point build: 1.2 %).
def status(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    return 0
marks = {}
import lodbuilder.sampling.fastfps as F
run = F._run_engine
def wrapped(*a, **k):
    marks["before_engine"] = status("VmRSS:")
    marks["peak_before_engine"] = max(marks.get("peak_before_engine", 0), status("VmHWM:"))
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # (the high-water mark starts again from the current RSS)
    except OSError:  # (no reset: the engine's peak below is the process's so far)
        pass
    r = run(*a, **k)
    marks["engine_peak"] = status("VmHWM:")
    return r
F._run_engine = wrapped
from lodbuilder.cli.main import main
t0 = time.perf_counter()
sys.argv = ["lodbuilder", "build", sys.argv[1], "-o", sys.argv[2], "--no-progress"]
import atexit
def report():  # printed at exit: main() run as the lodbuilder command does (no argv) prepares it
    marks["build_s"] = build_s
    marks["process_peak"] = max(status("VmHWM:"), marks.get("peak_before_engine", 0))
    use = resource.getrusage(resource.RUSAGE_SELF)  # start-up and imports included, not the shutdown
    marks["process_cpu_s"] = use.ru_utime + use.ru_stime
    print(json.dumps(marks), flush=True)
atexit.register(report)
code = main()
build_s = time.perf_counter() - t0
sys.exit(code)
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


_SET_WARM = r"""
import numpy, lodbuilder
lodbuilder.fastfps(numpy.random.default_rng(0).random((500, 3)))
try:
    from lodbuilder._kernels.warm import _prototypes, compile_group
except ImportError:
    pass
else:
    for group in _prototypes():
        compile_group(group)
"""


FPSAMPLE_LIMIT_S = 150.0  # fpsample's full ordering of an airborne scan can take minutes: stop there


def _fpsample_child(pts: np.ndarray, conn) -> None:  # noqa: ANN001 - a multiprocessing pipe
    import fpsample

    t0, c0 = time.perf_counter(), time.process_time()
    fpsample.bucket_fps_kdline_sampling(pts, len(pts), h=7)
    conn.send((time.perf_counter() - t0, time.process_time() - c0))


def time_fpsample(pts: np.ndarray, limit: float) -> tuple[float, float] | None:
    """fpsample's full ordering (bucket_fps_kdline_sampling for all N points) in a forked child
    (the same process image: the points are not copied), stopped after ``limit`` seconds (None)."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_fpsample_child, args=(pts, send))
    child.start()
    ready = recv.poll(limit)
    result = recv.recv() if ready else None
    if child.is_alive():
        child.kill()
    child.join()
    return result


def set_one(spec: str, n: int, repeat: int) -> dict:
    """One input of the set, in this (fresh) process: lodbuilder's full ordering and fpsample's
    (in a forked child, stopped after FPSAMPLE_LIMIT_S), alternating ``repeat`` times (smallest
    wall and CPU time of each), with the engine's record."""
    import lodbuilder

    exec(_SET_WARM, {})
    pts = load_set_input(spec, n)
    n = len(pts)
    time_fpsample(pts[:2000], FPSAMPLE_LIMIT_S)
    best: dict = {"lodbuilder": (np.inf, np.inf), "fpsample": (np.inf, np.inf)}
    runs: dict = {"lodbuilder": [], "fpsample": []}
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        o = lodbuilder.fastfps(pts)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        best["lodbuilder"] = (min(best["lodbuilder"][0], wall), min(best["lodbuilder"][1], cpu))
        runs["lodbuilder"].append([wall, cpu])
        fps = time_fpsample(pts, FPSAMPLE_LIMIT_S)
        if fps is not None:
            best["fpsample"] = (min(best["fpsample"][0], fps[0]), min(best["fpsample"][1], fps[1]))
            runs["fpsample"].append(list(fps))
    st = o.stats
    out = {
        "n": n, "h": o.voxel_size, "thin_points": st.get("thin_points", 0),
        "thin_points_found": st.get("thin_points_found", 0), "cpu_band_s": st["cpu_band"],
        "cpu_grid_s": st["cpu_grid"], "cpu_tail_s": st["cpu_tail"],
        "band_voxels_per_point": st["band_voxels"] / n, "pops_per_voxel": st["pops_per_voxel"],
        "grid_points": st["grid_points"], "time_band_s": st["time_band"], "time_grid_s": st["time_grid"],
        "time_tail_s": st["time_tail"], "time_s": best["lodbuilder"][0], "cpu_s": best["lodbuilder"][1],
        "lodbuilder_runs": runs["lodbuilder"], "fpsample_runs": runs["fpsample"],  # [wall s, CPU s] each
    }
    if best["fpsample"][0] == np.inf:
        out["fpsample_time_s"] = f"> {FPSAMPLE_LIMIT_S:g} (stopped)"
        out["ratio_to_fpsample"] = f"< {best['lodbuilder'][0] / FPSAMPLE_LIMIT_S:.3f}"
        return out
    out["fpsample_time_s"], out["fpsample_cpu_s"] = best["fpsample"]
    out["ratio_to_fpsample"] = best["lodbuilder"][0] / best["fpsample"][0]
    out["cpu_ratio_to_fpsample"] = best["lodbuilder"][1] / best["fpsample"][1]
    return out


def fpsample_one(spec: str, n: int) -> dict:
    """``--fpsample-one``: fpsample's full ordering of one input of the set once more, in a fresh
    process (the input loaded, fpsample warmed on 2,000 points, then timed in a forked child as in
    :func:`set_one`): {"time_s", "cpu_s"}, or {"stopped": True} after FPSAMPLE_LIMIT_S."""
    pts = load_set_input(spec, n)
    time_fpsample(pts[:2000], FPSAMPLE_LIMIT_S)
    fps = time_fpsample(pts, FPSAMPLE_LIMIT_S)
    return {"stopped": True} if fps is None else {"time_s": fps[0], "cpu_s": fps[1]}


def _spread(values: list[float]) -> float | None:
    """Largest / smallest of the runs (1.0: all equal; None: fewer than two runs)."""
    return max(values) / min(values) if len(values) > 1 and min(values) > 0 else None


def reference_runs(row: dict, spec: str, n: int, path: Path, runs: int) -> None:
    """The steadier reference (into ``row``): ``runs`` runs of the whole ``lodbuilder build``
    process and, alternating with them, fpsample's full ordering in fresh processes until it has
    ``runs`` runs in all (counting those of :func:`set_one`; none more where it was stopped).
    Each figure is the smallest of its runs, each ratio the ratio of the smallest, and the spread
    (largest / smallest) of each is kept: fpsample's own CPU time moved 13.8-24.5 s between quiet
    runs on the 2-core machine, more than the targets' margins."""
    fps = [list(r) for r in row.get("fpsample_runs", [])]
    stopped = not isinstance(row["fpsample_time_s"], float)
    builds = []
    for _ in range(max(runs, 1)):
        builds.append(build_rss(path, TREE))
        if not stopped and len(fps) < runs:
            cmd = [sys.executable, __file__, "--fpsample-one", spec, "--set-n", str(n)]
            res = subprocess.run(cmd, capture_output=True, text=True, check=True,
                                 env=dict(os.environ, PYTHONPATH=TREE))
            one = json.loads(res.stdout.strip().splitlines()[-1])
            if "stopped" in one:
                stopped = True
            else:
                fps.append([one["time_s"], one["cpu_s"]])
    row["reference_runs"] = runs
    row["build_runs"] = [
        {"build_s": m["build_s"], "process_s": m["process_s"], "whole_process_cpu_s": m["whole_process_cpu_s"],
         "cpu_before_exit_s": m["process_cpu_s"], "peak_rss_bytes_per_point": m["process_peak"] / row["n"]}
        for m in builds
    ]
    best = {k: min(m[k] for m in builds) for k in ("build_s", "process_s", "whole_process_cpu_s", "process_cpu_s")}
    row["build_s"], row["build_process_s"] = best["build_s"], best["process_s"]
    row["build_process_cpu_s"] = best["whole_process_cpu_s"]  # start-up to exit
    row["build_cpu_before_exit_s"] = best["process_cpu_s"]  # (as this benchmark measured before)
    row["build_process_cpu_spread"] = _spread([m["whole_process_cpu_s"] for m in builds])
    if fps:
        row["fpsample_runs"] = fps
        row["fpsample_time_s"] = min(r[0] for r in fps)
        row["fpsample_cpu_s"] = min(r[1] for r in fps)
        row["fpsample_cpu_spread"] = _spread([r[1] for r in fps])
        row["ratio_to_fpsample"] = row["time_s"] / row["fpsample_time_s"]
        row["cpu_ratio_to_fpsample"] = row["cpu_s"] / row["fpsample_cpu_s"]
        row["build_ratio_to_fpsample"] = best["build_s"] / row["fpsample_time_s"]
        row["build_process_ratio_to_fpsample"] = best["process_s"] / row["fpsample_time_s"]
        row["build_process_cpu_ratio_to_fpsample"] = best["whole_process_cpu_s"] / row["fpsample_cpu_s"]
        row["build_cpu_before_exit_ratio_to_fpsample"] = best["process_cpu_s"] / row["fpsample_cpu_s"]
    # the peak: the largest of the runs (the target holds on every run)
    row["build_peak_rss_bytes_per_point"] = max(m["process_peak"] for m in builds) / row["n"]
    row["engine_share_bytes_per_point"] = max(m["engine_peak"] - m["before_engine"] for m in builds) / row["n"]


def load_set_input(spec: str, n: int) -> np.ndarray:
    """A synthetic input of bench_inputs (rounded to float32, as its PLY file stores it) or a file."""
    from bench_inputs import SYNTHETIC, synthetic

    if spec in SYNTHETIC:
        return synthetic(spec, n).astype(np.float32).astype(np.float64)
    from lodbuilder.io import read_scan

    return read_scan(spec).points


def build_rss(path: Path, tree: str) -> dict:
    """``lodbuilder build`` of ``path`` in a fresh process, run as the command runs (``main()``
    with the process's command line): its wall time and peak RSS, and the whole process's wall
    time and CPU time (user + system), both measured here from interpreter start-up to the end of
    its shutdown (imports, read, ordering, write, exit); ``process_cpu_s`` is the CPU time the
    process had used just before its shutdown (what this benchmark reported before)."""
    import tempfile

    env = dict(os.environ, PYTHONPATH=tree)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        child = subprocess.Popen([sys.executable, "-c", _RSS_CODE, str(path), str(Path(tmp) / "a.h5")],
                                 env=env, cwd=tree, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = child.communicate()
        wall = time.perf_counter() - t0
        # the child's resource use, known once it is reaped: the whole process, its shutdown too
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if child.returncode:
        raise subprocess.CalledProcessError(child.returncode, "lodbuilder build", out, err)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return json.loads(out.strip().splitlines()[-1]) | {"process_s": wall, "whole_process_cpu_s": cpu}


def input_set(n: int, data: Path, survey: Path | None, repeat: int, only: list[str] | None,
              runs: int = 3) -> list[dict]:
    """Every input of the set (bench_inputs.py): the ordering against fpsample's in one fresh
    process per input, then ``lodbuilder build`` of its file in other fresh processes (peak RSS,
    build time), ``runs`` times alternating with more runs of fpsample (:func:`reference_runs`)."""
    import tempfile

    from bench_inputs import SYNTHETIC, real_files, synthetic

    from lodbuilder.io import write_points

    specs: list[tuple[str, str, Path | None]] = [(k, f"{k} {n} (synthetic)", None) for k in SYNTHETIC]
    specs += [(str(p), p.name, p) for p in real_files(data)]
    if survey is not None:
        specs.append((str(survey), f"survey {survey.name} (autzen tiled, tools/make_survey.py)", survey))
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for spec, label, path in specs:
            if only and not any(o in label for o in only):
                continue
            load = os.getloadavg()
            cmd = [sys.executable, __file__, "--set-one", spec, "--set-n", str(n), "--repeat", str(repeat)]
            res = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=TREE))
            if res.returncode:
                row = {"input": label, "failed": res.stderr.strip().splitlines()[-1][:300]}
                out.append(row)
                print(json.dumps(row), file=sys.stderr)
                continue
            row = {"input": label, **json.loads(res.stdout.strip().splitlines()[-1])}
            if path is None:
                path = Path(tmp) / f"{spec}.ply"
                write_points(path, synthetic(spec, n).astype(np.float32).astype(np.float64))
            reference_runs(row, spec, n, path, runs)
            row["load_avg"] = [load, os.getloadavg()]
            out.append(row)
            print(json.dumps(row), file=sys.stderr)
    return out


def set_rss(n: int, survey: Path | None, only: list[str] | None) -> list[dict]:
    """``--set --rss-only``: the peak RSS of ``lodbuilder build`` of each synthetic input of the set
    (and the survey LAZ), one fresh process each, without timing the orderings."""
    import tempfile

    from bench_inputs import SYNTHETIC, synthetic

    from lodbuilder.io import read_scan, write_points

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        specs = [(f"{k} {n} (synthetic)", k) for k in SYNTHETIC]
        specs += [] if survey is None else [(f"survey {survey.name} (autzen tiled, tools/make_survey.py)", None)]
        for label, kind in specs:
            if only and not any(o in label for o in only):
                continue
            if kind is None:
                path, npts = survey, len(read_scan(survey))
            else:
                pts = synthetic(kind, n).astype(np.float32).astype(np.float64)
                path, npts = Path(tmp) / f"{kind}.ply", len(pts)
                write_points(path, pts)
            m = build_rss(path, TREE)
            row = {"input": label, "n": npts, "build_s": m["build_s"],
                   "build_peak_rss_bytes_per_point": m["process_peak"] / npts,
                   "engine_share_bytes_per_point": (m["engine_peak"] - m["before_engine"]) / npts}
            out.append(row)
            print(json.dumps(row), file=sys.stderr)
    return out


def set_summary(rows: list[dict], n: int) -> dict:
    """The targets of issue 21 over the set: wall and CPU ratios to fpsample at >= 0.5 n points
    (where fpsample finished), peak RSS per point of every input of that size."""
    import statistics

    full = [r for r in rows if "build_peak_rss_bytes_per_point" in r and r["n"] >= n // 2]
    big = [r for r in full if isinstance(r.get("ratio_to_fpsample"), float)]

    def worst_median(key: str) -> tuple[float | None, float | None]:
        v = [r[key] for r in big]
        return (max(v), statistics.median(v)) if v else (None, None)

    wall, cpu = worst_median("ratio_to_fpsample"), worst_median("cpu_ratio_to_fpsample")
    pwall = worst_median("build_process_ratio_to_fpsample")
    pcpu = worst_median("build_process_cpu_ratio_to_fpsample")
    return {
        "inputs_at_full_size": [r["input"] for r in full],
        "worst_ratio_full_size": wall[0], "median_ratio_full_size": wall[1],
        "worst_cpu_ratio_full_size": cpu[0], "median_cpu_ratio_full_size": cpu[1],
        "worst_build_process_ratio_full_size": pwall[0], "median_build_process_ratio_full_size": pwall[1],
        "worst_build_process_cpu_ratio_full_size": pcpu[0],
        "median_build_process_cpu_ratio_full_size": pcpu[1],
        "worst_build_rss_bytes_per_point_full_size": max(
            (r["build_peak_rss_bytes_per_point"] for r in full), default=None),
        # largest / smallest of each input's runs (absent from reports made before the runs were repeated)
        "largest_fpsample_cpu_spread_full_size": max(
            (r["fpsample_cpu_spread"] for r in big if r.get("fpsample_cpu_spread")), default=None),
        "largest_build_process_cpu_spread_full_size": max(
            (r["build_process_cpu_spread"] for r in full if r.get("build_process_cpu_spread")), default=None),
        "fpsample_stopped": [r["input"] for r in rows if isinstance(r.get("fpsample_time_s"), str)],
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
    global SHARED, TREE
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
    ap.add_argument("--set", action="store_true",
                    help="the input set of tools/bench_inputs.py against fpsample (with --set-n points)")
    ap.add_argument("--set-n", type=int, default=1_000_000, help="points of the synthetic inputs of --set")
    ap.add_argument("--set-only", help="with --set: only inputs whose label contains one of these (comma-separated)")
    ap.add_argument("--survey", help="with --set: a survey LAZ (tools/make_survey.py); made (3 x 3) when absent")
    ap.add_argument("--rss-only", action="store_true",
                    help="with --set: only the peak RSS of lodbuilder build of the synthetic inputs and the survey")
    ap.add_argument("--data", default=str(SHARED), help="the real scans (default ../shared/data)")
    ap.add_argument("--tree", help="with --set: the source tree to time (default: this one), e.g. a "
                    "checkout of main for a before/after comparison with this benchmark program")
    ap.add_argument("--reference-runs", type=int, default=3,
                    help="with --set: runs of the whole lodbuilder build process and of fpsample's full "
                    "ordering per input, alternating (the smallest of each; ratios of the smallest)")
    ap.add_argument("--set-one", help=argparse.SUPPRESS)
    ap.add_argument("--fpsample-one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.tree:
        TREE = os.environ["LODBUILDER_BENCH_TREE"] = str(Path(args.tree).resolve())
    if args.set_one:
        print(json.dumps(set_one(args.set_one, args.set_n, args.repeat)))
        return
    if args.fpsample_one:
        print(json.dumps(fpsample_one(args.fpsample_one, args.set_n)))
        return
    if args.from_json:
        report = load_run(args.from_json)
        write_section(Path(args.markdown or ROOT / "docs" / "benchmarks.md"), "build", markdown(report))
        return
    if args.one:
        print(json.dumps(run_one(args.one, not args.no_fpsample)))
        return
    SHARED = Path(args.data)
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
        "timed_tree_commit": subprocess.run(["git", "-C", TREE, "rev-parse", "--short", "HEAD"],
                                            capture_output=True, text=True).stdout.strip(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load_avg_at_start": os.getloadavg(),
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "numba": numba.__version__,
        },
        "results": results,
    }
    if args.real:
        also = dict(a.split("=", 1) for a in args.also)
        only = args.only.split(",") if args.only else None
        report["real_scans"] = real_scans(args.baseline, args.repeat, also, only)
    if args.set:
        survey = Path(args.survey) if args.survey else Path("/tmp/lodbuilder_bench_survey_3x3.laz")
        if not survey.exists():
            subprocess.run([sys.executable, str(ROOT / "tools" / "make_survey.py"), "--nx", "3", "--ny", "3",
                            "-o", str(survey)], check=True, capture_output=True)
        only = args.set_only.split(",") if args.set_only else None
        if args.rss_only:
            report["set_rss"] = set_rss(args.set_n, survey, only)
        else:
            report["set"] = input_set(args.set_n, SHARED, survey, args.repeat, only, args.reference_runs)
            report["set_summary"] = set_summary(report["set"], args.set_n)
    trees = {"new": str(ROOT)} | ({"baseline": args.baseline} if args.baseline else {})
    if args.cli_rss:
        report["cli_build_rss"] = {name: cli_rss(1_000_000, tree) for name, tree in trees.items()}
        print(json.dumps(report["cli_build_rss"]), file=sys.stderr)
    if args.cold:
        report["cold_start_demo"] = cold_start(trees, args.repeat)
        print(json.dumps(report["cold_start_demo"]), file=sys.stderr)
    report["machine"]["load_avg_at_end"] = os.getloadavg()  # (after every section: not at the start)
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
        f"load average at the start {', '.join(f'{x:.2f}' for x in report['load_avg_at_start'])}, "
        f"at the end {', '.join(f'{x:.2f}' for x in m['load_avg_at_end'])}.",
    ]
    if report.get("results"):
        lines += ["", "| input | N | h | band voxels / point | pops / voxel | band s | grid s | tail s | total s "
                  "| fpsample s | ratio | peak RSS B/point |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report.get("results", []):
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
    if report.get("set"):
        from bench_inputs import set_markdown

        lines += set_markdown(report["set"], report["set_summary"])
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
