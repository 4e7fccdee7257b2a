"""Public farthest point ordering: validation and orchestration around the compiled kernels."""

from __future__ import annotations

import logging
import os
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

log = logging.getLogger(__name__)


def default_seed(points: np.ndarray) -> int:
    """The deterministic default seed: the point nearest the centroid (lowest index on ties)."""
    c = points.mean(axis=0)
    return int(np.argmin(((points - c) ** 2).sum(axis=1)))


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
    o = _run_engine(pts, rho, size, seed_arr, voxel_size, band_radius, c, max_memory, progress, timed)
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


def _duplicate_groups(pts: np.ndarray, seeds: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Group exact duplicates. Returns (group id per point, representative input index per group).

    The representative is the first listed seed of the group if any, else its lowest index.
    """
    n = pts.shape[0]
    # a quick check first: if the points' hashes are all different, so are the points (most scans)
    bits = (pts + 0.0).view(np.uint64)  # + 0.0: -0.0 and 0.0 are the same point
    hsh = bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)
    hsh ^= bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
    hsh ^= bits[:, 2] * np.uint64(0x165667B19E3779F9)
    hsh.sort()
    if not (hsh[1:] == hsh[:-1]).any():
        return None, None
    del bits, hsh
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


def _run_engine(pts, rho, size, seed_arr, voxel_size, band_radius, cost, max_memory, progress, timed=None):
    import time

    from .._kernels.warm import ensure_compiled
    from .band import TAIL_PER_SEP, TAIL_SLOPE, plan_and_build_band

    compiled = ensure_compiled(progress)  # a cold numba cache: compile first, and say so
    t0 = time.perf_counter()
    c0 = time.process_time()
    n = pts.shape[0]
    gid, rep = _duplicate_groups(pts, seed_arr)
    if gid is None or rep is None:  # no duplicates
        m, upts, useeds = n, pts, seed_arr
    else:
        m = rep.shape[0]
        upts = pts[rep]
        # engine seeds: the groups of the seeds, first occurrence, in order
        _, first = np.unique(gid[seed_arr], return_index=True)
        useeds = gid[seed_arr][np.sort(first)]
    report(progress, "band", 0, 1)
    extent = float(np.ptp(upts, axis=0).max())
    band, plan, found = plan_and_build_band(upts, voxel_size, band_radius, max_memory)
    release_freed_memory(n)
    h, r = plan.h, plan.r
    stats: dict[str, Any] = {"engine": "band", "n_points": n, "n_distinct": m}
    stats["thin_points"] = plan.thin_points
    stats["thin_points_found"] = found
    stats["compiled_kernels"] = compiled
    k_max = m if size is None else min(m, size)
    del upts
    stats["band_voxels"] = band.n_voxels
    stats["band_bytes"] = band.nbytes
    t1 = time.perf_counter()
    c1 = time.process_time()
    stats["time_band"] = t1 - t0
    stats["cpu_band"] = c1 - c0
    report(progress, "band", 1, 1)
    weighted = cost is not None
    inv = np.empty(m, dtype=np.int32)
    inv[band.perm] = np.arange(m, dtype=np.int32)
    seeds_c = inv[useeds]
    tidx, tkeys = timed if timed is not None else (np.empty(0, np.int64), np.empty(0))
    if gid is not None and tidx.size:  # one timed seed per distinct point: its first (largest key)
        _, first = np.unique(gid[tidx], return_index=True)
        first = np.sort(first)
        tidx, tkeys = gid[tidx[first]], tkeys[first]
    keep = ~np.isin(tidx, useeds)  # a seed is ordered first anyway: the kernels never meet it again
    tidx, tkeys = tidx[keep], tkeys[keep]
    tseed_c = inv[tidx].astype(np.int32)
    tkey_g = tkeys / h
    tpos = np.zeros(1, np.int64)
    stats["n_timed_seeds"] = int(tidx.size)
    del inv
    if weighted:
        ucost = (cost if rep is None else cost[rep])[band.perm]
        vcost = band.vcost * ucost[band.foot].astype(np.float32)
        pcost = ucost
        cmin = float(ucost.min())
        cscale = float(ucost.mean())  # hand over at the same Euclidean scale as an unweighted run
    else:
        cscale = 1.0
        vcost = band.vcost
        pcost = np.ones(1)
        cmin = 1.0
    from .._kernels.march import grid_phase
    from .._kernels.tail import euclid_tail
    from .._kernels.topology import point_pieces

    piece, npiece = point_pieces(band.nbr, band.cs, band.near, band.vcost)
    stats["pieces"] = int(npiece)

    if plan.separation is None:
        psep = np.full(1, np.inf, dtype=np.float32)
        pnrm = np.zeros((1, 3), dtype=np.float32)
        foot = np.zeros(1, dtype=np.int32)
        band.foot = foot  # not needed any more: free it before the ordering
    else:
        psep = (TAIL_PER_SEP / h * plan.separation[band.perm]).astype(np.float32)
        pnrm = plan.normal[band.perm]
        foot = band.foot
        plan.radius = plan.separation = plan.normal = plan.outer = None  # (copied above: free them)
    rho_g = -1.0 if rho is None else rho / h
    report(progress, "ordering", 0, k_max)
    order, radius, parent, k, val, lq, rank, pops = grid_phase(
        band.u, band.keys, band.nbr, band.cs, band.near, vcost, pcost, weighted, foot, pnrm,
        TAIL_SLOPE, seeds_c, k_max, rho_g, plan.handover / h * cscale, DEBUG, tseed_c, tkey_g, tpos,
        piece, np.int64(npiece),
    )
    del vcost
    release_freed_memory(n)
    if pops < 0:
        which = "front" if pops == -1 else "candidate"
        raise EngineError(f"the {which} heap broke its invariant (debug check); this is a bug, please report it")
    t2 = time.perf_counter()
    c2 = time.process_time()
    stats.update(grid_points=int(k), pops=int(pops), time_grid=t2 - t1, cpu_grid=c2 - c1)
    stats["pops_per_voxel"] = pops / max(band.n_voxels, 1)
    report(progress, "ordering", int(k), k_max)
    # the tail needs the points, the neighbour table and the point ranges only
    u, nbr, cs, perm, keys = band.u, band.nbr, band.cs, band.perm, band.keys
    del band, foot
    if k < k_max:
        from .._kernels.grid import coarse_runs

        reach = plan.handover / h * cscale / cmin  # the largest ball of the tail, in voxels
        levels = max(0, min(int(np.ceil(np.log2(max(2.0 * reach, 1.0)))), 9))
        rkey, ridx, rstart, rend = coarse_runs(keys, cs, levels)
        del keys
        k = euclid_tail(
            u, nbr, cs, rkey, ridx, rstart, rend, levels, pcost,
            weighted, cmin, psep, pnrm, TAIL_SLOPE, val, lq, rank, order, radius, parent, k, k_max, rho_g,
            tseed_c, tkey_g, tpos,
        )
        del rkey, ridx, rstart, rend
    stop = _stop_radius(val, rank, tseed_c) * h
    del psep, pnrm, val, lq, rank, u, nbr, cs
    release_freed_memory(n)
    t3 = time.perf_counter()
    stats["time_tail"] = t3 - t2
    stats["cpu_tail"] = time.process_time() - c2
    report(progress, "ordering", int(k), k_max)
    stats["piece_entries"] = _piece_entries(piece, order[:k])
    del piece
    uorder = perm[order[:k]].astype(np.int64)  # distinct-point index
    del perm, order
    user_grid = voxel_size is not None or band_radius is not None
    radius, stop, stats["rounding_bound"] = _promised(radius[:k] * h, stop, extent, h, r, user_grid)
    parent = parent[:k].astype(np.int64)
    return _assemble(pts, gid, rep, seed_arr, uorder, radius, parent, h, r, rho, size, stats, stop)


def _promised(radius, stop, extent, h, r, user_grid):
    """Radii (and the stop radius) raised by the rounding bound of grid-unit arithmetic, after
    refusing a build whose rounding would swamp them (:mod:`.precision`)."""
    from .precision import check_precision, promise, promise_one, rounding_bound, span

    delta = rounding_bound(span(extent, h, r))
    check_precision(radius, delta, extent=extent, h=h, r=r, user_grid=user_grid)
    return promise(radius, delta), promise_one(stop, delta), delta


PIECE_ENTRIES_MAX = 10_000  # the ranks kept in the build record (a scan of noise has a piece per point)


def _piece_entries(piece: np.ndarray, order: np.ndarray) -> list[int]:
    """The rank at which each piece's first point entered the ordering, ascending (at most
    PIECE_ENTRIES_MAX of them: the first ones), for "the level reaches P of the pieces"."""
    _, where = np.unique(piece[order], return_index=True)
    return np.sort(where)[:PIECE_ENTRIES_MAX].tolist()


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
