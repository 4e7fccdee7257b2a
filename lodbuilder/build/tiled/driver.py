"""The phases of a tiled build, run by the parent with an executor for the tile tasks.

Each phase leaves a marker (a JSON file) in the work directory when it is complete, and every
task output is renamed into place when finished, so a build that is killed at any moment resumes
at the first incomplete phase and redoes no finished tile.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import MemoryBudgetError
from ...progress import ProgressCallback, TaskCounts, report_tasks
from . import affinity as A
from . import layout as WL
from . import plan as P
from . import rounds as R
from .pieces import join_phase, reach
from .pool import bottom_levels, collect, result, submit
from .store import Store, as_store
from .sums import done as piece_done
from .sums import get_json, mark, put_json
from .survey import distribute_phase, plan_phase, read_phase
from .tasks import coarse_task, cover_tile, order_tile, parameters_task
from .timing import task_table
from .workdir import Spill

log = logging.getLogger(__name__)

#: the seam repair: a point waits while another tile's accepted point lies within SEAM_SPACING x key.
#: Across tiles every level's spacing is then at least SEAM_SPACING / (1 + SEAM_SPACING) x its radius
#: (0.2 at 0.25; 0.5 at 1.0), but a deferred point leaves its own tile's side covered only by the
#: other tile's point for a while (the tile ordered its later points as if it were there), so the
#: covering radius at equal size grows with it. 1M-point sheet in 4 tiles, one pass, covering at
#: 1 % / 0.1 % of the points over the in-memory build's, and the worst of 24 levels from the head to
#: 3 % (tools/bench_tiled.py --quality 1000000 --quality-tile-points 300000 --quality-workers 1):
#: 1.018 / 1.006 / 1.091 at 0.25, 1.243 / 1.146 / 1.416 at 1.0 (tiles that did not see each other
#: at all: 1.037 / 1.012 / 1.111 and 1.285 / 1.146 / 1.374). 0.25 removes the near-duplicates two
#: tiles make at a seam at little cost in covering.
SEAM_SPACING = 0.25
#: every tile is ordered this many times (see _order_passes). More passes make neighbouring tiles
#: agree at their seams, but slowly, and each costs a whole ordering of the scan (the order phase is
#: 83 of 132 s on the 21.6M-point survey): on the 1M-point sheet above, points of the first 5 % within
#: 0.5 x their level's radius of another tile's earlier point without the repair: 132 / 71 / 15 after
#: 1 / 2 / 3 passes; with the repair at 0.25 the covering at 1 % is 1.018 after 1 pass, 1.002 after 3
#: (--quality-passes).
TILE_PASSES = 1
#: the decimated copy aims at one point in COARSE_SHARE of the survey, at least COARSE_POINTS, at
#: most half what one worker orders within its budget (:func:`.plan.coarse_capacity`; the cells'
#: count overshoots the aim by 1.7 x on the surveys of tools/make_survey.py) and an eighth of the
#: survey; never fewer than COARSE_MIN (or every point): a band around fewer points is too coarse to
#: order a surface. A copy in proportion to the survey keeps the head's points per tile point, and
#: with them the tiles' grid phases (which start from the head), the same at every survey size: with
#: the copy held at 400,000 whatever the size, order_tile took 6.31 us a point of the 21.56M-point
#: survey and 7.97 of the 99M-point one at --max-memory 3GB (about 440 head points a tile against
#: 110). 54: the 21.56M survey's copy stays what it was. The coarse task grows with it (1.6 -> 5.2
#: CPU-s for a copy of 0.69M -> 2.84M points, serial: at 10^10 points the copy is capped by the
#: worker's memory and the head per tile shrinks again)
COARSE_SHARE = 54
COARSE_POINTS = 400_000
COARSE_MIN = 2_000
#: head size: points of the decimated copy's order per point of the head. Every tile's ordering
#: starts from the head points in its core and halo (marched as one front, one pop per voxel) and
#: goes on with one front per new point, each doubling of its points re-popping its voxels about
#: 0.6 times; a deeper head leaves the tiles fewer doublings and costs the coarse task little (below
#: its grid's hand-over the copy's order is the Euclidean tail). The halo stays as wide as the head's
#: at 1 in GRID_DECIMATION (narrower, the first tile levels after the head lose their exact radii: the
#: joint bunny's 4 mm level 1.11 x its true covering). On the 21.56M-point survey planned for 16
#: workers (197 tiles), 200 -> 50 took order_tile 124.8 -> 103.6 CPU-s, the coarse task 1.01 -> 1.00 s
#: (docs/benchmarks.md, "A deeper head")
HEAD_DECIMATION = 50
HEAD_MIN = 256
#: the coarse level's grid: at least the copy's order's estimated radius at one point in
#: GRID_DECIMATION of the copy (the head's at HEAD_DECIMATION 200, or at HEAD_MIN points where that
#: is more) over HEAD_RADIUS_VOXELS voxels (or the copy's own grid where that is coarser). The head
#: needs radii down to about 11-14 of the copy's spacings there; on the 21.56M-point survey's copy
#: (698,789 points) its own grid is 26.3, this one 69: CPU 7.8-8.1 -> 1.6-1.8 s (load 9, alternated),
#: the copy's covering by the head's prefixes (16 to 3,493 points) 0.98-1.07 x, mean 1.00 x, the own
#: grid's, and r_cut 157.3 against 159.0 (see docs/benchmarks.md, out-of-core builds)
GRID_DECIMATION = 200
HEAD_RADIUS_VOXELS = 3.0
#: the covering tasks add the head points within this many times the coarse level's certified
#: bound (the head's last radius and the copy's cell diagonal) of their tile: the head's levels down
#: from about a quarter of its size get exact radii (a halo as wide would hold every point)
HEAD_REACH = 2.0
#: halo width in units of the copy's estimated covering bound at 1 point in GRID_DECIMATION (its radius
#: there plus its cell diagonal): the stored radii are exact wherever the covering radius is below the
#: halo width (every level but the head's, which HEAD_REACH covers, and the first few after it)
HALO_FACTOR = 0.3


def _done(work: Store, phase: str) -> dict[str, Any] | None:
    """The marker of a finished phase whose files all check out (see :mod:`.sums`), else None."""
    return piece_done(work, phase)


def _order_passes(ex: cf.Executor, work: Store, name: str, by_size: list[P.Tile], nbrs: list[list[int]],
                  colour: list[int], passes: int, args: tuple, pieces: dict[str, Any], progress: ProgressCallback,
                  slots: int | None = None, lattice: list[float] | None = None,
                  written: dict[str, tuple[dict[str, Any], list[int]]] | None = None) -> int:
    """Order every tile ``passes`` times (Gauss-Seidel): in pass p, tile t sees as timed seeds the
    near-face points of its neighbours as they were last ordered (in pass p for the neighbours of a
    smaller colour, else in pass p - 1). Of the ready tasks, that of the longest chain of orderings
    waiting for it starts first (its bottom level in points, :func:`.pool.bottom_levels`), at most
    ``slots`` at a time (None: all at once): the executor's queue is first in, first out, and would
    run a task on the critical path that became ready late after all those submitted before it.
    The first colour's tiles see no neighbour in pass 1; each later ordering sees its neighbours'
    latest (see TILE_PASSES). ``lattice``: the scan's grid, on which each ordering labels its band
    pieces for the covering tasks (:func:`.tasks.order_tile`). ``written``: filled with the markers
    this call writes (name -> the task's result it holds, its size and CRC-32), which the phase's
    marker then need not read again (on an object store, three requests a tile in the parent).
    Returns the number of tile orderings a resume found done."""
    n_tiles = len(by_size)
    # an earlier pass's marker lists the tile's stream as it was then (a later pass replaced it)
    done = {(p, t.index) for p in range(1, passes + 1) for t in by_size
            if piece_done(work, WL.order_piece(t.index, p),
                          () if p == passes else (WL.stream(t.index), WL.seam(t.index), WL.band_labels(t.index)))
            is not None}
    found = len(done)

    def deps(p: int, t: int) -> list[tuple[int, int]]:
        d = [(p, u) if colour[u] < colour[t] else (p - 1, u) for u in nbrs[t]]
        return [x for x in [*d, (p - 1, t)] if x[0] >= 1]

    def call(p: int, tile: P.Tile) -> tuple:
        t = tile.index
        faces = tuple(WL.face(u, q) for q, u in deps(p, t) if u != t)
        doc = {**tile.to_json(), "core": pieces["core"][t], "halo": pieces["halo"][t]}
        return (work, t, doc, *args, faces, WL.face(t, p), lattice)

    todo = [(p, tile) for p in range(1, passes + 1) for tile in by_size if (p, tile.index) not in done]
    running: dict[cf.Future, tuple[int, int]] = {}
    total = n_tiles * passes
    size = {t.index: t.n_points for t in by_size}
    level = bottom_levels({(p, t.index): deps(p, t.index) for p in range(1, passes + 1) for t in by_size},
                          {(p, t.index): float(t.n_points) for p in range(1, passes + 1) for t in by_size})

    def tell() -> None:
        report_tasks(progress, "tiles", TaskCounts(len(done), total, sum(size[t] for _, t in done),
                                                   passes * sum(size.values()), len(running)))

    tell()
    try:
        while todo or running:
            ready = sorted((x for x in todo if all(d in done for d in deps(x[0], x[1].index))),
                           key=lambda x: -level[(x[0], x[1].index)])  # (stable: the largest first among equals)
            for p, tile in ready[: len(ready) if slots is None else max(slots - len(running), 0)]:
                todo.remove((p, tile))
                running[ex.submit(order_tile, *call(p, tile))] = (p, tile.index)
            fin, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
            for fut in fin:
                p, t = running.pop(fut)
                res = result(fut, name, f"ordering of tile {t + 1} of {n_tiles}")
                sums = put_json(work, WL.marker(WL.order_piece(t, p)), res)
                if written is not None:
                    written[WL.marker(WL.order_piece(t, p))] = (res, sums)
                WL.moment("tile")
                done.add((p, t))
                tell()
    except BaseException:
        for f in running:
            f.cancel()
        raise
    return found


def _check_rounds_fit(need: int, how: str, n_owners: int, worker_budget: int, budget: int, parallel: int) -> None:
    """Refuse seam rounds whose owner needs ``need`` bytes (``how``: "about", or "at least" for the
    bound known before any work) over ``worker_budget``, naming the budget that would do."""
    if need <= worker_budget:
        return
    per = need + P.PROCESS_BYTES  # the budget at which it fits a worker's share (plan.worker_budget inverted)
    enough = max(per * parallel / (1 - P.PARENT_FRACTION), per * parallel + P.PARENT_MIN)
    raise MemoryBudgetError(
        f"seam rounds need {how} {need / 2**30:.2f} GiB in each of {n_owners} worker(s) for the tiles' ordering "
        f"states, over the {worker_budget / 2**30:.2f} GiB each has of max_memory={budget / 2**30:.2f} GiB; give "
        f"max_memory of at least {math.ceil(enough / 2**30)} GiB, or build without seam rounds")


def _rounds_plan(ex: cf.Executor, tiles: list[P.Tile], size: np.ndarray, colour: list[int], parallel: int,
                 worker_budget: int, schedule: tuple[int, float], budget: int) -> dict[str, Any]:
    """The radius rounds' plan (:mod:`.affinity`): the owners of the tiles and what their states
    need, for the build record; refused (MemoryBudgetError) where an owner's states do not fit the
    worker budget."""
    n_owners = min(A.n_owners(ex, parallel), len(tiles))
    points = {t.index: int(size[t.index]) for t in tiles}
    owner = A.assign(points, colour, n_owners)
    need = A.owner_bytes(points, owner, n_owners)
    _check_rounds_fit(max(need), "about", n_owners, worker_budget, budget, parallel)
    return {"rounds": schedule[0], "q": schedule[1], "owners": n_owners, "owner_bytes_estimate": need,
            "worker_budget": worker_budget, "owner": owner}


def _order_rounds(ex: cf.Executor, work: Store, name: str, tiles: list[P.Tile], nbrs: list[list[int]],
                  colour: list[int], args: tuple, pieces: dict[str, Any], plan: dict[str, Any], parallel: int,
                  progress: ProgressCallback = None) -> int:
    """Every tile ordered in radius rounds, each tile's state on its owner (:mod:`.affinity`); the
    markers as the passes' (written once every tile is done: a resume redoes the rounds). Returns
    how many orderings a resume found done (all or none)."""
    if _done(work, "order") is not None:
        return len(tiles)
    halo = float(args[2])
    boxes = {t.index: (t.lo - 1.01 * halo, t.hi + 1.01 * halo) for t in tiles}
    docs = {t.index: {**t.to_json(), "core": pieces["core"][t.index], "halo": pieces["halo"][t.index], "args": args,
                      "near": ([boxes[u][0].tolist() for u in nbrs[t.index]], [boxes[u][1].tolist() for u in nbrs[t.index]])}
            for t in tiles}
    res = A.run_rounds(ex, work, name, docs, nbrs, colour, plan["owner"], parallel, plan["rounds"], plan["q"],
                       progress)
    plan["owner_state_bytes"] = res["owner_state_bytes"]
    for r in res["tiles"]:
        put_json(work, WL.marker(WL.order_piece(r["tile"], 1)), {**r, "rounds": res["rounds"], "q": res["q"],
                                                                  "state_bytes": res["state_bytes"]})
    return 0


def build_tiled(sources: list[tuple[Any, ...]], part: Path, name: str, work: Path | Store, executor: cf.Executor,
                *, parallel: int = 1, max_memory: int | None = None, voxel_size: float | None = None,
                band_radius: float | None = None, seam_spacing: float = SEAM_SPACING, seam_rounds: bool = False,
                tile_points: int | None = None, passes: int = TILE_PASSES, build: dict[str, Any] | None = None,
                provenance: dict[str, Any] | None = None, progress: ProgressCallback = None) -> dict[str, Any]:
    """Order one scan (``sources``: ``(stream, pose, member id, reopen)`` of one input, or of each
    input of a joint build; ``reopen`` opens the stream again on a worker, None: the parent reads
    it) tile by tile and write it to the part file ``part``; returns what was built and how long each phase
    took. ``work`` is the work directory or store (:mod:`.store`; kept on failure for a resume,
    emptied on success). ``seam_rounds``: the tiles ordered in radius rounds (:mod:`.rounds`) instead
    of one pass."""
    budget = P.default_budget() if max_memory is None else int(max_memory)
    worker_budget = max(64 << 20, P.worker_budget(budget, parallel) - P.PROCESS_BYTES)
    if seam_rounds:  # before any work: the states of the points alone (the tiles' halos come on top)
        owners = A.n_owners(executor, parallel)
        n_in = sum(int(s[0].n_points) for s in sources)
        _check_rounds_fit(A.STATE_BYTES_PER_POINT * -(-n_in // owners), "at least", owners, worker_budget, budget,
                          parallel)
    work = store = as_store(work)  # (the phases below take the store)
    store.claim()  # the directory made (or checked to be lodbuilder's), the object store's access checked
    clock = _Clock()

    # 1. read the scan into raw files, 2. plan its tiles and the decimated copy
    sp, pl, tiles = _read_and_plan(executor, work, name, sources, parallel, voxel_size, band_radius, budget,
                                   tile_points, clock, progress)
    n, n_tiles = sp.n, len(tiles)
    delta = float(pl["d_cell"]) * math.sqrt(3.0)  # every point is within a cell diagonal of the copy

    # 3. the coarse level (on a worker) while the other workers write the tiles' core and halo pieces
    coarse, dist = _coarse_and_tiles(executor, work, name, sp, pl, delta, worker_budget, progress)
    halo = float(dist["halo"])
    head_reach = HEAD_REACH * (float(coarse["r_cut"]) + delta)  # (how far covering tasks take head points)
    clock.lap("tiles")

    # 4. order every tile (on the workers), in passes
    args = (pl["voxel_size"], pl["band_radius"], halo, worker_budget)
    schedule = R.schedule(n, store.read_array(WL.HEAD_FILE, WL.HEAD).shape[0]) if seam_rounds else None
    by_size, colour, ordered, stats = _order(executor, work, name, tiles, dist, passes, args, progress, parallel,
                                             schedule, budget, [float(x) for x in sp.lo])
    resumed = {"tiles_ordered_before": ordered}
    clock.lap("order")

    # 5. merge the tile orders (one task, streaming), then invert the order (tasks)
    merged = _merge(executor, work, name, sp, stats, seam_spacing, sp.lo, float(pl["span"]), progress, parallel,
                    [(t.lo, t.hi) for t in tiles])
    clock.lap("merge")

    # 6. exact covering radii and band pieces of every tile, the radii combined, the points bucketed
    resumed["tiles_covered_before"], band_pieces, radii, buckets = _covering(
        executor, work, name, sp, sources, by_size, dist, pl, delta, head_reach, worker_budget, clock, progress)

    # 7. write the part file in stored order (bands of positions as tasks; the parent places their chunks)
    head = store.read_array(WL.HEAD_FILE, WL.HEAD)
    record = {**(build or {}), "method": "tiled", "voxel_size": pl["voxel_size"], "band_radius": pl["band_radius"],
              "engine_stats": band_pieces,
              "tiled": {"tiles": n_tiles, **_plan_record(pl, halo, head.shape[0], coarse), "head_reach": head_reach, "seam_alpha": seam_spacing,
                        "passes": passes, "read_blocks": len(sp.blocks or []), **_merge_record(merged, radii), "max_memory": budget, "parallel": parallel,
                        "guarantees": GUARANTEES, "resumed": resumed, "tile_colours": colour, "rounds": (get_json(work, WL.marker("order")) or {}).get("rounds"),
                        "tile_boxes": [[*t.lo.tolist(), *t.hi.tolist()] for t in tiles]}}
    info = _write(executor, work, part, name, sp, head["g"][:1], lambda: {**record, **_timings(clock, work, "write")},
                  {"reader": sp.reader, **(provenance or {})}, buckets, radii, progress)
    store.remove()
    return {"n_points": n, "n_ordered": n, "encoding": sp.encoding, "tiles": n_tiles, "resumed": resumed,
            "phases": clock.rounded(4), "seconds": clock.total(),
            "part": str(info.path), "worker_pid": os.getpid()}


def _read_and_plan(executor: cf.Executor, work: Store, name: str, sources: list[tuple[Any, ...]], parallel: int,
                   voxel_size: float | None, band_radius: float | None, budget: int, tile_points: int | None,
                   clock: _Clock, progress: ProgressCallback) -> tuple[Spill, dict[str, Any], list[P.Tile]]:
    """Phases 1 and 2: the scan read into raw files, then planned; returns the spill, the plan and its tiles."""
    # 1. read: the scan into raw files, with bounds, a sample and the coordinate encoding
    sp = read_phase(executor, work, name, sources, parallel, progress)
    clock.lap("read")

    # 2. plan: parameters, histogram, tiles, the decimated copy
    pl = _plan(executor, work, name, sp, voxel_size, band_radius, budget, parallel, tile_points, progress)
    tiles = [P.Tile.from_json(t) for t in pl["tiles"]]
    clock.lap("plan")
    log.info("scan %r: %d points in %d tile(s) of at most %d points", name, sp.n, len(tiles), pl["tile_cap"])
    return sp, pl, tiles


def _covering(executor: cf.Executor, work: Store, name: str, sp: Spill, sources: list[tuple[Any, ...]],
              by_size: list[P.Tile], dist: dict[str, Any], pl: dict[str, Any], delta: float, head_reach: float,
              worker_budget: int, clock: _Clock, progress: ProgressCallback) -> tuple[int, dict[str, Any], dict[str, Any], dict[str, Any]]:
    """Phase 6 and the write's first pass; returns (tiles covered before, band pieces, radii, buckets)."""
    # exact covering radii and band pieces of every tile (on the workers), the pieces joined (tasks
    # over bands of input indices), the radii combined in bands of positions; then tasks put the
    # points in stored order (the write's first pass: after the covering files and the tiles' points
    # are deleted, so that the buckets are never on disk beside them)
    n_tiles = len(by_size)
    covered = _cover(executor, work, name, sp, by_size, dist, pl, head_reach, worker_budget, progress)
    clock.lap("cover")
    band_pieces = join_phase(executor, work, name, sp.n, n_tiles)  # (then the tiles' points are deleted)
    clock.lap("pieces")
    radii = _radii(executor, work, name, sp.n, n_tiles, delta, progress)
    clock.lap("radii")
    buckets = _buckets(executor, work, name, sp, sources, progress)
    clock.lap("permute")
    return covered, band_pieces, radii, buckets


def _write(executor: cf.Executor, work: Store, part: Path, name: str, sp: Spill, seeds: np.ndarray,
           record: Callable[[], dict[str, Any]], provenance: dict[str, Any], buckets: dict[str, Any],
           radii: dict[str, Any], progress: ProgressCallback) -> Any:
    """Phase 7: the part written in bands of stored positions by tasks, assembled by the parent
    from their finished chunks (see :mod:`.bands`); ``record()`` the build record, asked for when
    every band is written. Returns the PartInfo."""
    from .bands import write_phase

    return write_phase(executor, work, part, name, sp, lambda: {"seeds": seeds, "build": record(),
                                                                 "provenance": provenance}, buckets, radii, progress)


def _order(executor: cf.Executor, work: Store, name: str, tiles: list[P.Tile], dist: dict[str, Any], passes: int,
           args: tuple, progress: ProgressCallback, parallel: int = 1, schedule: tuple[int, float] | None = None,
           budget: int = 0, lattice: list[float] | None = None) -> tuple[list[P.Tile], list[int], int, list[dict[str, Any]]]:
    """Phase 4: every tile ordered on the workers, in colour classes and passes, at most
    ``parallel`` at a time (see :func:`_order_passes`; 1: a scheduler whose workers are not
    counted, every ready ordering submitted at once), or in radius rounds of ``schedule`` (R, q)
    (:mod:`.rounds`). Returns the tiles largest first, their colours, how many orderings a resume
    found done, and each tile's marker."""
    # the largest tiles first, so that the last task to finish is a small one (fewer idle workers)
    size = np.asarray(dist["n_core"], np.int64) + np.asarray(dist["n_halo"], np.int64)
    by_size = sorted(tiles, key=lambda t: -int(size[t.index]))
    nbrs = P.tile_neighbours(tiles, float(dist["halo"]))
    colour = P.colour_tiles(nbrs)
    done = _done(work, "order")
    rounds = (done or {}).get("rounds")
    written: dict[str, tuple[dict[str, Any], list[int]]] = {}  # (the orderings' markers this build wrote)
    if done is None and schedule is not None:
        rounds = _rounds_plan(executor, tiles, size, colour, parallel, int(args[3]), schedule, budget)
    if rounds is not None:
        ordered = _order_rounds(executor, work, name, tiles, nbrs, colour, args, dist["pieces"], rounds, parallel,
                                progress)
    else:
        ordered = _order_passes(executor, work, name, by_size, nbrs, colour, passes, args, dist["pieces"], progress,
                                parallel if parallel > 1 else None, lattice, written)
    stats = [written[m][0] if m in written else get_json(work, m) or {}
             for m in (WL.marker(WL.order_piece(t.index, passes)) for t in tiles)]
    if _done(work, "order") is None:
        # every ordering's marker and last files, checked as one: the tiles' face files (read by the
        # orderings alone) are deleted now, and stay consumed only while every ordering checks out
        pieces = [WL.marker(WL.order_piece(t.index, p)) for t in tiles for p in range(1, passes + 1)]
        files = {k: v for st in stats for k, v in (st.get("files") or {}).items() if not k.startswith("face.")}
        mark(work, "order", {"files": {**{m: written[m][1] if m in written else work.sum(m) for m in pieces}, **files},
                             "rounds": None if rounds is None else {**rounds, "owner": [rounds["owner"][t.index] for t in tiles]}})
    return by_size, colour, ordered, stats


def _merge(executor: cf.Executor, work: Store, name: str, sp: Spill, stats: list[dict[str, Any]], seam_spacing: float,
           lo: np.ndarray, span: float, progress: ProgressCallback, parallel: int = 1,
           boxes: list[tuple[np.ndarray, np.ndarray]] | None = None) -> dict[str, Any]:
    """Phase 5: the tile orders merged by descending key with the seam repair (or what a finished
    merge recorded): the seam points' links (tasks over groups of tiles, ``boxes`` their (lo, hi))
    and repair, then bands of keys side by side (see :mod:`.merge`;
    about :data:`.plan.MERGE_BANDS_PER_WORKER` per worker); then the ranks, by tasks (:mod:`.ranks`)."""
    from .merge import BAND_ROWS, merge_phase
    from .ranks import ranks_phase

    merged = _done(work, "merge")
    if merged is None:
        merged = mark(work, "merge", merge_phase(executor, work, name, sp.n, stats, seam_spacing, lo,
                                                 span / (1 << 20), progress, P.merge_band_rows(sp.n, parallel, BAND_ROWS),
                                                 boxes))
    ranks_phase(executor, work, name, sp.n, sp.blocks or [], progress)
    return merged


def _cover(executor: cf.Executor, work: Store, name: str, sp: Spill, by_size: list[P.Tile], dist: dict[str, Any],
           pl: dict[str, Any], head_reach: float, worker_budget: int, progress: ProgressCallback) -> int:
    """Phase 6: the exact covering radii of every tile on the workers (from its core, its halo and
    the head points within ``head_reach`` of it); each covering task also
    labels its tile's band pieces (on the scan's grid: its voxel corners a whole number of voxels
    from the scan's lowest point; the neighbours' cores are read only when the halo is narrower
    than the pieces' reach), which the join (:func:`.pieces.join_phase`) joins next. Returns how
    many tiles a resume found covered."""
    n_tiles, pieces, spacing = len(by_size), dist["pieces"], float(pl["spacing"])
    spec = {"voxel_size": pl["voxel_size"], "band_radius": pl["band_radius"], "lattice": [float(x) for x in sp.lo],
            "max_memory": worker_budget, "halo": float(dist["halo"])}
    todo = [t for t in by_size if piece_done(work, WL.cover_piece(t.index)) is None]
    d = reach(spec["voxel_size"], spec["band_radius"])
    nbrs = P.tile_neighbours(sorted(by_size, key=lambda t: t.index), d) if spec["halo"] < d else None

    def band(t: P.Tile) -> dict[str, Any]:
        near = [] if nbrs is None else [pieces["core"][u] for u in nbrs[t.index]]
        return {**spec, "lo": t.lo.tolist(), "hi": t.hi.tolist(), "interior": t.interior.tolist(), "neighbours": near}

    futs = submit(executor, [(t.index, cover_tile, (work, t.index, spacing, pieces["core"][t.index],
                                                    pieces["halo"][t.index], band(t), head_reach)) for t in todo])
    collect(futs, lambda t: f"covering of tile {t + 1} of {n_tiles}", name, n_tiles, progress, "covering",
            lambda res: put_json(work, WL.marker(WL.cover_piece(res["tile"])), res),
            points=[t.n_points for t in sorted(by_size, key=lambda t: t.index)])
    return n_tiles - len(todo)


def _radii(executor: cf.Executor, work: Store, name: str, n: int, n_tiles: int, delta: float,
           progress: ProgressCallback) -> dict[str, Any]:
    """The stored radii and parents, combined from the covering files in bands of positions
    (tasks, :mod:`.radii`); returns the radii's marker."""
    from . import workdir as W
    from .radii import radii_phase

    return radii_phase(executor, work, name, n, n_tiles, delta, W.BLOCK, progress)


def _buckets(executor: cf.Executor, work: Store, name: str, sp: Spill, sources: list[tuple[Any, ...]],
             progress: ProgressCallback) -> dict[str, Any]:
    """The write's first pass: every read block read from its input again and split by
    destination into the write's buckets (tasks)."""
    from .write import buckets_phase

    return buckets_phase(executor, work, name, sp, sources, progress)


def _merge_record(merged: dict[str, Any], radii: dict[str, Any]) -> dict[str, Any]:
    """The build record's entries of the merge and of the radii."""
    return {"seam_points": int(merged["seam_points"]), "seam_links": merged.get("seam_links"),
            "seam_deferrals": int(merged["deferred"]),
            "spacing_over_radius_min": radii["spacing_over_radius_min"]}


class _Clock:
    """Seconds of each phase of a build (:meth:`lap` ends one) and of the whole."""

    def __init__(self) -> None:
        self.start = self.last = time.perf_counter()
        self.epoch = time.time()  # (the task table's times are seconds after it)
        self.cpu_last = time.process_time()
        self.times: dict[str, float] = {}
        self.cpu: dict[str, float] = {}  # the parent's own CPU seconds (its workers' not counted)

    def lap(self, phase: str) -> None:
        now, cpu = time.perf_counter(), time.process_time()
        self.times[phase] = now - self.last
        self.cpu[phase] = cpu - self.cpu_last
        self.last, self.cpu_last = now, cpu

    def rounded(self, digits: int) -> dict[str, float]:
        return {k: round(v, digits) for k, v in self.times.items()}

    def total(self) -> float:
        return time.perf_counter() - self.start


def _timings(clock: _Clock, work: Store, last: str) -> dict[str, Any]:
    """The build record's phase seconds (and their order: the record's keys are sorted), the
    parent's own CPU seconds per phase and the table of every task (see :mod:`.timing`), once
    the ``last`` phase ends (the write: asked for when its bands are written, their tasks in the
    table)."""
    clock.lap(last)
    return {"phase_seconds": clock.rounded(3), "phase_order": list(clock.times),
            "parent_cpu_seconds": {k: round(v, 3) for k, v in clock.cpu.items()},
            "build_started": clock.epoch, "tasks": task_table(work, clock.epoch)}


def _plan_record(pl: dict[str, Any], halo: float, head_points: int, coarse: dict[str, Any]) -> dict[str, Any]:
    """The build record's entries of the plan and the coarse level."""
    return {"tile_points_max": int(pl["tile_cap"]), "halo": halo, "coarse_points": int(pl["n_decimated"]),
            "coarse_cell": float(pl["d_cell"]), "head_points": int(head_points),
            "head_radius": float(coarse["r_cut"]), "coarse_voxel": float(coarse.get("voxel_size") or 0.0)}


def _plan(executor: cf.Executor, work: Store, name: str, sp: Spill, voxel_size: float | None,
          band_radius: float | None, budget: int, parallel: int, tile_points: int | None,
          progress: ProgressCallback) -> dict[str, Any]:
    """Phase 2: the shared parameters, the tiles (a k-d split of a point-count histogram) and the
    decimated copy (one point per cell of about the head's spacing), or what a finished plan recorded."""
    pl = _done(work, "plan")
    if pl is not None:
        return pl
    n = sp.n
    # the spacing and the band's parameters from the sample, on a worker (the parent loads no kernel)
    pending = submit(executor, [(0, parameters_task, (work, n, voxel_size, band_radius))])
    (params,) = collect(pending, lambda _: "the plan's parameters", name, 1, None, "plan")
    fits = P.tile_capacity(budget, parallel)
    m_target, m_limit = coarse_target(n, budget, parallel)
    return plan_phase(executor, work, name, sp, {k: params[k] for k in ("spacing", "voxel_size", "band_radius")},
                      m_limit, tile_points or P.balanced_tile_points(n, parallel, fits), m_target, progress)


def coarse_target(n: int, budget: int, parallel: int) -> tuple[int, int]:
    """The decimated copy's aim and its limit for a survey of ``n`` points (see COARSE_SHARE): the
    copy is ordered by one worker, never larger than the worker's budget allows."""
    limit = max(P.coarse_capacity(budget, parallel), COARSE_MIN)
    aim = min(max(COARSE_POINTS, n // COARSE_SHARE), max(limit // 2, COARSE_MIN), max(n // 8, min(n, COARSE_MIN)))
    return aim, limit


def _coarse_and_tiles(executor: cf.Executor, work: Store, name: str, sp: Spill, pl: dict[str, Any],
                      delta: float, worker_budget: int, progress: ProgressCallback
                      ) -> tuple[dict[str, Any], dict[str, Any]]:
    """Phase 3: the coarse level ordered on a worker while the other workers write every tile's
    core and halo pieces; returns their markers (coarse, distribute)."""
    coarse = _done(work, "coarse")
    pending: dict[cf.Future, int] = {}
    # the coarse level's covering radius, estimated from its size
    m_est = max(1, int(pl["n_decimated"]))
    head_est = max(HEAD_MIN, m_est // HEAD_DECIMATION)
    # the copy's order's radius at 1 point in GRID_DECIMATION: its grid and the halo (see HEAD_DECIMATION)
    r_grid = float(pl["d_cell"]) * math.sqrt(m_est / max(HEAD_MIN, m_est // GRID_DECIMATION))
    if coarse is None:
        pending = submit(executor, [(0, coarse_task, (work, head_est, worker_budget, r_grid / HEAD_RADIUS_VOXELS))])
    try:
        halo = HALO_FACTOR * (r_grid + delta)  # (a fraction of it; see HEAD_DECIMATION)
        dist = distribute_phase(executor, work, name, sp, pl, halo, progress)
    finally:
        if coarse is None:
            (coarse,) = collect(pending, lambda _: "the coarse level", name, 1, progress, "coarse")
            mark(work, "coarse", coarse)
    return coarse, dist


#: what a tiled archive guarantees (also stored in its build record)
GUARANTEES = (
    "every prefix's stored radius is an upper bound of the Euclidean distance from every point of the "
    "scan to the prefix (the exact covering radius of every tile's points by the prefix, computed from "
    "the tile and its halo: exact wherever it is below the halo width; capped by the coarse level's "
    "certified bound); radii never increase; every input point is stored exactly once; a point merged "
    "from one tile is at least seam_alpha times its merge radius from every earlier point of another "
    "tile or of the coarse level, so the spacing of every level between points of different tiles is "
    "at least seam_alpha / (1 + seam_alpha) times the level's radius (0.2 at the default seam_alpha "
    "0.25, 0.5 at seam_alpha 1); the points of one tile keep the tile's FastFPS order (spacing at least "
    "their insertion radius in the band metric, as in an in-memory build)"
)
