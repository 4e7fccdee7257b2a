"""Benchmark survey-scale tiled builds (issue 19's targets): prints one JSON document and writes it
to docs/bench/bench_survey.json.

``lodbuilder build`` runs as a subprocess on each survey given (one LAS/LAZ file, or a directory of
them ordered as one surface: ``--joint``) once per executor and worker count. For each run:

* wall seconds and points per second;
* CPU seconds of the whole process tree (every descendant's user + system time, sampled from /proc
  every ``--interval`` seconds: a process's last interval is missed) and of the parent alone (its
  exact getrusage at exit), the parent's share (target <= 3 %) and its CPU per phase (build record);
* peak RSS of the process tree (the sum over the tree at each sample) and its ratio to
  ``--max-memory`` (target <= 1.1: 3.3 GB at 3GB);
* the largest size on disk of the work directory over the run (sampled likewise) beside the
  archive's size (target <= 2 x), its kinds of work file at that moment, its largest size in each
  phase (``peak_work_by_phase``, with the three largest kinds), and the largest size of everything
  the build wrote;
* the build record's phase seconds, tile count and per-task table summed by kind (tasks, seconds,
  CPU seconds, workers seen, the largest peak resident size of a task's worker while it ran:
  ``peak_rss_by_kind``, largest first), and the scheduler simulation's prediction for 1-16 workers
  (tools/simulate_schedule.py) from that record: from the tasks' wall seconds (``simulation``,
  calibrated against the run) and from their CPU seconds (``simulation_cpu``: a free core for every
  process, the figure to read on a loaded machine) and, measured, where the workers waited
  (``measured_idle``: each phase's idle worker-seconds, first task, tail and the tasks' wall
  beyond their CPU);
* the speed-up of each worker count over 1 worker (target: 2 workers >= 1.9 x), and Dask
  LocalCluster over the process pool at equal workers (target <= 1.2).

Executors: ``pool`` (``--workers N``), ``dask`` (``--dask-local N``, work files beside the archive)
and ``dask-s3`` (``--dask-local N --work-dir s3://...``: the work files on moto's S3 server, started
by this program on 127.0.0.1 and found by the build through fsspec's ``FSSPEC_S3_*`` variables; the
server's own CPU is this program's, outside the measured tree, and ``peak_work_dir_bytes`` counts
the local disk only; ``bench_process_cpu_seconds``: this program's CPU during the run, the sampler's
and, for ``dask-s3``, the S3 server's, which competes with the build for the machine's cores;
``s3``: the server's requests by kind and by work-file family, with the bytes each way).

    python tools/make_survey.py --nx 4 --ny 4 -o /work/bench_data/survey_4x4.laz
    python tools/make_survey.py --nx 4 --ny 4 --files /work/bench_data/survey_4x4
    python tools/bench_survey.py /work/bench_data/survey_4x4.laz /work/bench_data/survey_4x4 \\
        --workers 1,2 --executor pool,dask --max-memory 1.5GB
    python tools/bench_survey.py /tmp/sstore/survey_4x4.laz --workers 2 --executor pool,dask-s3

``--seam-rounds``: every build with ``--seam-rounds`` (the tiles in radius rounds; ``rounds``: the
build record's plan of them, its owners' estimated and measured state bytes).

``--plan-workers W``: each build planned as for W workers while it runs on ``--workers`` (the merge's
bands of keys, and the tiles unless ``--tile-points`` gives them), so that the simulation's W-worker
figure replays a W-worker plan; the 21.56M survey as for 4 and for 16 workers on this 2-core machine
(128 tiles for 16: ``--tile-points`` would replace the plan's own tile size, and 168,000, the size
earlier records used, makes 197 tiles, a plan no 16-worker build makes). The 16-worker figure over the
4-worker one, each from its own record, is the speed-up between the plans:

    python tools/bench_survey.py /work/big/survey_14x14 --workers 2 --max-memory 16GB --no-warm-up \
        --plan-workers 4 --append
    python tools/bench_survey.py /work/big/survey_14x14 --workers 2 --max-memory 16GB --no-warm-up \
        --plan-workers 16 --append

Other inputs at the same settings (``--kind`` says what they are in the record), the synthetic inputs
of tools/bench_inputs.py and tools/make_fragmented.py built in tiles:

    python tools/bench_inputs.py uneven 2000000 -o /work/bench_data/uneven_2M.npy
    python tools/bench_survey.py /work/bench_data/uneven_2M.npy --workers 2 --max-memory 1.2GB --append \
        --kind "synthetic: tools/bench_inputs.py uneven"

Timings depend on the machine and its load (the load average before and after each run is in the
JSON): on a shared machine, compare runs of one invocation only.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
OUT = ROOT / "docs" / "bench" / "bench_survey.json"

#: the targets of issue 19 that one machine can check
TARGETS = {"parent_cpu_share_max": 0.03, "speedup_2_over_1_min": 1.9, "work_over_archive_max": 2.0,
           "dask_over_pool_max": 1.2, "rss_over_max_memory_max": 1.1, "speedup_16_over_4_min": 3.4,
           "points_per_second_16_min": 1.5e6}
EXECUTORS = ("pool", "dask", "dask-s3")
BUCKET = "lodbuilder-bench"

#: the child: ``lodbuilder build`` in this process, its own CPU (getrusage) written at exit.
#: ``BENCH_SURVEY_TILE_POINTS`` (``--tile-points``) orders the survey tiled in tiles of about that many points, as
#: ``_tile_points`` does: the decimated copy and its head as the plan makes them (it capped the copy at the tile
#: size too, which made the head of a survey's plan of small tiles some 5 x smaller and its halo twice as wide).
#: ``BENCH_SURVEY_PLAN_WORKERS`` (``--plan-workers W``) plans the build as for W workers while it runs on
#: ``--workers``: the merge's bands of keys sized for W (``plan.merge_band_rows``) and, without
#: ``--tile-points``, the tiles too, so that the scheduler simulation's W-worker figure replays a W-worker plan.
CHILD = """
import atexit, json, os, resource, sys
def _rusage():
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(os.environ["BENCH_SURVEY_RUSAGE"], "w") as f:
        json.dump({"self_cpu": s.ru_utime + s.ru_stime, "children_cpu": c.ru_utime + c.ru_stime,
                   "self_maxrss": s.ru_maxrss * 1024}, f)
atexit.register(_rusage)
tp = os.environ.get("BENCH_SURVEY_TILE_POINTS")
if tp:
    from lodbuilder.build.tiled import plan
    plan.needs_tiling = lambda *a, **k: True
    plan.balanced_tile_points = lambda *a, **k: int(tp)
pw = os.environ.get("BENCH_SURVEY_PLAN_WORKERS")
if pw:
    from lodbuilder.build.tiled import plan
    rows, tiles = plan.merge_band_rows, plan.balanced_tile_points
    plan.merge_band_rows = lambda n, parallel, most: rows(n, int(pw), most)
    if not tp:
        plan.needs_tiling = lambda *a, **k: True
        plan.balanced_tile_points = lambda n, parallel, fits: tiles(n, int(pw), fits)
from lodbuilder.cli.main import main
sys.exit(main(sys.argv[1:]))
"""


# ------------------------------------------------------------------------------------ sampling

def _stat(pid: int) -> tuple[int, float, int] | None:
    """(start time in ticks, CPU seconds, resident bytes) of process ``pid`` from /proc/<pid>/stat
    (its resident size is VmRSS of /proc/<pid>/status), None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return int(fields[19]), (int(fields[11]) + int(fields[12])) / TICK, int(fields[21]) * PAGE
    except (OSError, IndexError, ValueError):
        return None


def _children(pid: int) -> list[int] | None:
    """The child processes of ``pid`` (/proc/<pid>/task/*/children), None where the kernel has no
    such file."""
    out: list[int] = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []
    for t in tasks:
        try:
            with open(f"/proc/{pid}/task/{t}/children") as f:
                out += [int(x) for x in f.read().split()]
        except FileNotFoundError:
            if not os.path.exists(f"/proc/{pid}/task/{t}"):
                continue  # (the thread ended)
            return None
        except OSError:
            continue
    return out


def _all_children() -> dict[int, list[int]]:
    """Every process's children, from the parent pid of every process (one read per process)."""
    kids: dict[int, list[int]] = {}
    for e in os.listdir("/proc"):
        if e.isdigit():
            try:
                with open(f"/proc/{e}/stat") as f:
                    kids.setdefault(int(f.read().rsplit(")", 1)[1].split()[1]), []).append(int(e))
            except (OSError, IndexError, ValueError):
                pass
    return kids


TICK = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")


def tree(root: int) -> tuple[dict[tuple[int, int], float], int]:
    """The descendants of ``root`` (``root`` included): {(pid, start): CPU seconds}, summed RSS.
    Walks the tree's own children files (a few processes; reading every process of a shared
    machine took 2.5 ms a sample, 2.5 CPU-s in a 200 s run competing with the build)."""
    table: dict[int, list[int]] | None = None
    todo, cpu, rss = [root], {}, 0
    while todo:
        p = todo.pop()
        st = _stat(p)
        if st is None:
            continue
        kids = _children(p)
        if kids is None:  # (no children files: every process's parent instead)
            table = _all_children() if table is None else table
            kids = table.get(p, [])
        todo += kids
        cpu[(p, st[0])] = st[1]
        rss += st[2]
    return cpu, rss


def disk_bytes(path: Path, by_kind: dict[str, int] | None = None) -> tuple[int, int]:
    """Bytes allocated on disk under ``path`` in ``*.work`` directories, and in all (one walk);
    ``by_kind`` (when given) receives the work directories' bytes per kind of work file (a name's
    first part: ``raw``, ``cover``, ``bucket``, ...)."""
    work = total = 0
    for dirpath, _, files in os.walk(path):
        in_work = ".work" in Path(dirpath).relative_to(path).as_posix()
        for name in files:
            try:
                size = os.lstat(os.path.join(dirpath, name)).st_blocks * 512
            except OSError:
                continue
            total += size
            if in_work:
                work += size
                if by_kind is not None:
                    kind = name.split(".")[0] + (".tmp" if name.endswith(".tmp") else "")
                    by_kind[kind] = by_kind.get(kind, 0) + size
    return work, total


class Sampler(threading.Thread):
    """Samples a process tree and a directory every ``interval`` seconds until :meth:`stop`; the
    directory less often where its walk is dear (a survey's work directory holds thousands of
    files, and this process's CPU competes with the build's workers for the machine's cores): one
    walk gives both its sizes, and the next waits until the walks have taken at most DISK_SHARE of
    the time (9,684 files: 36 ms a walk, one every 1.8 s, where two walks every 0.2 s took 37 % of a
    core; a small directory is walked at every sample). At 5 % the walks took about 4 CPU-s of a
    200 s 2-worker build of the 21.56M survey, half a per cent of its wall time on 2 cores; the work
    directory's peak lasts tens of seconds (the write's buckets and chunks)."""

    DISK_SHARE = 0.02

    def __init__(self, pid: int, where: Path, interval: float) -> None:
        super().__init__(daemon=True)
        self.pid, self.where, self.interval = pid, where, interval
        self.cpu: dict[tuple[int, int], float] = {}
        self.peak_rss = self.peak_work = self.peak_all = self.samples = 0
        self.processes_max = 0
        self.peak_work_by_kind: dict[str, int] = {}  # the work directory's bytes per kind at its peak
        self.peak_work_at = 0.0  # seconds after the start
        self.timeline: list[tuple[float, int, dict[str, int]]] = []  # (epoch seconds, work bytes, by kind)
        self.t0 = time.perf_counter()
        self.disk_next = -math.inf  # (when the directory may be walked again)
        self._halt = threading.Event()

    def sample(self) -> None:
        cpu, rss = tree(self.pid)
        for k, v in cpu.items():
            self.cpu[k] = max(self.cpu.get(k, 0.0), v)
        self.peak_rss = max(self.peak_rss, rss)
        self.processes_max = max(self.processes_max, len(cpu))
        self.samples += 1
        now = time.perf_counter()
        if now < self.disk_next:
            return
        kinds: dict[str, int] = {}
        work, total = disk_bytes(self.where, kinds)
        self.disk_next = now + (time.perf_counter() - now) / self.DISK_SHARE
        if work > self.peak_work:
            self.peak_work, self.peak_work_by_kind = work, kinds
            self.peak_work_at = now - self.t0
        self.timeline.append((time.time(), work, kinds))
        self.peak_all = max(self.peak_all, total)

    def run(self) -> None:
        while not self._halt.is_set():
            self.sample()
            self._halt.wait(self.interval)

    def stop(self) -> None:
        self._halt.set()
        self.join()


# ------------------------------------------------------------------------------------ one run

def _record(archive: Path, name: str) -> dict[str, Any]:
    import lodbuilder

    with lodbuilder.open_archive(archive) as arc:
        b = dict(arc.scan(name).build)
    b.get("tiled", {}).pop("guarantees", None)
    return b


def task_summary(tasks: dict[str, Any] | None) -> dict[str, Any]:
    """The build record's task table summed by kind: tasks, wall and CPU seconds, the largest task,
    and how many worker processes ran them."""
    if not tasks:
        return {}
    cols = tasks["columns"]
    rows = [dict(zip(cols, r, strict=True)) for r in tasks["rows"]]
    out: dict[str, Any] = {}
    for r in rows:
        k = out.setdefault(r["kind"], {"tasks": 0, "seconds": 0.0, "cpu_seconds": 0.0, "largest_seconds": 0.0,
                                       "peak_rss_max": None})
        k["tasks"] += 1
        k["seconds"] += r["seconds"]
        k["cpu_seconds"] += r["cpu_seconds"]
        k["largest_seconds"] = max(k["largest_seconds"], r["seconds"])
        if r.get("peak_rss") is not None:
            k["peak_rss_max"] = max(k["peak_rss_max"] or 0, int(r["peak_rss"]))
    for k in out.values():
        k.update({x: round(k[x], 3) for x in ("seconds", "cpu_seconds", "largest_seconds")})
    peaks = {kind: k["peak_rss_max"] for kind, k in out.items() if k["peak_rss_max"] is not None}
    return {"by_kind": out, "peak_rss_by_kind": dict(sorted(peaks.items(), key=lambda x: -x[1])),
            "workers_seen": len({r["pid"] for r in rows}),
            "task_seconds": round(sum(r["seconds"] for r in rows), 3),
            "task_cpu_seconds": round(sum(r["cpu_seconds"] for r in rows), 3)}


def request_kind(environ: dict[str, Any]) -> tuple[str, str]:
    """(kind, object) of an S3 request: kind GET / GET range / PUT / HEAD / LIST / DELETE / POST ...;
    object: the key below the run's prefix with digits as ``#`` (a work file's family)."""
    import re

    method, query = environ.get("REQUEST_METHOD", "?"), environ.get("QUERY_STRING", "")
    parts = environ.get("PATH_INFO", "").lstrip("/").split("/", 2)  # bucket, run, key
    key = parts[2] if len(parts) > 2 else ""
    if method == "GET" and not key:
        kind = "LIST"
    elif method == "GET" and "HTTP_RANGE" in environ:
        kind = "GET range"
    elif "uploadId" in query or "uploads" in query:
        kind = f"{method} multipart"
    else:
        kind = method
    return kind, re.sub(r"\d+", "#", re.sub(r"\.[0-9a-f]{12}$", ".<id>", key)) if key else ""


class RequestCounter:
    """A WSGI wrapper that counts the S3 server's requests and bytes by :func:`request_kind`."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self.lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        self.kinds: dict[str, list[int]] = {}  # kind -> [requests, bytes in, bytes out]
        self.objects: dict[str, list[int]] = {}  # family -> [requests, bytes in, bytes out]

    def __call__(self, environ: dict[str, Any], start_response: Any) -> Any:
        kind, obj = request_kind(environ)
        sent = int(environ.get("CONTENT_LENGTH") or 0)
        body = list(self.app(environ, start_response))
        got = sum(len(b) for b in body)
        with self.lock:
            for table, k in ((self.kinds, kind), (self.objects, f"{kind} {obj}")):
                row = table.setdefault(k, [0, 0, 0])
                row[0] += 1
                row[1] += sent
                row[2] += got
        return body

    def summary(self, top: int = 40) -> dict[str, Any]:
        with self.lock:
            kinds = {k: dict(zip(("requests", "bytes_in", "bytes_out"), v, strict=True)) for k, v in self.kinds.items()}
            objs = sorted(self.objects.items(), key=lambda kv: -kv[1][0])[:top]
        return {"requests": sum(k["requests"] for k in kinds.values()), "by_kind": kinds,
                "top_objects": {k: dict(zip(("requests", "bytes_in", "bytes_out"), v, strict=True)) for k, v in objs}}


class S3:
    """moto's S3 server on 127.0.0.1 with one bucket: the work store of the ``dask-s3`` runs. Its
    requests are counted (:class:`RequestCounter`: a run's ``s3``)."""

    def __init__(self) -> None:
        import logging

        import boto3
        from moto.moto_server import threaded_moto_server as tms
        from moto.server import ThreadedMotoServer

        logging.getLogger("werkzeug").setLevel(logging.WARNING)  # (the server's line per request)
        dispatcher = tms.DomainDispatcherApplication
        counters: list[RequestCounter] = []

        def counted(*a: Any, **k: Any) -> RequestCounter:
            counters.append(RequestCounter(dispatcher(*a, **k)))
            return counters[-1]

        tms.DomainDispatcherApplication = counted  # (the server's application, built in its thread)
        self.server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
        try:
            self.server.start()
        finally:
            tms.DomainDispatcherApplication = dispatcher
        self.counter = counters[0]
        host, port = self.server.get_host_and_port()
        endpoint = f"http://{host}:{port}"
        boto3.client("s3", endpoint_url=endpoint, aws_access_key_id="test", aws_secret_access_key="test",
                     region_name="us-east-1").create_bucket(Bucket=BUCKET)
        self.env = {"FSSPEC_S3_ENDPOINT_URL": endpoint, "FSSPEC_S3_KEY": "test", "FSSPEC_S3_SECRET": "test"}

    def stop(self) -> None:
        self.server.stop()


_S3: list[S3] = []


def _s3() -> S3:
    if not _S3:
        _S3.append(S3())
    return _S3[0]


def _executor_args(executor: str, workers: int, where: Path) -> tuple[list[str], dict[str, str]]:
    """The command line options and environment of a run on ``executor``."""
    if executor == "pool":
        return ["--workers", str(workers)], {}
    if executor == "dask":
        return ["--dask-local", str(workers)], {}
    s3 = _s3()
    return ["--dask-local", str(workers), "--work-dir", f"s3://{BUCKET}/{where.name}"], s3.env


def parse_bytes(text: str) -> int:
    from lodbuilder._resources import parse_bytes as parse

    return parse(text)


def worker_share(max_memory: str, workers: int) -> int:
    """The bytes of ``--max-memory`` the planner gives each worker (a task's peak, the worker's own
    footprint included, should stay below it: compare ``tasks.peak_rss_by_kind``)."""
    from lodbuilder.build.tiled.plan import worker_budget

    return worker_budget(parse_bytes(max_memory), workers)


def peaks_by_phase(rec: dict[str, Any], timeline: list[tuple[float, int, dict[str, int]]], archive_bytes: int
                   ) -> dict[str, Any]:
    """The work directory's largest size within each phase of the build record (its phases' seconds
    one after another from ``build_started``) over the archive's size, with its three largest kinds
    of work file at that moment: where the peak is, and what makes it."""
    t, out = rec.get("build_started"), {}
    if t is None or not archive_bytes:
        return {}
    for phase in rec.get("phase_order") or []:
        end = t + float(rec["phase_seconds"][phase])
        inside = [x for x in timeline if t <= x[0] < end]
        t = end
        if inside:
            _, work, kinds = max(inside, key=lambda x: x[1])
            top = sorted(kinds.items(), key=lambda x: -x[1])[:3]
            out[phase] = {"over_archive": round(work / archive_bytes, 3),
                          "largest": {k: round(v / archive_bytes, 3) for k, v in top}}
    return out


def run_build(inputs: list[Path], joint: str | None, executor: str, workers: int, max_memory: str, base: Path,
              interval: float, tile_points: int | None = None, keep: Path | None = None,
              build_args: tuple[str, ...] = (), plan_workers: int | None = None) -> dict[str, Any]:
    """One measured ``lodbuilder build`` of ``inputs`` (see the module), with ``build_args`` more."""
    where = Path(tempfile.mkdtemp(prefix=f"{executor}{workers}_", dir=base))
    archive = where / "survey.h5"
    ex, ex_env = _executor_args(executor, workers, where)
    args = ["build", *map(str, inputs), "-o", str(archive), "--max-memory", max_memory, "--no-progress", "--json", *ex,
            *build_args]
    if joint:
        args += ["--joint", joint]
    env = dict(os.environ, BENCH_SURVEY_RUSAGE=str(where / "rusage.json"), **ex_env)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    if tile_points:
        env["BENCH_SURVEY_TILE_POINTS"] = str(tile_points)
    if plan_workers:
        env["BENCH_SURVEY_PLAN_WORKERS"] = str(plan_workers)
    load_before = os.getloadavg()[0]
    for s3 in _S3:
        s3.counter.reset()
    t0, c0 = time.perf_counter(), time.process_time()
    proc = subprocess.Popen([sys.executable, "-c", CHILD, *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=where)
    sampler = Sampler(proc.pid, where, interval)
    sampler.start()
    out, err = proc.communicate()
    wall = time.perf_counter() - t0
    sampler.stop()
    res: dict[str, Any] = {"executor": executor, "workers": workers, "plan_workers": plan_workers or workers,
                           "max_memory": max_memory,
                           "command": "lodbuilder " + " ".join(args), "rc": proc.returncode,
                           "wall_seconds": round(wall, 2), "load_before": load_before,
                           "bench_process_cpu_seconds": round(time.process_time() - c0, 2),
                           "load_after": os.getloadavg()[0], "samples": sampler.samples}
    if executor == "dask-s3":
        res["s3"] = _s3().counter.summary()
    if proc.returncode != 0:
        res["stderr"] = err[-2000:]
        shutil.rmtree(where, ignore_errors=True)
        return res
    rus = json.loads((where / "rusage.json").read_text())
    (scan,) = json.loads(out)["scans"]
    rec = _record(archive, scan["name"])
    parent_key = next((k for k in sampler.cpu if k[0] == proc.pid), None)
    others = sum(v for k, v in sampler.cpu.items() if k != parent_key)
    tree_cpu = others + rus["self_cpu"]
    n = int(scan["n_points"])
    archive_bytes = archive.stat().st_blocks * 512
    res.update({
        "n_points": n, "method": rec.get("method"), "points_per_second": round(n / wall),
        "cpu_tree_seconds": round(tree_cpu, 2), "cpu_parent_seconds": round(rus["self_cpu"], 2),
        "parent_cpu_share": round(rus["self_cpu"] / tree_cpu, 4) if tree_cpu else None,
        "cpu_parent_by_phase": rec.get("parent_cpu_seconds", {}),
        "processes_seen": len(sampler.cpu), "peak_rss_tree_bytes": sampler.peak_rss,
        "peak_rss_parent_bytes": rus["self_maxrss"],
        "rss_over_max_memory": round(sampler.peak_rss / parse_bytes(max_memory), 3),
        "worker_share_bytes": worker_share(max_memory, workers),
        "peak_work_dir_bytes": sampler.peak_work, "peak_written_bytes": sampler.peak_all,
        "archive_bytes": archive_bytes,
        "work_over_archive": round(sampler.peak_work / archive_bytes, 3) if archive_bytes else None,
        "peak_work_seconds": round(sampler.peak_work_at, 2),
        "peak_work_over_archive_by_kind": {k: round(v / archive_bytes, 3) for k, v in sorted(
            sampler.peak_work_by_kind.items(), key=lambda x: -x[1])} if archive_bytes else None,
        "peak_work_by_phase": peaks_by_phase(rec, sampler.timeline, archive_bytes),
        "phase_seconds": {k: rec["phase_seconds"][k] for k in rec.get("phase_order") or rec.get("phase_seconds", {})},
        "tiles": rec.get("tiled", {}).get("tiles"),
        "coarse_points": rec.get("tiled", {}).get("coarse_points"),
        "head_points": rec.get("tiled", {}).get("head_points"),
        "rounds": {k: v for k, v in (rec.get("tiled", {}).get("rounds") or {}).items() if k != "owner"} or None,
        "tasks": task_summary(rec.get("tasks")),
    })
    res["simulation"] = _simulate(rec, wall, workers)
    res["simulation_cpu"] = _simulate(rec, wall, workers, rus["self_cpu"])
    if rec.get("tasks"):
        from simulate_schedule import measured_idle

        res["measured_idle"] = measured_idle(rec, workers)
    if keep is not None:  # (to compare archives of two trees: the same survey gives the same datasets)
        keep.mkdir(parents=True, exist_ok=True)
        res["kept"] = str(shutil.move(str(archive), keep / f"{inputs[0].name}_{executor}{workers}.h5"))
    shutil.rmtree(where, ignore_errors=True)
    return res


def warm_up(base: Path, executor: str) -> float:
    """A small tiled build (a synthetic 30,000-point sheet in tiles of 6,000 points), not measured:
    numba's cache of every kernel a tiled build uses is filled (a first run on a fresh checkout
    compiles them for minutes) and the files are in the page cache. Returns its seconds."""
    import numpy as np

    from lodbuilder.io import write_points

    where = Path(tempfile.mkdtemp(prefix="warm_", dir=base))
    rng = np.random.default_rng(0)
    xy = rng.random((30_000, 2))
    sheet = write_points(where / "sheet.npy", np.c_[xy, 0.05 * np.sin(6 * xy[:, 0])])
    ex, ex_env = _executor_args(executor, 1, where)
    env = dict(os.environ, BENCH_SURVEY_RUSAGE=str(where / "rusage.json"), BENCH_SURVEY_TILE_POINTS="6000", **ex_env)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", CHILD, "build", str(sheet), "-o", str(where / "warm.h5"), "--max-memory",
                    "2GB", "--no-progress", "--json", *ex], env=env, capture_output=True, check=True, cwd=where)
    shutil.rmtree(where, ignore_errors=True)
    return round(time.perf_counter() - t0, 2)


def _simulate(rec: dict[str, Any], wall: float, workers: int, parent_cpu: float | None = None) -> dict[str, Any] | None:
    """The scheduler simulation of the run's record, calibrated on the run's own wall time: the
    tasks' wall seconds (the wall time outside the record's phases is serial parent work), or with
    ``parent_cpu`` (the parent's CPU seconds) their CPU seconds (the parent's CPU outside the phases
    is serial): what the run would take with a free core for every process."""
    if not rec.get("tasks"):
        return None
    from simulate_schedule import model_from_record, predict

    if parent_cpu is None:
        rest, durations = max(0.0, wall - sum(rec.get("phase_seconds", {}).values())), "wall"
    else:
        rest, durations = max(0.0, parent_cpu - sum(rec.get("parent_cpu_seconds", {}).values())), "cpu"
    return predict(model_from_record(rec, rest, {"workers": workers, "wall_seconds": round(wall, 2)}, durations))


# ------------------------------------------------------------------------------------ the document

def between_plans(surveys: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each worker count predicted from the record of a build planned for it (``--plan-workers``,
    its own tile size), for the surveys of the same inputs at the same budget: the W-worker figures
    of the W-worker plans' simulations (from the tasks' wall seconds and from their CPU seconds),
    points per second, and each plan's speed-up over the plan of the fewest workers, with issue
    19's targets (16 workers >= 3.4 x faster than 4, >= 1.5 M points/s). A plan's prediction for
    other worker counts replays tiles no such build cuts (the simulation's caveat)."""
    groups: dict[tuple, dict[int, dict[str, Any]]] = {}
    for sv in surveys:
        st = sv.get("settings") or {}
        run = next((r for r in sv.get("runs", []) if r.get("rc") == 0 and r.get("simulation")), None)
        if run is None or not st.get("plan_workers") or st.get("tile_points") or st.get("seam_rounds"):
            continue
        w = int(st["plan_workers"])
        pred = {}
        for sim, label in (("simulation", "wall_durations"), ("simulation_cpu", "cpu_durations")):
            row = next((p for p in (run.get(sim) or {}).get("predicted", []) if p["workers"] == w), None)
            if row is not None:
                pred[label] = row["wall_seconds"]
        if pred:
            group = (_same_input(sv["input"]), st.get("max_memory"))
            groups.setdefault(group, {})[w] = {"seconds": pred, "tiles": run.get("tiles"), "n_points": run["n_points"],
                                             "paths": sv["input"].get("paths")}
    out = []
    for (_, budget), plans in groups.items():
        if len(plans) < 2:
            continue
        ws = sorted(plans)
        first = plans[ws[0]]["seconds"]
        doc: dict[str, Any] = {"paths": plans[ws[0]]["paths"], "max_memory": budget, "plans": {}}
        for w in ws:
            sec = plans[w]["seconds"]
            doc["plans"][str(w)] = {"tiles": plans[w]["tiles"], "predicted_seconds": sec,
                                    "points_per_second": {k: round(plans[w]["n_points"] / v) for k, v in sec.items()},
                                    f"speedup_over_{ws[0]}": {k: round(first[k] / v, 3) for k, v in sec.items()
                                                              if k in first}}
        if 4 in plans and 16 in plans:
            four = plans[4]["seconds"]
            sp = {k: round(four[k] / v, 3) for k, v in plans[16]["seconds"].items() if k in four}
            pps = doc["plans"]["16"]["points_per_second"]
            doc["targets"] = {
                "speedup_16_over_4": {"worst": min(sp.values()), "target_min": TARGETS["speedup_16_over_4_min"],
                                      "met": min(sp.values()) >= TARGETS["speedup_16_over_4_min"]},
                "points_per_second_16": {"worst": min(pps.values()), "target_min": TARGETS["points_per_second_16_min"],
                                         "met": min(pps.values()) >= TARGETS["points_per_second_16_min"]}}
        out.append(doc)
    return out


def ratios(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Speed-ups over 1 worker per executor, Dask over the pool at equal workers, and the targets."""
    ok = [r for r in runs if r.get("rc") == 0]
    wall = {(r["executor"], r["workers"]): r["wall_seconds"] for r in ok}
    out: dict[str, Any] = {"speedup_over_1_worker": {}, "dask_over_pool": {}}
    for (ex, w), s in sorted(wall.items()):
        if (ex, 1) in wall and w != 1:
            out["speedup_over_1_worker"][f"{ex} {w}"] = round(wall[(ex, 1)] / s, 3)
        if ex.startswith("dask") and ("pool", w) in wall:
            out["dask_over_pool"][f"{ex} {w}"] = round(s / wall[("pool", w)], 3)
    checks = {}
    if ok:
        checks["parent_cpu_share"] = {"worst": max(r["parent_cpu_share"] for r in ok),
                                      "target_max": TARGETS["parent_cpu_share_max"]}
        checks["work_over_archive"] = {"worst": max(r["work_over_archive"] for r in ok),
                                       "target_max": TARGETS["work_over_archive_max"]}
        checks["rss_over_max_memory"] = {"worst": max(r["rss_over_max_memory"] for r in ok),
                                         "target_max": TARGETS["rss_over_max_memory_max"]}
    if "pool 2" in out["speedup_over_1_worker"]:
        checks["speedup_2_over_1"] = {"value": out["speedup_over_1_worker"]["pool 2"],
                                      "target_min": TARGETS["speedup_2_over_1_min"]}
    if out["dask_over_pool"]:
        checks["dask_over_pool"] = {"worst": max(out["dask_over_pool"].values()),
                                    "target_max": TARGETS["dask_over_pool_max"]}
    for c in checks.values():
        v = c.get("worst", c.get("value"))
        c["met"] = v <= c["target_max"] if "target_max" in c else v >= c["target_min"]
    out["targets"] = checks
    return out


#: what the surveys of tools/make_survey.py are (the default --kind)
SURVEY_KIND = "synthetic survey: the real autzen_trim.laz copied side by side (tools/make_survey.py)"


def describe_inputs(inputs: list[Path], kind: str = SURVEY_KIND) -> dict[str, Any]:
    files = [f for p in inputs for f in (sorted(p.iterdir()) if p.is_dir() else [p]) if f.is_file()]
    return {"paths": [str(p) for p in inputs], "files": len(files), "bytes": sum(f.stat().st_size for f in files),
            "kind": kind}


def _same_input(desc: dict[str, Any]) -> tuple:
    """What makes two surveys' inputs the same (file names, count and bytes; not their directory)."""
    return (tuple(Path(p).name for p in desc.get("paths", [])), desc.get("files"), desc.get("bytes"))


def _same_survey(sv: dict[str, Any]) -> tuple:
    """What makes two measured surveys the same: their inputs, the builds' settings (the budget, the
    plan's workers, the tile size, seam rounds; from the first run where a document lacks them) and
    the executors measured: a survey measured as for 16 workers and at --max-memory 3GB keeps both
    records, and a pool-only run does not replace a record of the pool against Dask."""
    run = (sv.get("runs") or [{}])[0]
    planned = run.get("plan_workers")
    settings = sv.get("settings") or {"max_memory": run.get("max_memory"), "tile_points": None, "seam_rounds": False,
                                      "plan_workers": None if planned == run.get("workers") else planned}
    executors = sorted({r.get("executor", "pool") for r in sv.get("runs", [])})
    return (_same_input(sv["input"]), tuple(sorted(settings.items())), tuple(executors))


def _commit() -> str:
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                          text=True).stdout.strip()


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("surveys", nargs="+", type=Path,
                   help="surveys to measure, each a LAS/LAZ file or a directory of them (ordered as one surface), "
                        "or any other scan file lodbuilder reads (say what it is with --kind)")
    p.add_argument("--joint", default="survey", help="the scan name of a directory's joint build (default survey)")
    p.add_argument("--workers", type=_ints, default=[1, 2], help="worker counts, comma-separated (default 1,2)")
    p.add_argument("--executor", default="pool",
                   help="comma-separated: pool, dask (Dask LocalCluster), dask-s3 (the same with its work files on "
                        "a local S3 server)")
    p.add_argument("--max-memory", default="3GB")
    p.add_argument("--interval", type=float, default=0.2, help="seconds between samples of /proc and the disk")
    p.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()), help="where the runs write")
    p.add_argument("--out", type=Path, default=OUT, help="the JSON file to write (default docs/bench/bench_survey.json)")
    p.add_argument("--no-warm-up", action="store_true", help="skip the unmeasured small build that fills numba's cache")
    p.add_argument("--append", action="store_true",
                   help="add the surveys to those of --out (one JSON for runs that need different executors); a "
                        "survey of the same files replaces its earlier runs")
    p.add_argument("--keep", type=Path, metavar="DIR",
                   help="keep each run's archive in DIR (as <survey name>_<executor><workers>.h5)")
    p.add_argument("--seam-rounds", action="store_true", help="build with --seam-rounds (the tiles in radius rounds)")
    p.add_argument("--tile-points", type=int, help=argparse.SUPPRESS)  # test knob: tiles of a small survey
    p.add_argument("--plan-workers", type=int, metavar="W",
                   help="plan the build as for W workers (its merge bands, and its tiles unless --tile-points) "
                        "while it runs on --workers: the simulation's W-worker figure then replays that plan")
    p.add_argument("--kind", default=SURVEY_KIND,
                   help="what the inputs are, for the record (default: the surveys of tools/make_survey.py; say "
                        "'synthetic' of any generated input)")
    args = p.parse_args(argv)
    executors = [e.strip() for e in args.executor.split(",") if e.strip()]
    if not executors or not set(executors) <= set(EXECUTORS):
        p.error(f"--executor takes {', '.join(EXECUTORS)} (comma-separated), got {args.executor!r}")
    doc: dict[str, Any] = {"benchmark": "bench_survey", "date": _dt.datetime.now().isoformat(timespec="seconds"),
                           "commit": _commit(), "command": " ".join(["python", "tools/bench_survey.py",
                                                                *(argv if argv is not None else sys.argv[1:])]),
                           "machine": platform.machine(), "cpus": os.cpu_count(),
                           "note": "the machine may be shared: see each run's load average before/after",
                           "surveys": []}
    args.work.mkdir(parents=True, exist_ok=True)
    if not args.no_warm_up:
        doc["warm_up_seconds"] = {ex: warm_up(args.work, ex) for ex in executors}
    for survey in args.surveys:
        joint = args.joint if survey.is_dir() else None
        sv: dict[str, Any] = {"input": describe_inputs([survey], args.kind), "joint": joint, "runs": [],
                              "settings": {"max_memory": args.max_memory, "plan_workers": args.plan_workers,
                                           "tile_points": args.tile_points, "seam_rounds": args.seam_rounds}}
        doc["surveys"].append(sv)
        for ex in executors:
            for w in args.workers:
                sv["runs"].append(run_build([survey], joint, ex, w, args.max_memory, args.work, args.interval,
                                            args.tile_points, args.keep,
                                            ("--seam-rounds",) if args.seam_rounds else (), args.plan_workers))
                print(json.dumps({k: v for k, v in sv["runs"][-1].items() if not k.startswith("simulation")}),
                      file=sys.stderr)
        sv.update(ratios(sv["runs"]))
    if args.append and args.out.exists():
        old = json.loads(args.out.read_text())
        doc["earlier"] = [*old.pop("earlier", []), {k: old[k] for k in ("date", "commit", "command") if k in old}]
        again = {_same_survey(sv) for sv in doc["surveys"]}  # a survey measured again: the new runs
        doc["surveys"] = [sv for sv in old.get("surveys", []) if _same_survey(sv) not in again] + doc["surveys"]
    doc["between_plans"] = between_plans(doc["surveys"])
    for s3 in _S3:
        s3.stop()
    text = json.dumps(doc, indent=1)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n")
    return 0 if all(r.get("rc") == 0 for sv in doc["surveys"] for r in sv["runs"]) else 1


if __name__ == "__main__":
    sys.exit(main())
