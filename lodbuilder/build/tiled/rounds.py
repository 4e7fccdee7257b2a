"""Radius rounds (issue 19, seams; the build option ``seam_rounds``, off by default): every tile
ordered in rounds.

Round p (1 .. R) takes every tile, colour by colour, from radius r_head / q^(p - 1) down to
r_head / q^p (r_head: the head's last radius); round R + 1 to the end. Each tile goes on from where
its last round stopped (:mod:`lodbuilder.sampling.resumable`: its band, distance field and heaps are
kept), and before each round its neighbours' points in its halo that they have ordered since its
last round join its ordering at once as sources (those of the neighbours of a lower colour ordered
in this round included; in the last round, the points below the last round's radius at their
keys, as timed seeds). A tile of a lower colour is then blind to its neighbours for one round
only, not for the whole ordering, and the points of different tiles keep their distance (see
docs/benchmarks.md, "Seams"); the covering pays for the sources that join early (ratio q).

The build runs the rounds in parallel (:mod:`.affinity`): each tile's state lives in one worker
process, its *owner*, for all rounds (:func:`round_step`, :func:`round_finish`; the states in
``_LIVE``), and only each round's new points near a neighbour travel, through the parent.
:func:`order_rounds` is the same in one task that holds every state (the reference the parallel
rounds match bit for bit: tests/test_rounds_parallel.py). Memory: a state costs about
:data:`.affinity.STATE_BYTES_PER_POINT` per point of its tile with its halo, an owner holds all
its tiles' states at once, and the rounds run only where that fits the worker budget (else the
build is refused: the error says what the workers would need; the build record's ``tiled.rounds``
says how the rounds ran).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import Any

import numpy as np

from . import layout as WL
from .blocks import tile_records
from .store import Store, as_store
from .tasks import HEAD, _put_tile, _stream, in_sorted
from .timing import timed_step, timed_task

#: the rounds' radius ratio q: each round orders every tile down to 1 / q of the last one's radius
#: (the covering pays for the sources that join early, at most this ratio: 1.05, the issue's target)
Q = 1.05
#: the rounds go down to about the radius of the level that holds this share of the points
#: (the issue measures the seams from the head to 3 %; the surface estimate below can be short)
DEPTH = 0.05
#: private: (rounds R, ratio q) instead of :func:`schedule`'s (tools/bench_seams.py, tests)
TILE_ROUNDS: tuple[int, float] | None = None


def schedule(n: int, head_points: int) -> tuple[int, float]:
    """How many rounds R and their ratio q for ``n`` points whose head has ``head_points``: rounds
    from the head's radius down to about the radius of the level of :data:`DEPTH` x ``n`` points, on
    a surface (a level's radius falls as the square root of its size): R = ln(DEPTH n / head) / (2 ln q)."""
    if TILE_ROUNDS is not None:
        return TILE_ROUNDS
    depth = DEPTH * n / max(head_points, 1)
    return max(1, math.ceil(0.5 * math.log(max(depth, 1.0)) / math.log(Q))), Q


def radii(head: np.ndarray, rounds: int, q: float) -> list[float | None]:
    """The radius each round stops at: the head's last radius / q^p for p = 1 .. ``rounds``, then
    None (to the end; only that when the head has no finite radius)."""
    r0 = float(head["r"][-1]) if head.shape[0] and np.isfinite(head["r"][-1]) else None
    return [None] if r0 is None else [r0 / q**p for p in range(1, rounds + 1)] + [None]


def _start(w: Store, t: int, doc: dict[str, Any], head: np.ndarray, hpts: np.ndarray, voxel_size: float,
           band_radius: float, halo: float, max_memory: int | None) -> dict[str, Any]:
    """Tile ``t``'s ordering state: its core, the head points in its core and halo as seeds, and
    every halo point not in the head as a timed seed that has not joined yet (key 0)."""
    from ...sampling.resumable import start_fastfps

    core = tile_records(w, doc["core"])
    lo, hi = np.asarray(doc["lo"]), np.asarray(doc["hi"])
    cpts = np.stack([core["x"], core["y"], core["z"]], axis=1)
    in_ext = np.all((hpts >= lo - halo) & (hpts <= hi + halo), axis=1)
    head_in_core, pos_in_core = in_sorted(head["g"], core["g"])  # (core is in input order)
    extra = in_ext & ~head_in_core
    seeds = np.concatenate([pos_in_core,
                            cpts.shape[0] + np.arange(int(extra.sum()))]).astype(np.int64)
    hrec = tile_records(w, doc["halo"])
    hrec = hrec[~in_sorted(hrec["g"], np.sort(head["g"]))[0]]
    first = cpts.shape[0] + int(extra.sum())
    pts = np.concatenate([cpts, hpts[extra], np.stack([hrec["x"], hrec["y"], hrec["z"]], axis=1)])
    rows = first + np.arange(hrec.shape[0])
    state = start_fastfps(pts, seeds=seeds if seeds.size else None, voxel_size=voxel_size,
                          band_radius=band_radius, max_memory=max_memory, timed_seeds=(rows, np.zeros(rows.size)))
    is_seed = np.zeros(pts.shape[0], bool)
    is_seed[seeds] = True
    srt = np.argsort(hrec["g"], kind="stable")
    return {"t": t, "core": core, "cpts": cpts, "lo": lo, "hi": hi, "interior": np.asarray(doc["interior"], bool),
            "is_seed": is_seed, "halo_g": hrec["g"][srt], "halo_rows": rows[srt], "state": state, "o": None,
            "seen": {}, "n_seeds": int(seeds.size)}


def _sources(tiles: dict[int, dict[str, Any]], t: int, nbrs: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The points in tile ``t``'s halo that its neighbours ordered since ``t``'s last round:
    (rows of ``t``'s points, keys)."""
    me = tiles[t]
    news: list[tuple[np.ndarray, np.ndarray] | None] = []
    for u in nbrs:
        if tiles[u]["o"] is None or me["halo_g"].size == 0:
            news.append(None)
            continue
        start = me["seen"].get(u, 0)
        me["seen"][u] = len(tiles[u]["o"])
        news.append(_news(tiles[u], start))
    return _halo_rows(me, news)


def _news(tile: dict[str, Any], start: int, near: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A tile's own points ordered from position ``start`` on (their input ids ``g``, keys); with
    ``near`` (a mask of its core points) only those it marks."""
    return _own(tile, tile["o"].order[start:], tile["o"].radius[start:], near)


def _own(tile: dict[str, Any], new: np.ndarray, rad: np.ndarray, near: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Of points ``new`` of a tile's ordering (radii ``rad``), those of its core with a finite radius
    (and marked in ``near``): (input ids, radii)."""
    own = (new < tile["cpts"].shape[0]) & np.isfinite(rad)
    idx, rad = new[own], rad[own]
    if near is not None:
        keep = near[idx]
        idx, rad = idx[keep], rad[keep]
    return tile["core"]["g"][idx], rad


def _in_boxes(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Which points ``p`` lie in one of the boxes (``lo``, ``hi``: their corners, one a row)."""
    keep = np.zeros(p.shape[0], bool)
    for a, b in zip(lo, hi, strict=True):
        keep |= np.all((p >= a) & (p <= b), axis=1)
    return keep


def _halo_rows(me: dict[str, Any], news: list[tuple[np.ndarray, np.ndarray] | None]) -> tuple[np.ndarray, np.ndarray]:
    """The rows of tile ``me``'s points and the keys of the neighbours' new points ``news`` (each
    neighbour's (g, keys), in :func:`_news`'s order; None: not ordered yet) that lie in its halo."""
    have = [new for new in news if new is not None and new[0].size]
    if not have or me["halo_g"].size == 0:
        return np.empty(0, np.int64), np.empty(0)
    g = np.concatenate([new[0] for new in have]) if len(have) > 1 else have[0][0]
    rad = np.concatenate([new[1] for new in have]) if len(have) > 1 else have[0][1]
    pos = np.minimum(np.searchsorted(me["halo_g"], g), me["halo_g"].size - 1)
    hit = me["halo_g"][pos] == g
    return me["halo_rows"][pos[hit]], rad[hit]


def _joining(rows: np.ndarray, keys: np.ndarray, rho: float | None) -> Any:
    """``resume_fastfps``'s sources: in a round every source joins at once (the points the
    neighbours of a lower colour ordered in this round too: this tile keeps away from them); in
    the last, the neighbours' points below the last round's radius join at their keys."""
    return None if rows.size == 0 else rows if rho is not None else (rows, keys)


@timed_task
def order_rounds(work: Store | str, docs: dict[int, dict[str, Any]], nbrs: list[list[int]], colour: list[int],
                 voxel_size: float, band_radius: float, halo: float, max_memory: int | None, rounds: int,
                 q: float) -> dict[str, Any]:
    """Order every tile in ``rounds`` radius rounds of ratio ``q`` and one last round to the end
    (see the module); writes each tile's stream and seam points as :func:`.tasks.order_tile` does
    and returns their results (``tiles``) and the largest state of a tile in bytes."""
    from ...sampling.resumable import resume_fastfps

    w = as_store(work)
    head, hpts = _head(w)
    tiles = {t: _start(w, t, doc, head, hpts, voxel_size, band_radius, halo, max_memory) for t, doc in docs.items()}
    seq = sorted(tiles, key=lambda t: colour[t])
    state_bytes = 0
    for rho in radii(head, rounds, q):
        for t in seq:
            rows, keys = _sources(tiles, t, nbrs[t])
            state_bytes = max(state_bytes, tiles[t]["state"].nbytes)
            tiles[t]["o"] = resume_fastfps(tiles[t]["state"], rho=rho, sources=_joining(rows, keys, rho), bulk=True)
    out = [_finish(w, tiles[t], hpts, halo) for t in sorted(tiles)]
    return {"tiles": out, "state_bytes": state_bytes, "rounds": rounds, "q": q}


#: the tile states this process owns in parallel rounds (:mod:`.affinity`): (build key, tile) -> state
_LIVE: dict[tuple[str, int], dict[str, Any]] = {}


def _head(w: Store) -> tuple[np.ndarray, np.ndarray]:
    head = w.read_array(WL.HEAD_FILE, HEAD)
    return head, np.stack([head["x"], head["y"], head["z"]], axis=1)


@timed_step
def round_steps(work: Store | str, key: str, calls: list[tuple[int, dict[str, Any] | None, list[Any]]],
                rho: float | None, step: Any = None) -> dict[str, Any]:
    """One round of each tile of ``calls`` ((tile, doc, news) as :func:`round_step` takes them), in
    the process that owns them, one after the other (``step``: :func:`round_step`); their results.
    A tile that fails is named on the exception (``lodbuilder_tile``)."""
    out = []
    for t, doc, news in calls:
        with _naming(t):
            out.append((step or round_step)(work, t, key, doc, rho, news))
    return {"tiles": out}


@contextlib.contextmanager
def _naming(t: int) -> Iterator[None]:
    """An exception raised within names tile ``t`` (``lodbuilder_tile``: the parent's message)."""
    try:
        yield
    except Exception as exc:
        with contextlib.suppress(Exception):  # (an exception that takes no attributes)
            exc.lodbuilder_tile = t  # type: ignore[attr-defined]
        raise


def round_step(work: Store | str, t: int, key: str, doc: dict[str, Any] | None, rho: float | None,
               news: list[tuple[np.ndarray, np.ndarray] | None]) -> dict[str, Any]:
    """One round of tile ``t`` in the process that owns its state (kept in ``_LIVE`` under
    ``key``): started on the first (``doc``: the tile as :func:`order_rounds`'s, with ``args``,
    its voxel size, band radius, halo and memory, and ``near``, its neighbours' halo boxes), then
    ordered down to ``rho`` after its neighbours' new points in its halo (``news``: (g, keys) or
    None per neighbour) join. Returns the points it ordered in this round that lie in a
    neighbour's halo box (``g``, ``keys``), the bytes of its state and about how many of its points
    are ordered so far (``ordered``: positions of the ordering, seeds included, at most its core's)."""
    from ...sampling.resumable import news_start, resume_fastfps, resume_news

    tile = _LIVE.get((key, t))
    if tile is None:
        if doc is None:
            raise RuntimeError(f"tile {t}'s state of the rounds is not in this worker process (was it restarted?)")
        w = as_store(work)
        head, hpts = _head(w)
        tile = _start(w, t, doc, head, hpts, *doc["args"])
        tile["near"] = _in_boxes(tile["cpts"], np.asarray(doc["near"][0], float).reshape(-1, 3),
                                 np.asarray(doc["near"][1], float).reshape(-1, 3))
        _LIVE[(key, t)] = tile
    rows, keys = _halo_rows(tile, news)
    st, since = tile["state"], tile.get("k", 0)
    if rho is not None:  # (the points of this round only: the whole ordering is not needed yet)
        new, rad, tile["k"] = resume_news(st, since, rho=rho, sources=_joining(rows, keys, rho), bulk=True,
                                          _trusted=True)
        g, k = _own(tile, new, rad, tile["near"])
    else:  # (the seeds come first; the ordering's positions are the engine's after its copies of seeds)
        tile["o"] = resume_fastfps(st, rho=rho, sources=_joining(rows, keys, rho), bulk=True)
        shift = st.seed_arr.shape[0] - news_start(st) if since >= news_start(st) else 0
        g, k = _news(tile, since + shift, tile["near"])
    done = tile["cpts"].shape[0] if rho is None else min(int(tile["k"]), tile["cpts"].shape[0])
    return {"tile": t, "g": g, "keys": k, "state_bytes": _nbytes(tile), "ordered": done}


def _nbytes(tile: dict[str, Any]) -> int:
    """The bytes of a tile's state, counted again only when its arrays change (a new phase, the
    tail's heap made): a count walks some forty arrays."""
    st = tile["state"]
    at = (st.phase, len(st.tail))
    if tile.get("nb_at") != at:
        tile["nb_at"], tile["nb"] = at, int(st.nbytes)
    return int(tile["nb"])


@timed_task
def round_finish(work: Store | str, key: str, ts: list[int], halo: float) -> dict[str, Any]:
    """The streams and seam points of tiles ``ts`` written from their states, which are dropped."""
    w = as_store(work)
    hpts = _head(w)[1]
    out = []
    for t in ts:
        with _naming(t):
            out.append(_finish(w, _LIVE.pop((key, t)), hpts, halo))
    return {"tiles": out}


def round_drop(key: str) -> int:
    """Drop every state of ``key`` this process holds (a failed build); how many."""
    gone = [k for k in _LIVE if k[0] == key]
    for k in gone:
        del _LIVE[k]
    return len(gone)


def _finish(w: Store, tile: dict[str, Any], hpts: np.ndarray, halo: float) -> dict[str, Any]:
    """Write a tile's stream and seam points; its result as :func:`.tasks.order_tile` returns it."""
    t, o = tile["t"], tile["o"]
    stream = _stream(o, tile["is_seed"], tile["core"], tile["cpts"], hpts, tile["lo"], tile["hi"], tile["interior"])
    files, n_seam = _put_tile(w, t, stream, halo, None)
    tile["state"] = None
    return {"tile": t, "n_points": int(tile["core"].shape[0]), "n_stream": int(stream.shape[0]),
            "n_seeds": tile["n_seeds"], "n_timed": int(tile["halo_rows"].size), "n_seam": n_seam,
            "key_hist": WL.key_hist(stream["key"]), "band_voxels": int(o.stats.get("band_voxels", 0)),
            "files": files}
