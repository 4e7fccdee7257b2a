"""Public farthest point ordering: validation and orchestration around the compiled kernels."""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from typing import Any

import numpy as np

from .._resources import TRIM_MIN_POINTS, release_freed_memory  # noqa: F401 - TRIM_MIN_POINTS re-exported
from .._validate import (
    check_positive,
    check_size,
    strict_keywords,
    validate_indices,
    validate_points,
)
from ..errors import EngineError, InputError
from ..progress import ProgressCallback, report
from .ordering import Ordering
from .spacing import axis_max, axis_min

log = logging.getLogger(__name__)


def default_seed(points: np.ndarray) -> int:
    """The deterministic default seed: the point nearest the centroid (lowest index on ties)."""
    c = points.mean(axis=0)
    # one coordinate at a time: the same sums as ((points - c) ** 2).sum(axis=1) (three terms
    # added from the left) without its (N, 3) temporary and strided reduction (5 x faster)
    d2 = points[:, 0] - c[0]
    d2 *= d2
    for axis in (1, 2):
        e = points[:, axis] - c[axis]
        e *= e
        d2 += e
    return int(np.argmin(d2))


def validate_cost(cost: Any, n: int, name: str = "cost") -> np.ndarray:
    """Return a per-point cost (speed) array: (N,) float64, finite and > 0."""
    arr = np.asarray(cost)
    if arr.ndim != 1 or arr.shape[0] != n:
        raise InputError(f"{name} must have one value per point, shape ({n},), got {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all() or (arr <= 0).any():
        raise InputError(f"{name} must be finite and > 0 everywhere; clamp or fill it first")
    return arr


def _prepare(points, rho, size, seeds):
    pts = validate_points(points)
    n = pts.shape[0]
    rho = check_positive(rho, "rho")
    size = None if size is None else check_size(size, n)
    if seeds is None:
        seed_arr = np.array([default_seed(pts)], dtype=np.int64)
    else:
        seed_arr = validate_indices(seeds, n, "seeds")
        if seed_arr.size == 0:
            seed_arr = np.array([default_seed(pts)], dtype=np.int64)
    return pts, n, rho, size, seed_arr


def check_ordering(o: Ordering) -> Ordering:
    """The post-conditions of every ordering, in O(N): ``order`` holds distinct indices in
    [0, N) (all of them for a full ordering), ``radius`` is non-increasing and starts at inf,
    ``parent`` is -1 or an earlier position. Raises :class:`EngineError` naming the first broken one."""
    n, k = o.n_points, len(o)
    order, radius, parent = o.order, o.radius, o.parent

    def fail(what: str) -> EngineError:
        return EngineError(f"ordering of {n:,} points failed its check: {what}; this is a bug, please report it")

    if order.shape != (k,) or radius.shape != (k,) or parent.shape != (k,):
        raise fail(f"order/radius/parent shapes {order.shape}/{radius.shape}/{parent.shape} differ")
    if k == 0:
        return o
    if order.min() < 0 or order.max() >= n:
        raise fail("an index out of range")
    seen = np.zeros(n, dtype=bool)
    seen[order] = True
    if int(seen.sum()) != k:
        raise fail("an index appears twice")
    if not np.isinf(radius[0]) or np.isnan(radius).any():
        raise fail(f"radius[0] = {radius[0]} (inf expected) or NaN radii")
    if not (0.0 <= o.stop_radius <= radius[-1]) or (k == n and o.stop_radius != 0.0):
        raise fail(f"stop radius {o.stop_radius} after the last radius {radius[-1]} of {k:,} points")
    bad = np.flatnonzero(radius[1:] > radius[:-1])
    if bad.size:
        raise fail(f"radius increases at position {bad[0] + 1}")
    pos = np.arange(k)
    bad = np.flatnonzero((parent < -1) | (parent >= pos))
    if bad.size:
        raise fail(f"parent of position {bad[0]} is {parent[bad[0]]}, not an earlier position")
    return o


def _truncate(order, radius, parent, rho, size):
    """The prefix asked by ``rho``/``size`` of an ordering computed one point further (or to the
    end), and its stop radius: the radius of the first point left out, 0 when none is."""
    k = order.shape[0]
    if rho is not None:
        from ..levels import count_above

        k = min(k, count_above(radius, rho))
    if size is not None:
        k = min(k, size)
    stop = float(radius[k]) if k < order.shape[0] else 0.0
    return order[:k].copy(), radius[:k].copy(), parent[:k].copy(), stop


@strict_keywords
def euclidean_fps(
    points: Any,
    *,
    rho: float | None = None,
    size: int | None = None,
    seeds: Any = None,
    cost: Any = None,
) -> Ordering:
    """Exact Euclidean farthest point ordering, O(N * K). A baseline for small inputs.

    Same conventions as :func:`fastfps`; ``cost`` scales each pair's distance by the mean of the
    two points' costs.
    """
    pts, n, rho, size, seed_arr = _prepare(points, rho, size, seeds)
    c = np.ones(n) if cost is None else validate_cost(cost, n)
    from .._kernels.euclid import euclidean_fps_kernel

    k_max = n if size is None else min(n, max(size, seed_arr.size) + 1)  # one more: the stop radius
    order, radius, parent = euclidean_fps_kernel(pts, seed_arr, k_max, c)
    order, radius, parent, stop = _truncate(order, radius, parent, rho, size)
    return check_ordering(
        Ordering(order, radius, parent, 0.0, 0.0, seed_arr, n, {"engine": "euclidean"}, stop)
    )


@strict_keywords
def fastfps(
    points: Any,
    *,
    rho: float | None = None,
    size: int | None = None,
    seeds: Any = None,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    cost: Any = None,
    max_memory: int | None = None,
    progress: ProgressCallback = None,
    timed_seeds: Any = None,
    lattice: Any = None,
    pieces: bool = False,
) -> Ordering:
    """Farthest point ordering of ``points`` under the band (surface) metric.

    Args:
        points: (N, 3) array of finite coordinates.
        rho: stop once the next insertion radius is <= rho (the prefix then covers within rho).
        size: stop after this many points.
        seeds: must-keep input indices that come first, in the given order. Default: the point
            nearest the centroid.
        voxel_size: grid spacing h (default: derived from the point spacing).
        band_radius: band radius r (default: derived from h).
        cost: optional per-point cost F > 0 (feature sensitivity): distances grow F times faster.
        max_memory: bytes the band may use (default: 60 % of physical memory).
        progress: ``progress(stage, done, total)`` callback.
        timed_seeds: ``(indices, keys)``: points that are never chosen but join the ordering as
            soon as the largest remaining distance is at most their key (a distance: they stand
            for points another ordering chose at that radius; used by the tiled build for the
            neighbours' points near a tile's faces). They appear in the result with their key as
            radius. Not with ``cost``.
        lattice: (3,) a point the band grid's voxel corners fall on (a whole number of voxels from
            it; default: the grid is placed from the points' box), so that orderings of parts of a
            scan share the scan's grid. With ``voxel_size`` and ``band_radius`` only.
        pieces: also give each point's connected piece of the band (``Ordering.pieces``).

    Returns:
        An :class:`Ordering`.
    """
    voxel_size = check_positive(voxel_size, "voxel_size")
    band_radius = check_positive(band_radius, "band_radius")
    pts, n, rho, size, seed_arr = _prepare(points, rho, size, seeds)
    c = None if cost is None else validate_cost(cost, n)
    if max_memory is not None and (not isinstance(max_memory, (int, np.integer)) or max_memory <= 0):
        raise InputError(f"max_memory must be a positive number of bytes, got {max_memory!r}")
    timed = _timed_seeds(timed_seeds, n, c is not None)
    grid = _lattice(lattice, voxel_size, band_radius)
    o = _run_engine(pts, rho, size, seed_arr, voxel_size, band_radius, c, max_memory, progress, timed, grid,
                    bool(pieces))
    release_freed_memory(n)  # the band and the kernels' state are gone now
    return check_ordering(o)


DEBUG = os.environ.get("LODBUILDER_DEBUG_HEAPS", "") not in ("", "0")  # check heap invariants


def _timed_seeds(timed: Any, n: int, weighted: bool) -> tuple[np.ndarray, np.ndarray]:
    """The timed seeds as (indices, keys) by non-increasing key (stable), checked."""
    if timed is None:
        return np.empty(0, np.int64), np.empty(0)
    if weighted:
        raise InputError("timed_seeds cannot be combined with cost; pass one or the other")
    idx, keys = timed
    idx = validate_indices(idx, n, "timed_seeds")
    keys = np.asarray(keys, dtype=np.float64).reshape(-1)
    if keys.shape != idx.shape or not (keys >= 0).all() or np.isnan(keys).any():
        raise InputError(
            f"timed_seeds needs one non-negative key per index ({idx.size} indices, {keys.size} keys); "
            "pass (indices, keys) of equal length"
        )
    srt = np.argsort(-keys, kind="stable")
    return idx[srt], keys[srt]


def _lattice(lattice: Any, voxel_size: float | None, band_radius: float | None) -> np.ndarray | None:
    """The lattice point of :func:`fastfps`, checked (None: none given)."""
    if lattice is None:
        return None
    if voxel_size is None or band_radius is None:
        raise InputError("lattice places a given grid: pass voxel_size and band_radius with it")
    a = np.asarray(lattice, dtype=np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise InputError(f"lattice must be 3 finite coordinates, got shape {a.shape}; pass one point (x, y, z)")
    return a


def _hash_collisions(pts: np.ndarray) -> bool:
    """Whether two points share a 64-bit hash of their coordinates (always when two are equal;
    otherwise about n^2 / 2^65: 3e-8 for a million points); see
    :func:`lodbuilder._kernels.grid.hash_collisions` (splitmix64's finaliser: coordinates read
    from float32 files have 29 zero bits at the bottom of their float64 mantissa, and a plain
    multiply-and-xor would give a million such points shared hashes)."""
    from .._kernels.grid import hash_collisions

    return bool(hash_collisions(np.ascontiguousarray(pts, dtype=np.float64)))


def _duplicate_groups(pts: np.ndarray, seeds: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Group exact duplicates. Returns (group id per point, representative input index per group).

    The representative is the first listed seed of the group if any, else its lowest index.
    """
    n = pts.shape[0]
    if not _hash_collisions(pts):  # a quick check first: all hashes differ, so do the points (most scans)
        return None, None
    srt = np.lexsort((pts[:, 2], pts[:, 1], pts[:, 0]))
    sp = pts[srt]
    new = np.ones(n, dtype=bool)
    new[1:] = (sp[1:] != sp[:-1]).any(axis=1)
    if new.all():  # no duplicates: (None, None) stands for the identity (no copies)
        return None, None
    gid_sorted = np.cumsum(new) - 1
    gid = np.empty(n, dtype=np.int64)
    gid[srt] = gid_sorted
    rep = srt[new].copy()  # stable sort: lowest index of each group
    claimed = np.zeros(rep.shape[0], dtype=bool)
    for s in seeds:
        g = gid[s]
        if not claimed[g]:
            rep[g] = s
            claimed[g] = True
    return gid, rep


def _run_engine(pts, rho, size, seed_arr, voxel_size, band_radius, cost, max_memory, progress, timed=None,
                lattice=None, want_pieces=False):
    from .._kernels.warm import ensure_compiled

    compiled = ensure_compiled(progress)  # a cold numba cache: compile first, and say so
    t0, c0 = time.perf_counter(), time.process_time()
    n = pts.shape[0]
    gid, rep, useeds, m, extent, band, plan, stats = _engine_band(
        pts, seed_arr, voxel_size, band_radius, max_memory, progress, compiled, lattice)
    h, r = plan.h, plan.r
    k_max = m if size is None else min(m, size)
    t1, c1 = time.perf_counter(), time.process_time()
    stats.update(time_band=t1 - t0, cpu_band=c1 - c0)
    report(progress, "band", 1, 1)
    seeds_c, tseed_c, tkey_g = _engine_seeds(band.perm, m, useeds, gid, timed, h)
    tpos = np.zeros(1, np.int64)  # the timed seeds' cursor, shared by the grid phase and the tail
    stats["n_timed_seeds"] = int(tseed_c.size)
    vcost, pcost, cmin, cscale = _engine_costs(cost, rep, band)
    piece, npiece = _pieces(band, stats)
    point_pieces = _input_pieces(piece, band.perm, gid) if want_pieces else None
    psep, pnrm, foot = _tail_fields(band, plan)
    rho_g = -1.0 if rho is None else rho / h
    report(progress, "ordering", 0, k_max)
    order, radius, parent, k, val, lq, rank, pops = _grid_phase(
        band, vcost, pcost, cost is not None, foot, pnrm, seeds_c, k_max, rho_g,
        plan.handover / h * cscale, tseed_c, tkey_g, tpos, piece, npiece,
    )
    del vcost
    release_freed_memory(n)
    t2, c2 = time.perf_counter(), time.process_time()
    stats.update(grid_points=int(k), pops=int(pops), time_grid=t2 - t1, cpu_grid=c2 - c1)
    stats["pops_per_voxel"] = pops / max(band.n_voxels, 1)
    report(progress, "ordering", int(k), k_max)
    # the tail needs the points, the neighbour table and the point ranges only
    u, nbr, cs, perm, keys = band.u, band.nbr, band.cs, band.perm, band.keys
    del band, foot
    runs = _tail_runs(keys, cs, plan.handover / h * cscale / cmin) if k < k_max else None
    del keys  # (before the tail: it holds the coarse runs instead)
    ud = _points_and_values(u, val)
    del u, val
    if runs is not None:
        k = _euclid_tail(
            ud, nbr, cs, runs, pcost, cost is not None, cmin, psep, pnrm, lq, rank,
            order, radius, parent, k, k_max, rho_g, tseed_c, tkey_g, tpos,
        )
    del runs
    stop = _stop_radius(ud[:, 3], rank, tseed_c) * h
    del psep, pnrm, ud, lq, rank, nbr, cs
    release_freed_memory(n)
    stats.update(time_tail=time.perf_counter() - t2, cpu_tail=time.process_time() - c2)
    report(progress, "ordering", int(k), k_max)
    stats["piece_entries"] = _piece_entries(piece, order[:k], npiece)
    del piece
    uorder = perm[order[:k]].astype(np.int64)  # distinct-point index
    del perm, order
    user_grid = voxel_size is not None or band_radius is not None
    radius, stop, stats["rounding_bound"] = _promised(radius[:k] * h, stop, extent, h, r, user_grid)
    parent = parent[:k].astype(np.int64)  # (the kernels' int32 positions)
    o = _assemble(pts, gid, rep, seed_arr, uorder, radius, parent, h, r, rho, size, stats, stop)
    return o if point_pieces is None else dataclasses.replace(o, pieces=point_pieces)


def _input_pieces(piece: np.ndarray, perm: np.ndarray, gid: np.ndarray | None) -> np.ndarray:
    """Each input point's band piece (int32) from the pieces in band order (``perm``: band slot ->
    distinct point; ``gid``: input point -> distinct point, None for the identity)."""
    out = np.empty(perm.shape[0], np.int32)
    out[perm] = piece
    return out if gid is None else out[gid]


def _engine_band(pts, seed_arr, voxel_size, band_radius, max_memory, progress, compiled, lattice=None):
    """The band over the distinct points: (group ids, representatives, engine seeds, number of
    distinct points, their extent, the band, its plan, the engine's stats so far)."""
    gid, rep, upts, useeds = _distinct_points(pts, seed_arr)
    m = upts.shape[0]
    extent = float((axis_max(upts) - axis_min(upts)).max())
    stats: dict[str, Any] = {"engine": "band", "n_points": pts.shape[0], "n_distinct": m}
    band, plan = _band(upts, voxel_size, band_radius, max_memory, progress, compiled, stats, lattice)
    return gid, rep, useeds, m, extent, band, plan, stats


def _distinct_points(pts, seed_arr):
    """The engine's input: (group id per point, representative per group, the distinct points,
    the engine seeds). Without duplicates the ids are None and the points and seeds are the input's."""
    gid, rep = _duplicate_groups(pts, seed_arr)
    if gid is None or rep is None:  # no duplicates
        return None, None, pts, seed_arr
    # engine seeds: the groups of the seeds, first occurrence, in order
    _, first = np.unique(gid[seed_arr], return_index=True)
    return gid, rep, pts[rep], gid[seed_arr][np.sort(first)]


def _engine_seeds(perm, m, useeds, gid, timed, h):
    """The seeds and the timed seeds in band (Morton) numbering, and the timed keys in grid units."""
    inv = np.empty(m, dtype=np.int32)
    inv[perm] = np.arange(m, dtype=np.int32)
    seeds_c = inv[useeds]
    tidx, tkeys = timed if timed is not None else (np.empty(0, np.int64), np.empty(0))
    if gid is not None and tidx.size:  # one timed seed per distinct point: its first (largest key)
        _, first = np.unique(gid[tidx], return_index=True)
        first = np.sort(first)
        tidx, tkeys = gid[tidx[first]], tkeys[first]
    keep = ~np.isin(tidx, useeds)  # a seed is ordered first anyway: the kernels never meet it again
    tidx, tkeys = tidx[keep], tkeys[keep]
    return seeds_c, inv[tidx].astype(np.int32), tkeys / h


def _engine_costs(cost, rep, band):
    """(voxel cost, point cost, least point cost, cost scale): ones for an unweighted run."""
    if cost is None:
        return band.vcost, np.ones(1), 1.0, 1.0
    ucost = (cost if rep is None else cost[rep])[band.perm]
    vcost = band.vcost * ucost[band.foot].astype(np.float32)
    # the scale: hand over at the same Euclidean scale as an unweighted run
    return vcost, ucost, float(ucost.min()), float(ucost.mean())


def _tail_fields(band, plan):
    """(separation, normal, foot voxel) per point for the thin-sheet slope of the ordering; stand-ins
    of one element when the plan found no thin sheets. Frees what the ordering no longer needs."""
    from .band import TAIL_PER_SEP

    if plan.separation is None:
        band.foot = np.zeros(1, dtype=np.int32)  # not needed any more: free it before the ordering
        return np.full(1, np.inf, dtype=np.float32), np.zeros((1, 3), dtype=np.float32), band.foot
    psep = (TAIL_PER_SEP / plan.h * plan.separation[band.perm]).astype(np.float32)
    pnrm = plan.normal[band.perm]
    plan.radius = plan.separation = plan.normal = plan.outer = None  # (copied above: free them)
    return psep, pnrm, band.foot


def _grid_phase(band, vcost, pcost, weighted, foot, pnrm, seeds_c, k_max, rho_g, handover_g,
                tseed_c, tkey_g, tpos, piece, npiece):
    """The ordering on the grid, down to the hand-over radius: the compiled kernel, checked."""
    from .._kernels.march import grid_phase
    from .band import TAIL_SLOPE

    out = grid_phase(
        band.u, band.keys, band.nbr, band.cs, band.near, vcost, pcost, weighted, foot, pnrm,
        TAIL_SLOPE, seeds_c, k_max, rho_g, handover_g, DEBUG, tseed_c, tkey_g, tpos,
        piece, np.int64(npiece),
    )
    pops = out[-1]
    if pops < 0:
        which = "front" if pops == -1 else "candidate"
        raise EngineError(f"the {which} heap broke its invariant (debug check); this is a bug, please report it")
    return out


def _band(upts, voxel_size, band_radius, max_memory, progress, compiled, stats, lattice=None):
    """Plan and build the band of the distinct points; its figures go to ``stats``."""
    from .band import plan_and_build_band

    report(progress, "band", 0, 1)
    band, plan, found = plan_and_build_band(upts, voxel_size, band_radius, max_memory, lattice=lattice)
    release_freed_memory(stats["n_points"])
    stats["thin_points"] = plan.thin_points
    stats["thin_points_found"] = found
    stats["compiled_kernels"] = compiled
    stats["band_voxels"] = band.n_voxels
    stats["band_bytes"] = band.nbytes
    return band, plan


def _pieces(band, stats):
    """The connected piece of the band of each point, and their count (also in ``stats``)."""
    from .._kernels.topology import point_pieces

    known, band.pieces = band.pieces, None  # (found while the band was planned: not again)
    piece, npiece = known if known is not None else point_pieces(band.nbr, band.cs, band.near, band.vcost)
    stats["pieces"] = int(npiece)
    return piece, npiece


def _tail_runs(keys, cs, reach):
    """The coarse runs of the voxel keys that the Euclidean tail searches, for balls of up to
    ``reach`` voxels (cells of side 2^j >= the reach): (rkey, ridx, rstart, rend, levels)."""
    from .._kernels.grid import coarse_runs

    levels = max(0, min(int(np.ceil(np.log2(max(reach, 1.0)))), 9))
    return (*coarse_runs(keys, cs, levels), levels)


def _points_and_values(u: np.ndarray, val: np.ndarray) -> np.ndarray:
    """(M, 4): every point's grid coordinates and its value side by side, so that the tail reads
    both from one cache line (it replaces u and val: no more memory than the two)."""
    ud = np.empty((u.shape[0], 4))
    ud[:, :3] = u
    ud[:, 3] = val
    return ud


def _euclid_tail(ud, nbr, cs, runs, pcost, weighted, cmin, psep, pnrm, lq, rank,
                 order, radius, parent, k, k_max, rho_g, tseed_c, tkey_g, tpos):
    """The ordering below the hand-over radius with exact distances among neighbours (in place);
    returns the new count."""
    from .._kernels.tail import euclid_tail
    from .band import TAIL_SLOPE

    rkey, ridx, rstart, rend, levels = runs
    return euclid_tail(
        ud, nbr, cs, rkey, ridx, rstart, rend, levels, pcost,
        weighted, cmin, psep, pnrm, TAIL_SLOPE, lq, rank, order, radius, parent, k, k_max, rho_g,
        tseed_c, tkey_g, tpos,
    )


def _promised(radius, stop, extent, h, r, user_grid):
    """Radii (and the stop radius) raised by the rounding bound of grid-unit arithmetic, after
    refusing a build whose rounding would swamp them (:mod:`.precision`)."""
    from .precision import check_precision, promise, promise_one, rounding_bound, span

    delta = rounding_bound(span(extent, h, r))
    check_precision(radius, delta, extent=extent, h=h, r=r, user_grid=user_grid)
    return promise(radius, delta), promise_one(stop, delta), delta


PIECE_ENTRIES_MAX = 10_000  # the ranks kept in the build record (a scan of noise has a piece per point)


def _piece_entries(piece: np.ndarray, order: np.ndarray, npiece: int) -> list[int]:
    """The rank at which each piece's first point entered the ordering, ascending (at most
    PIECE_ENTRIES_MAX of them: the first ones), for "the level reaches P of the pieces"
    (``npiece``: the count of pieces; one pass, no sort of the ranks' pieces)."""
    from .._kernels.pieces import first_entries

    where = first_entries(np.ascontiguousarray(piece, np.int32), np.ascontiguousarray(order, np.int32),
                          np.int64(npiece))
    return where[:PIECE_ENTRIES_MAX].tolist()


def _stop_radius(val: np.ndarray, rank: np.ndarray, timed: np.ndarray) -> float:
    """The next candidate's distance (grid units) when the kernels stopped: the largest value of
    a point not ordered (timed seeds are not candidates), 0 when every point is ordered. Each
    value is an upper bound of the point's band distance to the ordered points, so this bounds
    the covering radius of the whole ordering."""
    left = rank < 0
    left[timed] = False
    return float(val[left].max()) if left.any() else 0.0


def _assemble(pts, gid, rep, seed_arr, uorder, radius, parent, h, r, rho, size, stats, stop=0.0):
    """Map the distinct-point ordering back to input indices; add duplicate seeds and duplicates."""
    n = pts.shape[0]
    m = n if rep is None else rep.shape[0]
    stats["n_duplicates"] = int(n - m)
    if rep is None:  # no duplicates: the engine's ordering is the answer
        stats["n_duplicate_seeds"] = 0
        if size is not None and uorder.shape[0] > size:
            stop = max(stop, float(radius[size]))
            uorder, radius, parent = uorder[:size], radius[:size], parent[:size]
        return Ordering(uorder, radius, parent, h, r, seed_arr, n, stats, stop)
    nseed_u = int(np.unique(gid[seed_arr]).size)
    extra = seed_arr[rep[gid[seed_arr]] != seed_arr]  # seeds that are copies of an earlier seed
    shift = seed_arr.shape[0] - nseed_u  # every user seed comes first, copies too
    stats["piece_entries"] = [e if e < nseed_u else e + shift for e in stats.get("piece_entries", [])]
    head = seed_arr  # all user seeds, in the given order, radius inf
    body = rep[uorder[nseed_u:]]
    order = np.concatenate([head, body])
    # engine position -> final position
    epos = np.empty(uorder.shape[0], dtype=np.int64)
    final_pos_of_input = np.full(n, -1, dtype=np.int64)
    final_pos_of_input[order] = np.arange(order.shape[0])
    epos[:] = final_pos_of_input[rep[uorder]]
    rad = np.concatenate([np.full(head.shape[0], np.inf), radius[nseed_u:]])
    par_body = parent[nseed_u:]
    par_body = np.where(par_body >= 0, epos[np.maximum(par_body, 0)], -1)
    par = np.concatenate([np.full(head.shape[0], -1, dtype=np.int64), par_body])
    complete = uorder.shape[0] == m
    if complete and order.shape[0] < n and (rho is None or rho <= 0):
        # exact duplicates: after every distinct point, by the rank of their representative
        placed = np.zeros(n, dtype=bool)
        placed[order] = True
        dups = np.flatnonzero(~placed)
        rk = final_pos_of_input[rep[gid[dups]]]
        srt = np.lexsort((dups, rk))
        dups = dups[srt]
        order = np.concatenate([order, dups])
        rad = np.concatenate([rad, np.zeros(dups.shape[0])])
        par = np.concatenate([par, rk[srt]])
    if size is not None and order.shape[0] > size:
        stop = max(stop, float(rad[size]))
        order, rad, par = order[:size], rad[:size], par[:size]
    stats["n_duplicate_seeds"] = int(extra.size)
    return Ordering(order.astype(np.int64), rad, par.astype(np.int64), h, r, seed_arr, n, stats, stop)
