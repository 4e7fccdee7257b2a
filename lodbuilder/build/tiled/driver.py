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
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import BuildError, LodbuilderError
from ...progress import ProgressCallback, report
from . import plan as P
from .sums import SumFile, write_json
from .sums import done as piece_done
from .tasks import coarse_task, cover_tile, order_tile
from .workdir import Decimator, Spill, distribute, point_blocks, read_json, spill

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
#: the decimated copy has at most this many points (its ordering is one task), and at least
#: COARSE_MIN (or every point): a band around fewer points is too coarse to order a surface
COARSE_POINTS = 400_000
COARSE_MIN = 2_000
#: head size: points of the decimated copy's order per point of the head
HEAD_DECIMATION = 200
HEAD_MIN = 256
#: halo width in units of the coarse level's covering bound: the stored radii are exact wherever the
#: covering radius is below the halo width (every level but the first few times the head's size)
HALO_FACTOR = 0.3


def _done(work: Path, phase: str) -> dict[str, Any] | None:
    """The marker of a finished phase whose files all check out (see :mod:`.sums`), else None."""
    return piece_done(work, phase)


def _mark(work: Path, phase: str, doc: dict[str, Any]) -> dict[str, Any]:
    write_json(work / f"{phase}.json", doc)
    return doc


def _submit(ex: cf.Executor, calls: list[tuple[int, Any, tuple]]) -> dict[cf.Future, int]:
    return {ex.submit(fn, *args): t for t, fn, args in calls}


def _result(fut: cf.Future, name: str, where: str) -> Any:
    """A finished task's result; its failure fails the scan, naming the task."""
    try:
        return fut.result()
    except LodbuilderError as exc:
        raise BuildError(f"scan {name!r}: {where} failed: {exc}") from exc
    except BrokenProcessPool:
        raise BuildError(f"scan {name!r}: {where} failed: its worker process "
                         "died (killed or out of memory: lower --max-memory per worker or use fewer "
                         "workers)") from None
    except Exception as exc:
        text = " ".join(str(exc).split())
        raise BuildError(f"scan {name!r}: {where} failed: {type(exc).__name__}: {text}") from exc


def _collect(futs: dict[cf.Future, int], what: str, name: str, n_total: int, progress: ProgressCallback,
             stage: str, on_result: Any = None) -> list[dict[str, Any]]:
    """Wait for submitted tasks; a failure fails the scan, naming the tile. ``on_result(result)``
    is called as each task finishes (to record it for a resume)."""

    def where(t: int) -> str:
        return what if n_total == 1 and stage == "coarse" else f"{what} of tile {t + 1} of {n_total}"

    done = n_total - len(futs)
    report(progress, stage, done, n_total)
    out = []
    try:
        for fut in cf.as_completed(futs):
            out.append(_result(fut, name, where(futs[fut])))
            if on_result is not None:
                on_result(out[-1])
            done += 1
            report(progress, stage, done, n_total)
    except BaseException:
        for f in futs:
            f.cancel()
        raise
    return out


def _order_passes(ex: cf.Executor, work: Path, name: str, by_size: list[P.Tile], nbrs: list[list[int]],
                  colour: list[int], passes: int, args: tuple, progress: ProgressCallback) -> int:
    """Order every tile ``passes`` times (Gauss-Seidel): in pass p, tile t sees as timed seeds the
    near-face points of its neighbours as they were last ordered (in pass p for the neighbours of a
    smaller colour, else in pass p - 1). A task starts as soon as those are done, largest tiles
    first. In the first pass the tiles of the first colour see no neighbour; each later ordering
    sees its neighbours' latest, and the orderings agree more with each pass (see TILE_PASSES).
    Returns the number of tile orderings a resume found done."""
    n_tiles = len(by_size)
    # an earlier pass's marker lists the tile's stream as it was then (a later pass replaced it)
    done = {(p, t.index) for p in range(1, passes + 1) for t in by_size
            if piece_done(work, f"order.{t.index}.{p}", () if p == passes else (f"stream.{t.index}.bin",))
            is not None}
    found = len(done)

    def deps(p: int, t: int) -> list[tuple[int, int]]:
        d = [(p, u) if colour[u] < colour[t] else (p - 1, u) for u in nbrs[t]]
        return [x for x in [*d, (p - 1, t)] if x[0] >= 1]

    def call(p: int, tile: P.Tile) -> tuple:
        t = tile.index
        faces = tuple(str(work / f"face.{u}.{q}.bin") for q, u in deps(p, t) if u != t)
        return (str(work), t, tile.to_json(), *args, faces, str(work / f"face.{t}.{p}.bin"))

    todo = [(p, tile) for p in range(1, passes + 1) for tile in by_size if (p, tile.index) not in done]
    running: dict[cf.Future, tuple[int, int]] = {}
    total = n_tiles * passes
    report(progress, "tiles", len(done), total)
    try:
        while todo or running:
            for p, tile in [x for x in todo if all(d in done for d in deps(x[0], x[1].index))]:
                todo.remove((p, tile))
                running[ex.submit(order_tile, *call(p, tile))] = (p, tile.index)
            fin, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
            for fut in fin:
                p, t = running.pop(fut)
                res = _result(fut, name, f"ordering of tile {t + 1} of {n_tiles}")
                write_json(work / f"order.{t}.{p}.json", res)
                done.add((p, t))
                report(progress, "tiles", len(done), total)
    except BaseException:
        for f in running:
            f.cancel()
        raise
    return found


def _spacing(sample: np.ndarray, n: int) -> float:
    from ...sampling.band import median_spacing

    if sample.shape[0] < 2:
        return 1.0
    s = median_spacing(sample) * math.sqrt(sample.shape[0] / max(n, 1))
    return s if s > 0 else float(np.ptp(sample, axis=0).max() or 1.0) / math.sqrt(max(n, 1))


def build_tiled(
    sources: list[tuple[Any, Any, int | None]],
    part: Path,
    name: str,
    work: Path,
    executor: cf.Executor,
    *,
    parallel: int = 1,
    max_memory: int | None = None,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    seam_spacing: float = SEAM_SPACING,
    tile_points: int | None = None,
    passes: int = TILE_PASSES,
    build: dict[str, Any] | None = None,
    provenance: dict[str, Any] | None = None,
    progress: ProgressCallback = None,
) -> dict[str, Any]:
    """Order one scan (``sources``: one stream, or several posed streams for a joint build) tile by
    tile and write it to the part file ``part``; returns what was built and how long each phase
    took. ``work`` is the work directory (kept on failure for a resume, removed on success)."""
    from ...archive.files import make_own_dir, remove_own_dir
    from ...sampling.band import choose_parameters
    from .merge import assemble_radii, merge_tiles, write_ranks
    from .write import bucket_points, write_scan

    budget = P.default_budget() if max_memory is None else int(max_memory)
    make_own_dir(work, work.name)  # or check that the one a killed build left is lodbuilder's
    times: dict[str, float] = {}
    t_all = time.perf_counter()

    # 1. read: the scan into raw files, with bounds, a sample and the coordinate encoding
    t0 = time.perf_counter()
    doc = _done(work, "spill")
    if doc is None:
        sp = spill(sources, work, progress)
        with SumFile(work / "sample.npy") as f:
            np.save(f, sp.sample)
        sp.files = {**(sp.files or {}), "sample.npy": f.sum}
        _mark(work, "spill", sp.to_json())
    else:
        sp = Spill.from_json(doc, np.load(work / "sample.npy"))
    n = sp.n
    times["read"] = time.perf_counter() - t0

    # 2. plan: parameters, histogram, tiles, the decimated copy
    t0 = time.perf_counter()
    pl = _done(work, "plan")
    if pl is None:
        s = _spacing(sp.sample, n)
        h, r = choose_parameters(sp.sample, voxel_size if voxel_size is not None else P_VOXEL(s),
                                 band_radius)
        grid = P.Grid.around(sp.lo, sp.hi)
        span = float(np.max(sp.hi - sp.lo)) or 1.0
        fits = P.tile_capacity(budget, parallel)
        cap = tile_points or fits
        # the decimated copy is ordered by one worker: no larger than the worker's budget allows
        m_target = min(COARSE_POINTS, max(fits, COARSE_MIN), max(n // 8, min(n, COARSE_MIN)))
        d_cell = max(s * math.sqrt(n / m_target), span / (1 << 20))
        hist = np.zeros(int(np.prod(grid.shape)), np.int64)
        dec = Decimator(grid.lo, d_cell)
        for g0, pts in point_blocks(work, n):
            hist += np.bincount(grid.index(pts), minlength=hist.shape[0])
            dec.add(g0, pts)
        n_dec = dec.write(work / "decimated.i8")
        limit = max(fits, COARSE_MIN)
        while n_dec > limit:  # the cell count overshot the target: coarser cells, one more pass
            d_cell *= 1.1 * math.sqrt(n_dec / limit)
            dec = Decimator(grid.lo, d_cell)
            for g0, pts in point_blocks(work, n):
                dec.add(g0, pts)
            n_dec = dec.write(work / "decimated.i8")
        tiles = P.split_tiles(hist, grid, cap)
        pl = _mark(work, "plan", {"spacing": s, "voxel_size": h, "band_radius": r, "tile_cap": cap,
                                  "grid": {"lo": grid.lo.tolist(), "cell": grid.cell, "shape": list(grid.shape)},
                                  "tiles": [t.to_json() for t in tiles], "d_cell": d_cell, "span": span,
                                  "n_decimated": n_dec, "files": {"decimated.i8": dec.sum}})
    tiles = [P.Tile.from_json(t) for t in pl["tiles"]]
    grid = P.Grid(np.asarray(pl["grid"]["lo"]), float(pl["grid"]["cell"]), tuple(pl["grid"]["shape"]))
    n_tiles = len(tiles)
    delta = float(pl["d_cell"]) * math.sqrt(3.0)  # every point is within a cell diagonal of the copy
    times["plan"] = time.perf_counter() - t0
    log.info("scan %r: %d points in %d tile(s) of at most %d points", name, n, n_tiles, pl["tile_cap"])

    # 3. the coarse level (on a worker) while the parent writes the tiles' core and halo files
    t0 = time.perf_counter()
    worker_budget = max(64 << 20, P.worker_budget(budget, parallel) - P.PROCESS_BYTES)
    coarse = _done(work, "coarse")
    pending: dict[cf.Future, int] = {}
    if coarse is None:
        head_size = max(HEAD_MIN, int(pl["n_decimated"]) // HEAD_DECIMATION)
        pending = _submit(executor, [(0, coarse_task, (str(work), head_size, worker_budget))])
    try:
        dist = _done(work, "distribute")
        if dist is None:
            # the halo: a fraction of the coarse level's covering radius, estimated from its size
            m_est = max(1, int(pl["n_decimated"]))
            head_est = max(HEAD_MIN, m_est // HEAD_DECIMATION)
            r_est = pl["d_cell"] * math.sqrt(m_est / head_est)
            halo = HALO_FACTOR * (r_est + delta)
            lookup = P.tile_lookup(tiles, grid)
            n_core, n_halo, sums = distribute(work, n, tiles, grid, lookup, halo, progress)
            dist = _mark(work, "distribute", {"halo": halo, "n_core": n_core.tolist(), "n_halo": n_halo.tolist(),
                                              "files": sums})
    finally:
        if coarse is None:
            (coarse,) = _collect(pending, "the coarse level", name, 1, progress, "coarse")
            _mark(work, "coarse", coarse)
    halo = float(dist["halo"])
    times["tiles"] = time.perf_counter() - t0

    # 4. order every tile (on the workers), in passes
    t0 = time.perf_counter()
    # the largest tiles first, so that the last task to finish is a small one (fewer idle workers)
    size = np.asarray(dist["n_core"], np.int64) + np.asarray(dist["n_halo"], np.int64)
    by_size = sorted(tiles, key=lambda t: -int(size[t.index]))
    nbrs = P.tile_neighbours(tiles, halo)
    colour = P.colour_tiles(nbrs)
    args = (pl["voxel_size"], pl["band_radius"], halo, worker_budget)
    resumed = {"tiles_ordered_before": _order_passes(executor, work, name, by_size, nbrs, colour, passes, args,
                                                     progress)}
    stats = [read_json(work / f"order.{t.index}.{passes}.json") or {} for t in tiles]
    times["order"] = time.perf_counter() - t0

    # 5. merge the tile orders (in the parent, streaming)
    t0 = time.perf_counter()
    merged = _done(work, "merge")
    if merged is None:
        min_cell = float(pl["span"]) / (1 << 20)
        merged = merge_tiles(work, n, n_tiles, [int(s.get("n_seam", 0)) for s in stats], seam_spacing, sp.lo, min_cell,
                             progress)
        merged["files"]["rank.i8"] = write_ranks(work, n)
        _mark(work, "merge", merged)
    times["merge"] = time.perf_counter() - t0

    # 6. exact covering radii of every tile (on the workers), combined; meanwhile the parent puts
    #    the points in stored order (the first pass of the write)
    t0 = time.perf_counter()
    todo = [t for t in by_size if piece_done(work, f"cover.{t.index}") is None]
    resumed["tiles_covered_before"] = n_tiles - len(todo)
    calls = [(t.index, cover_tile, (str(work), t.index, float(pl["spacing"]))) for t in todo]
    futs = _submit(executor, calls)
    try:
        buckets = _done(work, "buckets")
        if buckets is None:
            buckets = _mark(work, "buckets", bucket_points(work, n, sp.fields, progress))
    finally:
        _collect(futs, "covering", name, n_tiles, progress, "covering",
                 lambda res: write_json(work / f"cover.{res['tile']}.json", res))
    radii = _done(work, "radii")
    if radii is None:
        radii = _mark(work, "radii", assemble_radii(work, n, n_tiles, delta, progress))
    times["cover"] = time.perf_counter() - t0

    # 7. write the part file in stored order
    t0 = time.perf_counter()
    head = np.fromfile(work / "head.bin", dtype=np.dtype([("g", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                                                             ("r", "<f8"), ("parent", "<i8")]))
    record = {
        **(build or {}),
        "method": "tiled",
        "tiled": {
            "tiles": n_tiles,
            "tile_points_max": int(pl["tile_cap"]),
            "halo": halo,
            "coarse_points": int(pl["n_decimated"]),
            "coarse_cell": float(pl["d_cell"]),
            "head_points": int(head.shape[0]),
            "head_radius": float(coarse["r_cut"]),
            "seam_alpha": seam_spacing,  # the record's name of seam_spacing (stored in archives)
            "passes": passes,
            "seam_points": int(merged["seam_points"]),
            "seam_deferrals": int(merged["deferred"]),
            "spacing_over_radius_min": radii["spacing_over_radius_min"],
            "max_memory": budget,
            "parallel": parallel,
            "guarantees": GUARANTEES,
            "resumed": resumed,
            "tile_boxes": [[*t.lo.tolist(), *t.hi.tolist()] for t in tiles],
            "tile_colours": colour,
        },
        "voxel_size": pl["voxel_size"],
        "band_radius": pl["band_radius"],
        "phase_seconds": {k: round(v, 3) for k, v in times.items()},
    }
    info = write_scan(work, part, name, n, sp.fields, sp.metadata, sp.encoding, head["g"][:1], record,
                      {"reader": sp.reader, **(provenance or {})}, progress, buckets)
    times["write"] = time.perf_counter() - t0
    remove_own_dir(work, work.name)
    return {"n_points": n, "n_ordered": n, "encoding": sp.encoding, "tiles": n_tiles, "resumed": resumed,
            "phases": {k: round(v, 4) for k, v in times.items()}, "seconds": time.perf_counter() - t_all,
            "part": str(info.path), "worker_pid": os.getpid()}


def P_VOXEL(spacing: float) -> float:
    """The engine's automatic voxel size for a point spacing (lodbuilder.sampling.band)."""
    from ...sampling.band import VOXEL_PER_SPACING

    return VOXEL_PER_SPACING * spacing


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
