"""A farthest point ordering that stops at a radius and goes on later, with new sources.

:func:`start_fastfps` builds the band and the kernels' state of :func:`.fastfps.fastfps` and orders
nothing; :func:`resume_fastfps` orders on from where the state stopped down to ``rho`` (or to the
end) and returns the whole ordering so far. The band, the distance field, the front and the
candidate heap are kept between calls, so stopping at ``rho1`` and going on gives exactly the order
of one call (both in the grid phase and in the Euclidean tail).

Sources: points declared at the start as timed seeds (``timed_seeds``, key 0 for "not yet") are
never candidates; a later call may bring some of them in (``sources``): each joins the ordering
as soon as the largest remaining distance is at most its new key (at once when the key is at least
that distance, or not given), is marched like a sample, and appears in the ordering with its key as
radius and no parent, as every timed seed does. The ordering is then the one of
:func:`.fastfps.fastfps` with those keys from the start. No ``cost``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validate import check_positive, validate_indices
from ..errors import InputError
from .fastfps import (
    DEBUG,
    _assemble,
    _engine_band,
    _engine_seeds,
    _pieces,
    _points_and_values,
    _prepare,
    _tail_fields,
    _tail_runs,
    _timed_seeds,
    check_ordering,
)
from .ordering import Ordering


@dataclass(eq=False)
class FastFPSState:
    """Everything an ordering needs to go on (:func:`resume_fastfps`); opaque to callers.

    ``k`` points are ordered; ``phase`` is "grid" (the band and the grid state are held) or
    "tail" (the Euclidean tail: points, values and neighbour tables only)."""

    pts: np.ndarray
    gid: np.ndarray | None
    rep: np.ndarray | None
    seed_arr: np.ndarray
    h: float
    r: float
    handover_g: float
    extent: float
    user_grid: bool
    inv: np.ndarray  # distinct point -> band (cell order) index
    perm: np.ndarray  # band index -> distinct point
    seeds_c: np.ndarray
    tseed_c: np.ndarray
    tkey_g: np.ndarray
    tpos: np.ndarray
    piece: np.ndarray
    npiece: int
    psep: np.ndarray
    pnrm: np.ndarray
    stats: dict[str, Any] = field(default_factory=dict)
    band: Any = None
    foot: Any = None
    grid: tuple | None = None  # the grid kernels' state (_kernels.march.grid_state)
    phase: str = "grid"
    tail: dict[str, Any] = field(default_factory=dict)
    #: band index -> its position in ``tseed_c`` (-1: not a timed seed); kept right for the pending ones
    tslot: np.ndarray = field(default_factory=lambda: np.empty(0, np.int32))

    @property
    def k(self) -> int:
        return int(self.grid[26][0]) if self.grid is not None else int(self.tail["k"])

    @property
    def nbytes(self) -> int:
        """Bytes held by the state's arrays (the input points included)."""
        arrays: list[Any] = [self.pts, self.gid, self.rep, self.inv, self.perm, self.tseed_c, self.tkey_g,
                             self.piece, self.psep, self.pnrm, self.foot, self.tslot]
        arrays += list(self.grid or ()) + [v for v in self.tail.values() if isinstance(v, np.ndarray)]
        arrays += list(self.tail.get("runs") or ())[:4] + list(self.tail.get("heap", ()))
        total = sum(a.nbytes for a in arrays if isinstance(a, np.ndarray))
        return total + (self.band.nbytes if self.band is not None else 0)


def start_fastfps(
    points: Any,
    *,
    seeds: Any = None,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    max_memory: int | None = None,
    timed_seeds: Any = None,
) -> FastFPSState:
    """The state of :func:`.fastfps.fastfps` (same arguments, no ``cost``) before its first point."""
    from .._kernels.march import grid_state
    from .._kernels.warm import ensure_compiled

    voxel_size = check_positive(voxel_size, "voxel_size")
    band_radius = check_positive(band_radius, "band_radius")
    pts, n, _, _, seed_arr = _prepare(points, None, None, seeds)
    timed = _timed_seeds(timed_seeds, n, False)
    compiled = ensure_compiled(None)
    gid, rep, useeds, m, extent, band, plan, stats = _engine_band(
        pts, seed_arr, voxel_size, band_radius, max_memory, None, compiled)
    h = plan.h
    seeds_c, tseed_c, tkey_g = _engine_seeds(band.perm, m, useeds, gid, timed, h)
    inv = np.empty(m, dtype=np.int32)
    inv[band.perm] = np.arange(m, dtype=np.int32)
    piece, npiece = _pieces(band, stats)
    psep, pnrm, foot = _tail_fields(band, plan)
    stats["n_timed_seeds"] = int(tseed_c.size)
    state = FastFPSState(
        pts, gid, rep, seed_arr, h, plan.r, plan.handover / h, extent,
        voxel_size is not None or band_radius is not None, inv, band.perm, seeds_c, tseed_c, tkey_g,
        np.zeros(1, np.int64), piece, int(npiece), psep, pnrm, stats, band, foot,
    )
    state.grid = grid_state(band.u, band.keys, band.cs, m, tseed_c, piece, np.int64(npiece))
    state.tslot = np.full(m, -1, np.int32)
    state.tslot[tseed_c] = np.arange(tseed_c.size, dtype=np.int32)
    return state


def resume_fastfps(state: FastFPSState, *, rho: float | None = None, sources: Any = None,
                   bulk: bool = False) -> Ordering:
    """Order on from where ``state`` stopped until the next insertion radius is <= ``rho`` (to the
    end without), after bringing in ``sources``: indices, or (indices, keys), of timed seeds
    declared at the start that have not joined yet (those that have are skipped); each joins at
    its key, at once when the key is not given or not below the largest remaining distance.
    With ``bulk``, the timed seeds that join at the same moment in the grid phase are marched
    together (one march instead of one each: faster, and the radii are still covering radii, but
    the ordering is no longer the one of :func:`.fastfps.fastfps` with those keys).
    Returns the whole ordering so far (an :class:`Ordering`: its ``stop_radius`` bounds the
    distance of every point not ordered yet)."""
    rho = _advance(state, rho, sources, bulk)
    return _result(state, rho)


def _advance(state: FastFPSState, rho: float | None, sources: Any, bulk: bool, trusted: bool = False) -> float | None:
    """Bring in ``sources`` and order on until the next radius is <= ``rho`` (checked; returned)."""
    rho = check_positive(rho, "rho")
    rho_g = -1.0 if rho is None else rho / state.h
    if sources is not None:
        _bring_in(state, sources, trusted)
    if state.phase == "grid":
        _grid(state, rho_g, bulk)
    if state.phase == "tail" and state.tail["k"] < state.inv.shape[0]:
        _tail(state, rho_g)
    return rho


def resume_news(state: FastFPSState, since: int, *, rho: float | None = None, sources: Any = None,
                bulk: bool = False, _trusted: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`resume_fastfps` without the whole ordering (neither assembled nor checked: the
    ordering it returns later checks every radius): the points ordered from the engine's position
    ``since`` on that are not seeds, as input indices and with the radii that ordering gives them,
    and the position to pass next time. The copies of points (exact duplicates) that the complete
    ordering appends at its end are not among them. ``_trusted``: ``sources`` are indices alone,
    an int64 array of distinct points in range (the radius rounds' own rows), not checked again."""
    from .precision import promise, rounding_bound, span

    _advance(state, rho, sources, bulk, _trusted)
    if state.grid is not None:
        order, radius, k = state.grid[16], state.grid[17], state.k
    else:
        order, radius, k = state.tail["order"], state.tail["radius"], int(state.tail["k"])
    first = max(since, news_start(state))
    uorder = state.perm[order[first:k]].astype(np.int64)
    rad = promise(radius[first:k] * state.h, rounding_bound(span(state.extent, state.h, state.r)))
    return (uorder if state.rep is None else state.rep[uorder]), rad, k


def news_start(state: FastFPSState) -> int:
    """The engine's position of its first point that is not a seed (the seeds come first)."""
    if state.rep is None or state.gid is None:
        return int(state.seed_arr.shape[0])
    return int(np.unique(state.gid[state.seed_arr]).size)


def _tail(state: FastFPSState, rho_g: float) -> None:
    """The Euclidean tail from where it stopped (its values and cell heap kept)."""
    from .._kernels.tail import tail_loop, tail_start
    from .band import TAIL_SLOPE

    t = state.tail
    one = np.ones(1)
    if "heap" not in t:  # (first time: the values tightened, the heap built, as euclid_tail does)
        t["heap"] = tail_start(t["ud"], t["cs"], one, False, state.psep, state.pnrm, TAIL_SLOPE, t["lq"], t["rank"],
                               t["order"])
        t["hn"] = np.full(1, t["heap"][2].shape[0], np.int64)
    rkey, ridx, rstart, rend, levels = t["runs"]
    t["k"] = tail_loop(
        t["ud"], t["nbr"], t["cs"], rkey, ridx, rstart, rend, levels, one, False, 1.0, state.psep, state.pnrm,
        TAIL_SLOPE, t["lq"], t["rank"], t["order"], t["radius"], t["parent"], t["k"], state.inv.shape[0], rho_g,
        state.tseed_c, state.tkey_g, state.tpos, *t["heap"], t["hn"],
    )


def _now(state: FastFPSState) -> float:
    """The largest value of a point not ordered (grid units): the radius of the next candidate.
    :func:`.fastfps._stop_radius`'s value without its copies: the timed seeds (never candidates)
    are the points with a slot (``tslot``), and the maximum is taken in place."""
    if state.phase == "grid":
        assert state.grid is not None
        val, rank = state.grid[5], state.grid[7]
    else:
        val, rank = state.tail["ud"][:, 3], state.tail["rank"]
    left = rank < 0
    left &= state.tslot < 0
    top = float(np.max(val, where=left, initial=-np.inf))
    return 0.0 if top == -np.inf else top


def _bring_in(state: FastFPSState, sources: Any, trusted: bool = False) -> None:
    """Give the pending timed seeds named in ``sources`` their new keys (in place, re-sorted);
    ``trusted``: see :func:`resume_news`."""
    if trusted:
        idx = sources
        keys = np.full(idx.size, np.inf)
    elif isinstance(sources, tuple):
        idx = validate_indices(sources[0], state.pts.shape[0], "sources")
        keys = np.asarray(sources[1], dtype=np.float64).reshape(-1)
        if keys.shape != idx.shape or np.isnan(keys).any() or (keys < 0).any():
            raise InputError(
                f"sources needs one non-negative key per index ({idx.size} indices, {keys.size} keys); "
                "pass (indices, keys) of equal length"
            )
        keys = keys / state.h
    else:
        idx = validate_indices(sources, state.pts.shape[0], "sources")
        keys = np.full(idx.size, np.inf)
    if state.gid is not None:
        idx = state.gid[idx]
    band_idx = state.inv[idx]
    pos = int(state.tpos[0])
    slot = state.tslot[band_idx]  # (a pending timed seed's position in tseed_c; -1: not a timed seed)
    if (slot < 0).any():
        odd = slot < 0
        odd[odd] = ~np.isin(band_idx[odd], state.seeds_c)  # (the seeds are ordered first: skipped as joined)
        if odd.any():
            bad = int(np.flatnonzero(odd)[0])
            raise InputError(
                f"sources[{bad}] was not a timed seed at the start; pass every point that may become a source "
                "in timed_seeds (key 0: not yet)"
            )
    live = slot >= pos  # (a source that has joined already is skipped)
    if not live.any():
        return
    tkey = state.tkey_g[pos:].copy()
    at = slot[live] - pos
    tkey[at] = np.minimum(keys[live], _now(state))
    moved = np.zeros(tkey.size, bool)
    moved[at] = True
    rest = np.flatnonzero(~moved)
    if rest.size == 0 or tkey[at].min() > tkey[rest[0]]:
        # (the usual case: every new key above the others, which stay sorted: the stable sort is
        # the moved ones sorted among themselves, then the others in their order)
        mine = np.flatnonzero(moved)
        srt = np.concatenate([mine[np.argsort(-tkey[mine], kind="stable")], rest])
    else:
        srt = np.argsort(-tkey, kind="stable")
    state.tseed_c[pos:] = state.tseed_c[pos:][srt]
    state.tkey_g[pos:] = tkey[srt]
    state.tslot[state.tseed_c[pos:]] = np.arange(pos, state.tseed_c.size, dtype=np.int32)


def _grid(state: FastFPSState, rho_g: float, bulk: bool) -> None:
    """The grid phase from where it stopped; on to the tail state when it is done."""
    from .._kernels.march import grid_loop, grid_wake_all
    from .band import TAIL_SLOPE

    band, st = state.band, state.grid
    assert st is not None
    m = state.inv.shape[0]
    bad = grid_loop(
        band.u, band.keys, band.nbr, band.cs, band.near, band.vcost, np.ones(1), False, state.foot, state.pnrm,
        TAIL_SLOPE, state.seeds_c, m, rho_g, state.handover_g, DEBUG, state.tseed_c, state.tkey_g,
        state.tpos, state.piece, np.int64(state.npiece), st, bulk,
    )
    if bad < 0:
        from ..errors import EngineError

        raise EngineError("a heap broke its invariant (debug check); this is a bug, please report it")
    ctr, ckey = st[26], st[11]
    k, hn = int(ctr[0]), int(ctr[1])
    if k < m and hn > 0 and ckey[0] >= 0.0 and ckey[0] >= state.handover_g:
        return  # stopped at rho: stay in the grid phase
    grid_wake_all(band.u, band.cs, np.ones(1), False, np.int64(state.npiece), st)
    runs = _tail_runs(band.keys, band.cs, state.handover_g) if k < m else None
    state.stats.update(grid_points=k, pops=int(ctr[3]))
    state.tail = {
        "ud": _points_and_values(band.u, st[5]), "nbr": band.nbr, "cs": band.cs, "runs": runs, "lq": st[6],
        "rank": st[7], "order": st[16], "radius": st[17], "parent": st[18], "k": k,
    }
    state.grid = state.band = state.foot = None
    state.phase = "tail"


def _result(state: FastFPSState, rho: float | None) -> Ordering:
    """The whole ordering so far, in input indices (as :func:`.fastfps.fastfps` returns it)."""
    if state.grid is not None:
        order, radius, parent, k = state.grid[16], state.grid[17], state.grid[18], state.k
    else:
        t = state.tail
        order, radius, parent, k = t["order"], t["radius"], t["parent"], t["k"]
    from .precision import check_precision, promise, promise_one, rounding_bound, span

    stop = _now(state) * state.h
    uorder = state.perm[order[:k]].astype(np.int64)
    rad = radius[:k] * state.h
    delta = rounding_bound(span(state.extent, state.h, state.r))
    # the precision check on the radii this ordering measured: not the timed seeds' keys (no
    # parent, finite; "not yet" ones that never joined come last with key 0)
    chosen = (parent[:k] >= 0) | ~np.isfinite(rad)
    check_precision(rad[chosen], delta, extent=state.extent, h=state.h, r=state.r, user_grid=state.user_grid)
    rad, stop = promise(rad, delta), promise_one(stop, delta)
    stats = dict(state.stats, rounding_bound=delta)
    o = _assemble(state.pts, state.gid, state.rep, state.seed_arr, uorder, rad, parent[:k].astype(np.int64),
                  state.h, state.r, rho, None, stats, stop)
    return check_ordering(o)
