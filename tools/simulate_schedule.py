"""Predict a tiled build's wall time on W workers from the task durations its build record keeps
(a scheduler simulation: issue 19 allows it for the 16-core figures where no such machine is at hand).

The model is a sequence of stages (the build's phases, in order). A stage runs the parent's own
work (``parent_seconds``) while its tasks run on the workers; it ends when both are done, and the
next stage starts then. Tasks start when their dependencies are done, on the first free worker, in
priority order (list scheduling, largest first as the driver submits them). From a build record
(:func:`model_from_record`):

* a phase without tasks is the parent's alone: its wall seconds;
* a phase with tasks: the tasks are those that started in it (the record's task table), and the
  parent's share is its CPU seconds in that phase (its waits for the tasks are not work);
* tile orderings depend on their neighbours of a smaller colour (the order phase's colour classes;
  on the previous pass's orderings too when there are several passes), and the ready one with the
  longest chain of orderings waiting for it (its bottom level, from the recorded seconds) starts
  first, as the driver starts them (by the tiles' points);
* rounds inside a phase (:data:`AFTER`): the seam repair (``seam_repair``) waits for the seam
  links (``seam_links``), the merge's bands (``merge_band``) for the seam repair, the ranks' first
  round (``rank_band``) for the bands, their second
  round (``rank_block``) for the whole first, the radii's second round (``finish_band``) for the
  whole first (``radii_band``), the join of the band pieces for the tiles' pieces (``cover_tile``;
  ``pieces_tile`` in older records): its bands (``join_band``) first, then the join of their pairs
  (``join_task``; one task over every tile's shared points in older records); the write's bands wait for its first band
  (run alone: it decides the datasets' creation properties). The phases after the order are cover
  -> pieces (the join) -> radii -> permute (the buckets) -> write, each a stage (older records:
  the radii and the buckets inside the cover phase, the join beside them);
* ``rest``: seconds of the wall time the record does not cover (start-up, the write phase, the
  archive's commit), serial in the parent.

Assumptions (what the prediction does not capture):

* a task takes as long on W workers as it took when recorded: no contention for memory
  bandwidth, caches, disk or cores. On the lent 16-core machine the tree's CPU grew 13 % from 4
  to 16 workers (9 % at 8) with the same tasks; ``--slowdown 8:1.09,16:1.13`` replays that
  growth (every task that much longer, the parent's work not), off by default;
* the parent's phases take what they took when recorded, and no start-up, commit or transfer
  cost grows with the workers (a cluster's network is not modelled);
* it replays the record's tiles: a build planned for W workers cuts about TILES_PER_WORKER x W
  tiles (:data:`lodbuilder.build.tiled.plan.TILES_PER_WORKER`), so W workers are predicted from a
  record whose tiles were planned for W (a build with fewer workers but that tile size), not from
  one with fewer, larger tiles (whose colour chain bounds the order phase). Several archives, each
  at its own worker count, give the speed-ups between plans (:func:`compare`);
* durations measured on a loaded 2-core machine make every prediction an estimate: the tasks'
  CPU seconds (``--durations cpu``) stand for what a free core gives, and a loaded machine's
  CPU seconds are themselves higher (the same 128-tile build: 328 and 371 task CPU-s at load 0-5
  and 10); the calibration (the prediction at the measured worker count over the measured wall
  time) says how far to trust it.

Each predicted row has every stage's lower bounds (:func:`bounds`: work per worker, longest
chain of dependent tasks, the parent's own work): where a stage's seconds exceed its work per
worker, the schedule idles.

    python tools/simulate_schedule.py ARCHIVE [--scan NAME] [--rest SECONDS] [--workers 1,2,4,8,16] [--fifo]
    python tools/simulate_schedule.py PLANNED_FOR_4.h5 PLANNED_FOR_16.h5 --workers 4,16 --durations cpu
"""

from __future__ import annotations

import argparse
import heapq
import json
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

WORKERS = (1, 2, 4, 8, 16)


@dataclass
class Task:
    id: str
    seconds: float
    deps: list[str] = field(default_factory=list)
    priority: float | None = None  # larger first (default: seconds)


@dataclass
class Stage:
    name: str
    parent_seconds: float = 0.0
    tasks: list[Task] = field(default_factory=list)


def makespan(tasks: list[Task], workers: int, fifo: bool = False) -> float:
    """Wall time of ``tasks`` on ``workers`` workers by list scheduling: whenever a worker is free,
    it takes the ready task (all dependencies finished) of the highest priority (``fifo``: the one
    that became ready first, then the largest: a queue that takes every ready task as it comes,
    largest first among those ready at once, as the order phase did before it kept its tasks to
    the workers' count). Dependencies on
    tasks not in the list count as finished."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    ids = {t.id for t in tasks}
    if len(ids) != len(tasks):
        raise ValueError("task ids must be unique")
    waiting = {t.id: {d for d in t.deps if d in ids} for t in tasks}
    users: dict[str, list[str]] = {}
    for t in tasks:
        for d in waiting[t.id]:
            users.setdefault(d, []).append(t.id)
    by_id = {t.id: t for t in tasks}
    rank = {t.id: i for i, t in enumerate(sorted(tasks, key=lambda t: (-(t.seconds if t.priority is None or fifo
                                                                            else t.priority), t.id)))}
    ready = [(0.0 if fifo else 0, rank[i], i) for i, w in waiting.items() if not w]
    heapq.heapify(ready)
    running: list[tuple[float, str]] = []  # (end time, id)
    now, free, done = 0.0, workers, 0
    while done < len(tasks):
        while free and ready:
            *_, i = heapq.heappop(ready)
            heapq.heappush(running, (now + by_id[i].seconds, i))
            free -= 1
        if not running:
            raise ValueError("the task dependencies have a cycle")
        now, i = heapq.heappop(running)
        finished = [i]
        while running and running[0][0] <= now:
            finished.append(heapq.heappop(running)[1])
        for i in finished:
            free += 1
            done += 1
            for u in users.get(i, []):
                waiting[u].discard(i)
                if not waiting[u]:
                    heapq.heappush(ready, (now if fifo else 0, rank[u], u))
    return now


def _scaled(tasks: list[Task], factor: float) -> list[Task]:
    return tasks if factor == 1.0 else [Task(t.id, t.seconds * factor, t.deps, t.priority) for t in tasks]


def simulate(stages: list[Stage], workers: int, fifo: bool = False, slowdown: float = 1.0) -> dict[str, float]:
    """Seconds of each stage and of the whole on ``workers`` workers (``fifo``: see :func:`makespan`;
    ``slowdown``: every task takes that many times its seconds, the parent's work as recorded)."""
    out = {s.name: max(s.parent_seconds, makespan(_scaled(s.tasks, slowdown), workers, fifo)) for s in stages}
    out["total"] = sum(out.values())
    return out


def critical_path(tasks: list[Task]) -> float:
    """The longest chain of dependent tasks' seconds (no number of workers finishes them sooner)."""
    from lodbuilder.build.tiled.pool import bottom_levels

    ids = {t.id for t in tasks}
    level = bottom_levels({t.id: [d for d in t.deps if d in ids] for t in tasks}, {t.id: t.seconds for t in tasks})
    return max(level.values(), default=0.0)


def bounds(stages: list[Stage], workers: int, slowdown: float = 1.0) -> dict[str, dict[str, float]]:
    """Each stage's lower bounds on ``workers`` workers: its tasks' seconds over the workers
    (``work``), its longest chain of dependent tasks (``path``) and the parent's own work
    (``parent``). A stage's simulated seconds above the largest of them is the scheduler's idle
    time; a path above the work is idle that no order of the same tasks removes."""
    return {s.name: {"work": round(slowdown * sum(t.seconds for t in s.tasks) / workers, 2),
                     "path": round(slowdown * critical_path(s.tasks), 2), "parent": round(s.parent_seconds, 2)}
            for s in stages if s.tasks}


def predict(model: dict[str, Any], workers: list[int] | tuple[int, ...] = WORKERS, fifo: bool = False,
            slowdown: dict[int, float] | None = None) -> dict[str, Any]:
    """Predicted wall seconds and speed-up over 1 worker for each worker count (``model`` from
    :func:`model_from_record`), with each stage's lower bounds (:func:`bounds`) and the model's
    notes (``fifo``: see :func:`makespan`; ``slowdown``: worker count -> factor on its tasks'
    seconds, for tasks that run slower side by side; none by default)."""
    stages = model["stages"]
    slow = {w: float((slowdown or {}).get(w, 1.0)) for w in sorted({1, *workers})}
    walls = {w: simulate(stages, w, fifo, slow[w]) for w in slow}
    one = walls[1]["total"]
    rows = [{"workers": w, "wall_seconds": round(walls[w]["total"], 2),
             "speedup_over_1": round(one / walls[w]["total"], 3) if walls[w]["total"] else None,
             **({"slowdown": slow[w]} if slow[w] != 1.0 else {}),
             "stages": {k: round(v, 2) for k, v in walls[w].items() if k != "total"},
             "bounds": bounds(stages, w, slow[w])} for w in workers]
    serial = sum(s.parent_seconds for s in stages if not s.tasks)
    out = {"predicted": rows, "serial_parent_seconds": round(serial, 2),
           "task_seconds": round(sum(t.seconds for s in stages for t in s.tasks), 2),
           "notes": model.get("notes", [])}
    if model.get("measured"):
        m = model["measured"]
        sim = simulate(stages, m["workers"], fifo)["total"]
        out["calibration"] = {"workers": m["workers"], "measured_wall_seconds": m["wall_seconds"],
                              "predicted_wall_seconds": round(sim, 2),
                              "predicted_over_measured": round(sim / m["wall_seconds"], 3)}
    return out


# ------------------------------------------------------------------------------------ build records

_ORDER = re.compile(r"^order\.(\d+)\.(\d+)$")
#: task kinds that start only when every task of the listed kinds in their phase is done
AFTER = {"seam_repair": ("seam_links",), "merge_band": ("seam_repair",), "rank_band": ("merge_band",), "rank_block": ("rank_band",),
         "finish_band": ("radii_band",), "radii_band": ("cover_tile",), "join_band": ("cover_tile", "pieces_tile"),
         "join_task": ("join_band", "cover_tile", "pieces_tile")}
#: the write's first band (its task table piece: the first write_band to start) before the others
FIRST_BAND = "write_band"


def _neighbours(boxes: list[list[float]], halo: float) -> list[list[int]]:
    """The tiles whose boxes come within ``halo`` of each other (as lodbuilder.build.tiled.plan)."""
    out = []
    for i, a in enumerate(boxes):
        out.append([j for j, b in enumerate(boxes) if j != i and all(
            b[k] <= a[k + 3] + halo and b[k + 3] >= a[k] - halo for k in range(3))])
    return out


def _order_deps(piece: str, colour: list[int], nbrs: list[list[int]]) -> list[str]:
    """A tile ordering's dependencies, as the driver's order phase has them."""
    m = _ORDER.match(piece)
    if not m or not colour:
        return []
    t, p = int(m.group(1)), int(m.group(2))
    deps = [(p, u) if colour[u] < colour[t] else (p - 1, u) for u in nbrs[t]] + [(p - 1, t)]
    return [f"order.{u}.{q}" for q, u in deps if q >= 1]


def _round_deps(row: dict[str, Any], phase: list[dict[str, Any]]) -> list[str]:
    """A task's dependencies on the earlier rounds of its phase (see :data:`AFTER`)."""
    before = AFTER.get(row["kind"], ())
    deps = [r["piece"] for r in phase if r["kind"] in before]
    if row["kind"] == "write_band" and row["piece"] != FIRST_BAND:
        deps.append(FIRST_BAND)
    return deps


def _critical_first(tasks: list[Task]) -> None:
    """The tile orderings' priorities: their bottom levels (as the driver's order phase, see
    :func:`lodbuilder.build.tiled.pool.bottom_levels`), from their seconds."""
    from lodbuilder.build.tiled.pool import bottom_levels

    order = {t.id: t for t in tasks if _ORDER.match(t.id)}
    level = bottom_levels({i: [d for d in t.deps if d in order] for i, t in order.items()},
                          {i: t.seconds for i, t in order.items()})
    for i, t in order.items():
        t.priority = level[i]


def model_from_record(rec: dict[str, Any], rest: float = 0.0, measured: dict[str, Any] | None = None,
                      durations: str = "wall") -> dict[str, Any]:
    """The stages of a tiled build's record (``build`` of its scan: ``phase_seconds`` and
    ``phase_order``, ``parent_cpu_seconds``, ``tasks``, ``tiled``); ``rest``: serial seconds the
    record does not cover; ``measured``: ``{"workers", "wall_seconds"}`` of the run, for the
    calibration. ``durations="cpu"``: every task and every parent phase takes its CPU seconds (what
    a machine with a free core for each would give, if the work is CPU-bound: a build measured on a
    loaded machine waited for cores; ``rest`` is then the parent's CPU outside the phases)."""
    if durations not in ("wall", "cpu"):
        raise ValueError(f"durations must be wall or cpu, got {durations!r}")
    secs = rec.get("phase_seconds") or {}
    phases = {k: secs[k] for k in rec.get("phase_order") or secs}  # (the stored record sorts its keys)
    cpu = rec.get("parent_cpu_seconds") or {}
    table = rec.get("tasks") or {"columns": [], "rows": []}
    rows = [dict(zip(table["columns"], r, strict=True)) for r in table["rows"]]
    tiled = rec.get("tiled") or {}
    colour = list(tiled.get("tile_colours") or [])
    nbrs = _neighbours(tiled.get("tile_boxes") or [], float(tiled.get("halo") or 0.0)) if colour else []
    what = "wall" if durations == "wall" else "CPU"
    notes = [f"predicted by list scheduling of the recorded task {what} seconds (tools/simulate_schedule.py), not "
             "measured: tasks are assumed to take as long as they did when recorded"]
    stages, t0 = [], 0.0
    resumed = [r for r in rows if r["start"] < 0]
    if resumed:
        notes.append(f"{len(resumed)} task(s) were done before a resume: left out")
    key = "seconds" if durations == "wall" else "cpu_seconds"
    for name, secs in phases.items():
        t1 = t0 + float(secs)
        mine = [r for r in rows if t0 <= r["start"] < t1 or (name == list(phases)[-1] and r["start"] >= t1)]
        tasks = [Task(r["piece"], float(r[key]), _order_deps(r["piece"], colour, nbrs) + _round_deps(r, mine))
                 for r in mine]
        _critical_first(tasks)
        parent = float(secs) if not tasks and durations == "wall" else float(cpu.get(name, 0.0))
        stages.append(Stage(name, parent, tasks))
        t0 = t1
    if rest > 0:
        stages.append(Stage("rest", float(rest)))
        notes.append(f"{rest:.2f} s outside the record's phases (start-up, write, commit) counted as serial "
                     "parent work")
    return {"stages": stages, "notes": notes, "measured": measured}


def measured_idle(rec: dict[str, Any], workers: int) -> dict[str, Any]:
    """Where the measured run's workers waited, from its task table (not a prediction): for each
    phase its wall seconds, the worker-seconds its tasks ran (wall and CPU; a task counts in the
    phases its run overlaps) and the worker-seconds no task ran (``idle``: ``workers`` x wall
    minus the tasks'), the seconds until its first task started and from the first worker to
    finish its last task of the phase to the phase's end (``tail``); and the tasks' wall seconds
    beyond their CPU seconds (``waiting``: for cores, disk or memory). The phases' idle time is
    what a speed-up short of the worker count is made of, with the waiting."""
    secs = rec.get("phase_seconds") or {}
    table = rec.get("tasks") or {"columns": [], "rows": []}
    rows = [dict(zip(table["columns"], r, strict=True)) for r in table["rows"] if r]
    rows = [r for r in rows if r["start"] >= 0]  # (a resumed build's earlier tasks: not in this run)
    out: dict[str, Any] = {}
    t0 = 0.0
    for name in rec.get("phase_order") or secs:
        t1 = t0 + float(secs[name])
        busy = sum(max(0.0, min(r["start"] + r["seconds"], t1) - max(r["start"], t0)) for r in rows)
        mine = [r for r in rows if t0 <= r["start"] < t1]
        ends: dict[Any, float] = {}
        for r in mine:
            ends[r["pid"]] = max(ends.get(r["pid"], 0.0), r["start"] + r["seconds"])
        out[name] = {"wall": round(t1 - t0, 2), "busy": round(busy, 2), "idle": round(workers * (t1 - t0) - busy, 2),
                     "first_task_after": round(min((r["start"] for r in mine), default=t1) - t0, 2),
                     "tail": round(t1 - min(ends.values()), 2) if len(ends) == workers else round(t1 - t0, 2),
                     "waiting": round(sum(r["seconds"] - r["cpu_seconds"] for r in mine), 2)}
        t0 = t1
    return {"by_phase": out, "idle": round(sum(p["idle"] for p in out.values()), 2),
            "waiting": round(sum(p["waiting"] for p in out.values()), 2)}


#: task kinds whose work does not depend on the tile plan (per read block or band of positions):
#: their CPU seconds in two records of one survey differ by the machine's load alone
REFERENCE_KINDS = ("read_block", "survey_block", "bucket_block", "write_band", "rank_band", "rank_block")


def reference_seconds(rec: dict[str, Any]) -> float:
    """The CPU seconds of a record's tasks of :data:`REFERENCE_KINDS`."""
    table = rec.get("tasks") or {"columns": [], "rows": []}
    rows = [dict(zip(table["columns"], r, strict=True)) for r in table["rows"] if r]
    return sum(float(r["cpu_seconds"]) for r in rows if r["kind"] in REFERENCE_KINDS and r["start"] >= 0)


def compare(models: list[dict[str, Any]], workers: list[int], fifo: bool = False,
            slowdown: dict[int, float] | None = None, references: list[float] | None = None) -> dict[str, Any]:
    """Each model (a record planned for its worker count) predicted at its own worker count
    (``workers``, one per model), and the speed-ups over the first: the figure a build planned for
    W workers gives beside one planned for the first count (the tile plans differ). With
    ``references`` (each record's :func:`reference_seconds`), every record's tasks are scaled to
    the first record's load (records measured at different loads of a shared machine)."""
    if len(models) != len(workers):
        raise ValueError(f"{len(models)} record(s) need as many worker counts, got {len(workers)}")
    if references is not None and not all(r > 0 for r in references):
        raise ValueError(f"every record needs tasks of {', '.join(REFERENCE_KINDS)} to be normalised")
    runs = []
    for i, (m, w) in enumerate(zip(models, workers, strict=True)):
        load = references[0] / references[i] if references else 1.0
        slow = {w: load * float((slowdown or {}).get(w, 1.0))}
        runs.append({"workers": w, **predict(m, [w], fifo, slow), **({"load_scale": round(load, 3)} if references else {})})
    first = runs[0]["predicted"][0]["wall_seconds"]
    for r in runs:
        wall = r["predicted"][0]["wall_seconds"]
        r["speedup_over_first"] = round(first / wall, 3) if wall else None
    return {"runs": runs}


def _slowdown(text: str | None) -> dict[int, float]:
    """``"8:1.09,16:1.13"`` -> {8: 1.09, 16: 1.13}."""
    out = {}
    for part in filter(None, (text or "").split(",")):
        w, _, f = part.partition(":")
        out[int(w)] = float(f)
    return out


def _record(path: Path, scan: str | None) -> dict[str, Any]:
    import lodbuilder

    with lodbuilder.open_archive(path) as arc:
        return dict(arc.scan(scan or arc.scans[0]).build)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("archive", type=Path, nargs="+",
                   help="an archive with a tiled scan (its build record); several: each predicted at its own "
                        "worker count (--workers, one per archive), with the speed-ups over the first")
    p.add_argument("--scan", help="the scan's name (default: the archive's only scan)")
    p.add_argument("--rest", type=float, default=0.0,
                   help="serial seconds not in the record (the run's wall time minus its phases)")
    p.add_argument("--workers", default=None, help="worker counts (default 1,2,4,8,16)")
    p.add_argument("--durations", choices=("wall", "cpu"), default="wall",
                   help="replay the tasks' wall seconds, or their CPU seconds (a loaded machine's record)")
    p.add_argument("--slowdown", default=None,
                   help="W:F,...: tasks take F times their recorded seconds on W workers (e.g. 16:1.13, the tree CPU "
                        "growth measured from 4 to 16 workers); none by default")
    p.add_argument("--normalise", action="store_true",
                   help="several archives: scale each record's tasks to the first's load (by the CPU seconds of the "
                        "task kinds that do not depend on the tile plan, REFERENCE_KINDS)")
    p.add_argument("--fifo", action="store_true",
                   help="ready tasks in the order they became ready (the order phase before it started the "
                        "critical path first)")
    args = p.parse_args(argv)
    workers = [int(w) for w in (args.workers or ",".join(map(str, WORKERS))).split(",")]
    recs = [_record(a, args.scan) for a in args.archive]
    models = [model_from_record(r, args.rest, durations=args.durations) for r in recs]
    slow = _slowdown(args.slowdown)
    out = (predict(models[0], workers, args.fifo, slow) if len(models) == 1
           else compare(models, workers, args.fifo, slow, [reference_seconds(r) for r in recs] if args.normalise else None))
    from benchdoc import commit

    head = {"tool": "simulate_schedule", "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "commit": commit(),
            "command": " ".join(["python", "tools/simulate_schedule.py", *(sys.argv[1:] if argv is None else argv)]),
            "records": [str(a) for a in args.archive], "kind": "prediction (not measured)"}
    print(json.dumps({**head, **out}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
