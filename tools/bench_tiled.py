"""Benchmark the tiled (out-of-core) build (JSON on stdout; --markdown writes its section of
docs/benchmarks.md).

Three measurements (each optional):

* ``--survey FILE``: ``lodbuilder build FILE --max-memory M`` in a subprocess, once per executor
  given (``--workers 1 2``, ``--dask-local 2``): wall time, peak RSS of the whole process tree
  (sampled every 0.1 s from /proc), phases from the build record, time per point. Make the file
  with tools/make_survey.py (the real autzen_trim.laz tiled 14 x 14: 21.56M points).
* ``--reference N``: the in-memory build of the synthetic N-point range-scan sheet of
  tools/bench_build.py (``lodbuilder.fastfps`` in a fresh process), for the time per point ratio.
* ``--quality N``: the same synthetic sheet built tiled (``--quality-memory``, ``--quality-workers``)
  and in memory: covering radius at equal sizes (1 %, 0.1 %, 0.01 % of N), the ratio, and the
  smallest spacing / radius of those levels and of every level (the build record's check).

    python tools/bench_tiled.py --survey /work/bench_data/survey_14x14.laz --workers 1 2 --dask-local 2 \\
        --max-memory 3GB --reference 4000000 --quality 4000000
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))


def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for e in os.listdir("/proc"):
        if e.isdigit():
            try:
                with open(f"/proc/{e}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
                kids.setdefault(int(fields[1]), []).append(int(e))
            except OSError:
                pass
    return kids


def tree_rss(pid: int, cpu: dict[int, float] | None = None) -> int:
    """Resident bytes of ``pid`` and all its descendants; ``cpu`` (pid -> CPU seconds so far) is
    updated for each of them."""
    kids = _children()
    todo, total = [pid], 0
    tick = os.sysconf("SC_CLK_TCK")
    while todo:
        p = todo.pop()
        todo += kids.get(p, [])
        try:
            with open(f"/proc/{p}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1]) * 1024
            if cpu is not None:
                with open(f"/proc/{p}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
                cpu[p] = max(cpu.get(p, 0.0), (int(fields[11]) + int(fields[12])) / tick)  # utime + stime
        except (OSError, IndexError, ValueError):
            pass
    return total


def run_measured(cmd: list[str], env: dict[str, str] | None = None) -> dict:
    """Run ``cmd``: wall seconds, peak RSS of its process tree, CPU seconds of the tree (user + system
    of every waited-for descendant) and the load average at the end (other users of the machine)."""
    t0 = time.perf_counter()
    load_before = os.getloadavg()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = 0
    cpu: dict[int, float] = {}  # sampled every 0.1 s: misses at most the last 0.1 s of each process
    while proc.poll() is None:
        peak = max(peak, tree_rss(proc.pid, cpu))
        time.sleep(0.1)
    out, err = proc.communicate()
    return {"rc": proc.returncode, "seconds": round(time.perf_counter() - t0, 2), "peak_rss_tree_bytes": peak,
            "cpu_seconds_tree": round(sum(cpu.values()), 1), "load_before": load_before, "load_after": os.getloadavg(),
            "stdout": out[-2000:], "stderr": err[-2000:]}


def survey(path: Path, max_memory: str, executor: list[str], work: Path) -> dict:
    import lodbuilder

    out = work / f"survey_{'_'.join(executor).replace('-', '')}.h5"
    if out.exists():
        out.unlink()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-m", "lodbuilder.cli.main", "build", str(path), "-o", str(out), "--max-memory",
           max_memory, "--no-progress", "--json", *executor]
    r = run_measured(cmd, env)
    res = {"executor": " ".join(executor), "max_memory": max_memory,
           **{k: r[k] for k in ("rc", "seconds", "peak_rss_tree_bytes", "cpu_seconds_tree", "load_before",
                                "load_after")}}
    if r["rc"] != 0:
        res["stderr"] = r["stderr"]
        return res
    doc = json.loads(r["stdout"])
    (st,) = doc["scans"]
    res.update(n_points=st["n_points"], method=st["method"], build_seconds=st["seconds"], phases=st["phases"],
               seconds_per_million=round(st["seconds"] / st["n_points"] * 1e6, 3),
               peak_rss_tree_gb=round(r["peak_rss_tree_bytes"] / 1e9, 3))
    with lodbuilder.open_archive(out) as arc:
        tiled = dict(arc.scan(st["name"]).build.get("tiled", {}))
    tiled.pop("guarantees", None)
    res["tiled"] = tiled
    out.unlink()
    return res


REFERENCE_CODE = """
import json, sys, time
sys.path.insert(0, {tools!r})
from bench_build import range_scan_sheet
import lodbuilder
pts = range_scan_sheet({n})
lodbuilder.fastfps(pts[:2000])
t0 = time.perf_counter()
lodbuilder.fastfps(pts)
print(json.dumps({{"n": len(pts), "seconds": time.perf_counter() - t0}}))
"""


def reference(n: int) -> dict:
    code = REFERENCE_CODE.format(tools=str(ROOT / "tools"), n=n)
    r = run_measured([sys.executable, "-c", code], dict(os.environ, PYTHONPATH=str(ROOT)))
    doc = json.loads(r["stdout"].strip().splitlines()[-1])
    return {"input": f"synthetic range-scan sheet {n}", "n_points": doc["n"], "seconds": round(doc["seconds"], 2),
            "seconds_per_million": round(doc["seconds"] / doc["n"] * 1e6, 3),
            "peak_rss_tree_gb": round(r["peak_rss_tree_bytes"] / 1e9, 3)}


def quality(n: int, max_memory: str, workers: int, seam: float | None, tile_points: int | None = None,
            passes: int | None = None) -> dict:
    import numpy as np
    from bench_build import range_scan_sheet
    from scipy.spatial import cKDTree

    import lodbuilder
    from lodbuilder.io import write_points

    pts = range_scan_sheet(n)
    with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR")) as d:
        f = write_points(Path(d) / "sheet.npy", pts)
        kw: dict = {} if seam is None else {"seam_spacing": seam}
        if tile_points:
            kw["_tile_points"] = tile_points
        if passes:
            kw["_tile_passes"] = passes
        t0 = time.perf_counter()
        res = lodbuilder.build_archive(f, Path(d) / "t.h5", max_memory=max_memory, workers=workers, **kw)
        t_tiled = time.perf_counter() - t0
        with lodbuilder.open_archive(Path(d) / "t.h5") as arc:
            v = arc.scan("sheet")
            order, radius = v.source_index[:], v.radius[:]
            tiled = dict(v.build.get("tiled", {}))
    tiled.pop("guarantees", None)
    t0 = time.perf_counter()
    ref = lodbuilder.fastfps(pts)
    t_mem = time.perf_counter() - t0
    rows = []
    for frac in (0.01, 0.001, 0.0001):
        k = int(round(frac * len(pts)))
        ct = float(cKDTree(pts[order[:k]]).query(pts, workers=-1)[0].max())
        cm = float(cKDTree(pts[ref.order[:k]]).query(pts, workers=-1)[0].max())
        dt = cKDTree(pts[order[:k]]).query(pts[order[:k]], k=2)[0][:, 1].min()
        dm = cKDTree(pts[ref.order[:k]]).query(pts[ref.order[:k]], k=2)[0][:, 1].min()
        rows.append({"fraction": frac, "size": k, "cover_tiled": ct, "cover_in_memory": cm,
                     "cover_ratio": round(ct / cm, 4), "stored_radius_tiled": float(radius[k]),
                     "spacing_over_radius_tiled": round(float(dt / radius[k]), 4),
                     "spacing_over_cover_in_memory": round(float(dm / cm), 4)})
    # every level from the head's size to 3 %: the worst covering ratio (the hand-over from the head
    # to the tiles and the seams show there, between the three sizes above)
    h = int(tiled.get("head_points", 1))
    sweep = []
    for k in sorted({int(k) for k in np.geomspace(max(h // 2, 2), max(0.03 * len(pts), h + 2), 24)}):
        ct = float(cKDTree(pts[order[:k]]).query(pts, workers=-1)[0].max())
        cm = float(cKDTree(pts[ref.order[:k]]).query(pts, workers=-1)[0].max())
        sweep.append([k, round(ct / cm, 4)])
    worst = max(sweep, key=lambda r: r[1])
    # seams: points of the first 5 % within half their level's radius of an earlier point of
    # another tile (the head counts as no tile)
    boxes = np.asarray(tiled.get("tile_boxes", []))
    p = pts[order]
    tile = np.full(len(p), -1)
    for t, b in enumerate(boxes):
        inside = np.all((p >= b[:3]) & (p <= b[3:]), axis=1) & (tile < 0)
        tile[inside] = t
    tile[:h] = -1
    j = np.arange(h, max(h, int(0.05 * len(p))))
    close = cKDTree(p).query_ball_point(p[j], 0.5 * radius[j + 1] * (1 - 1e-12), workers=-1)
    crowded = sum(1 for k, near in zip(j, close, strict=True)
                  if any(i < k and tile[i] >= 0 and tile[i] != tile[k] for i in near))
    return {"input": f"synthetic range-scan sheet {len(pts)}", "max_memory": max_memory, "workers": workers,
            "tile_points": tile_points, "method": res.scans[0].method, "seconds_tiled": round(t_tiled, 2),
            "seconds_in_memory": round(t_mem, 2), "levels": rows, "sweep": sweep,
            "sweep_worst": {"size": worst[0], "cover_ratio": worst[1]}, "crowded_first_5pct": crowded, "tiled": tiled}


def ratios(doc: dict) -> str:
    """The target ratios of a run: 2 workers over 1, Dask over the pool, survey time per point over
    the in-memory reference (each only when both runs are in the doc)."""
    runs = {r["executor"]: r for r in doc.get("survey", {}).get("runs", []) if not r.get("rc")}
    out = []
    w1, w2, dk = runs.get("--workers 1"), runs.get("--workers 2"), runs.get("--dask-local 2")
    if w1 and w2:
        out.append(f"2 workers over 1: {w1['seconds'] / w2['seconds']:.2f} x faster (target >= 1.6)")
    if w2 and dk:
        out.append(f"Dask LocalCluster over the pool (2 workers): {dk['seconds'] / w2['seconds']:.2f} (target <= 1.15)")
    ref = doc.get("reference")
    best = min((r["seconds_per_million"] for r in runs.values()), default=None)
    if ref and best is not None:
        out.append(f"time per point, fastest survey run over the in-memory reference: "
                   f"{best / ref['seconds_per_million']:.2f} (target <= 1.3)")
    return "; ".join(out) + ("." if out else "")


def markdown(doc: dict) -> str:
    """The docs/benchmarks.md section of a run (or of several runs merged: a list of docs)."""
    docs = doc if isinstance(doc, list) else [doc]
    lines: list[str] = []
    for d in docs:
        lines.append(f"Run {d['date']} at commit {d['commit']} ({d['cpus']} cpus, load before "
                     f"{', '.join(f'{x:.1f}' for x in d['load_before'])}): `{d['command']}`")
        lines.append("")
        if "survey" in d:
            sv = d["survey"]
            lines += [f"Survey `{Path(sv['file']).name}` ({sv['bytes'] / 1e6:.0f} MB LAZ):", "",
                      "| executor | points | wall s | CPU s of the tree | load before / after | s per M points "
                      "| peak RSS of the tree | tiles | phases (s) |",
                      "|---|---:|---:|---:|---|---:|---:|---:|---|"]
            for r in sv["runs"]:
                if r.get("rc"):
                    lines.append(f"| {r['executor']} | failed | | | | | | | {r.get('stderr', '')[-120:]} |")
                    continue
                ph = ", ".join(f"{k} {v:.0f}" for k, v in r["phases"].items())
                load = (f"{r['load_before'][0]:.1f} / {r['load_after'][0]:.1f}" if "load_before" in r else "")
                lines.append(f"| {r['executor']} | {r['n_points']:,} | {r['seconds']:.0f} | {r.get('cpu_seconds_tree', '')} "
                             f"| {load} | {r['seconds_per_million']:.2f} "
                             f"| {r['peak_rss_tree_gb']:.2f} GB | {r['tiled'].get('tiles')} | {ph} |")
            lines.append("")
            lines.append(ratios(d))
            lines.append("")
        if "reference" in d:
            r = d["reference"]
            lines += [f"In-memory reference, {r['input']}: {r['seconds']:.1f} s, {r['seconds_per_million']:.2f} s per "
                      f"M points, peak RSS {r['peak_rss_tree_gb']:.2f} GB.", ""]
        if "quality" in d:
            q = d["quality"]
            t = q["tiled"]
            lines += [f"Quality, {q['input']} ({t.get('tiles')} tiles, {t.get('passes', 1)} pass(es), seam_spacing "
                      f"{t.get('seam_alpha')}, {t.get('seam_deferrals')} deferrals; tiled "
                      f"{q['seconds_tiled']:.0f} s, in memory {q['seconds_in_memory']:.0f} s); spacing / radius over "
                      f"every level {t.get('spacing_over_radius_min', float('nan')):.3f}:", "",
                      "| size | covering tiled | covering in memory | ratio | spacing / radius (tiled) |",
                      "|---:|---:|---:|---:|---:|"]
            for r in q["levels"]:
                lines.append(f"| {r['size']:,} ({r['fraction']:.2%}) | {r['cover_tiled']:.5f} | {r['cover_in_memory']:.5f} "
                             f"| {r['cover_ratio']:.3f} | {r['spacing_over_radius_tiled']:.3f} |")
            lines.append("")
            if "sweep_worst" in q:
                w = q["sweep_worst"]
                lines += [f"Worst covering ratio over {len(q['sweep'])} sizes from half the head "
                          f"({t.get('head_points')} points) to 3 %: {w['cover_ratio']:.3f} at {w['size']:,} points"
                          + (f" (tiles of at most {q['tile_points']:,} points)." if q.get("tile_points") else ".")
                          + (f" Points of the first 5 % within 0.5 x their level's radius of an earlier point of another "
                             f"tile: {q['crowded_first_5pct']}." if "crowded_first_5pct" in q else ""), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--survey", type=Path)
    p.add_argument("--max-memory", default="3GB")
    p.add_argument("--workers", type=int, nargs="*", default=[])
    p.add_argument("--dask-local", type=int, nargs="*", default=[])
    p.add_argument("--reference", type=int)
    p.add_argument("--quality", type=int)
    p.add_argument("--quality-memory", default="3GB")
    p.add_argument("--quality-workers", type=int, default=2)
    p.add_argument("--seam-spacing", type=float)
    p.add_argument("--quality-tile-points", type=int,
                   help="points per tile of the quality build (a test knob: more tiles than the budget makes)")
    p.add_argument("--quality-passes", type=int, help="tile passes of the quality build (default: TILE_PASSES)")
    p.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()))
    p.add_argument("--markdown", type=Path, help="write the 'tiled' section of this file (docs/benchmarks.md)")
    p.add_argument("--from-json", nargs="+", help="render saved JSON runs into --markdown, no new run")
    args = p.parse_args(argv)
    if args.from_json:
        from benchdoc import load_run

        docs = [load_run(f) for f in args.from_json]
        text = markdown(docs)
        if args.markdown:
            from benchdoc import write_section

            write_section(args.markdown, "tiled", text)
        print(text)
        return 0
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    doc: dict = {"benchmark": "bench_tiled", "date": _dt.datetime.now().isoformat(timespec="seconds"),
                 "commit": commit, "command": " ".join(sys.argv), "machine": platform.machine(),
                 "cpus": os.cpu_count(), "load_before": os.getloadavg()}
    if args.survey:
        runs = [["--workers", str(w)] for w in args.workers] + [["--dask-local", str(w)] for w in args.dask_local]
        doc["survey"] = {"file": str(args.survey), "bytes": args.survey.stat().st_size, "runs": []}
        for ex in runs or [[]]:
            doc["survey"]["runs"].append(survey(args.survey, args.max_memory, ex, args.work))
            print(json.dumps(doc["survey"]["runs"][-1]), file=sys.stderr)
    if args.reference:
        doc["reference"] = reference(args.reference)
        print(json.dumps(doc["reference"]), file=sys.stderr)
    if args.quality:
        doc["quality"] = quality(args.quality, args.quality_memory, args.quality_workers, args.seam_spacing,
                                 args.quality_tile_points, args.quality_passes)
    doc["load_after"] = os.getloadavg()
    print(json.dumps(doc, indent=1))
    if args.markdown:
        from benchdoc import write_section

        write_section(args.markdown, "tiled", markdown(doc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
