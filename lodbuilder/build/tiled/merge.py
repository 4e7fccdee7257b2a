"""Merging the tile orderings into one order, and the exact covering radii of that order.

**Merge.** The head (the coarse global level) comes first, in its own order. Then the tile streams
are merged by descending key (an external k-way merge: each tile's stream is read block by block,
never whole). Seam repair: a point closer to a tile boundary than its key (a *seam point*) is
checked, when its turn comes, against the points of other tiles (and the head) accepted so far;
if one lies within ``alpha`` times its key it waits: its key becomes (distance / ``alpha``) and it
is merged again at that key, when the check is repeated (a lazy greedy over the seam points only).
Every accepted point is therefore at least ``alpha`` times its acceptance key from every earlier
point of another tile; inside a tile the tile's own farthest point order keeps its points apart.

**Replacement.** A seam point that waits leaves a gap on its side of the face: its tile ordered its
later points as if it were there, and the other tile's point that stopped it lies across the face
(the covering at equal size grew up to 1.14 x the in-memory build's at ``alpha`` 0.5 on a wavy sheet
in 16 tiles). So the first time a point of the seam zone (rows within ``ZONE`` x their key of a
shared face, read once before the merge: a few times the points along the faces at the finest
spacing) waits, one of its tile's later points near it takes its place at once, at its key: among
the rows of its tile within its key of it whose key is at least ``KEY_FLOOR`` and ``alpha`` times its key (rows
its tile ordered soon after it, :func:`seam_candidates`), still in their stream, the one farthest
from the accepted points (at least ``GAP`` x key, or none: no gap worth filling), if at least
``alpha`` x key from every accepted point of another tile. Its row is skipped when its stream
reaches it. It keeps ``alpha`` x its key from the other tiles like every merged point, and from
the rows its tile ordered between the two (they are at least its own key from it). So at ``alpha``
1 nothing replaces (the candidates' keys would have to equal the demoted row's). The accepted points a replacement measures against: the head, and the merged rows
within ``REACH`` x their key of a shared face (kept in a hash grid with the replacements).

**Radii.** The keys decide the order; the radii stored with it are proven: for each tile, the
exact covering radius of its core by every prefix of the final order (computed from the core and
its halo, exact while below the halo width, an upper bound above it: :func:`cover_tile`), combined
by a k-way merge over tiles (the maximum), capped by the certified bound of the coarse level
(its radius on the decimated copy plus the decimation cell's diagonal) and made non-increasing:
in bands of positions, by tasks (:mod:`.radii`).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from ...progress import ProgressCallback, report
from . import layout as WL
from . import workdir as W
from .store import Store, as_store
from .tasks import HEAD, STREAM
from .timing import timed_task

log = logging.getLogger(__name__)

BUF = 1 << 16  # rows per tile buffer in the merge
#: the seam zone: the rows within ZONE x their key of a face their tile shares (the replacements'
#: candidates are among them), the accepted rows within REACH x their key of one (the replacements
#: measure gaps against them) and the smallest gap a replacement fills (x key): see the module
ZONE = 4.0
REACH = 3.0
GAP = 0.5
#: a replacement's key is at least KEY_FLOOR x the demoted row's (see seam_candidates)
KEY_FLOOR = 0.5


class _StreamReader:
    def __init__(self, store: Store, name: str) -> None:
        self.f = store.open(name)
        self.left = (store.size(name) or 0) // STREAM.itemsize

    def read(self, rows: int) -> np.ndarray:
        m = min(rows, self.left)
        a = W.read_rows(self.f, np.dtype("<f8"), 6 * m).reshape(m, 6)
        self.left -= m
        return a

    def close(self) -> None:
        self.f.close()


def _zone_rows(work: Store, n_tiles: int) -> tuple[np.ndarray, np.ndarray]:
    """The zone rows of every tile's stream (margin < ``ZONE`` x key) and their tiles: one read of
    the streams, block by block, keeping only those rows."""
    parts, tiles = [], []
    for t in range(n_tiles):
        r = _StreamReader(work, WL.stream(t))
        try:
            while r.left:
                a = r.read(16 * BUF)
                parts.append(a[a[:, 5] < ZONE * a[:, 1]])
                tiles.append(np.full(parts[-1].shape[0], t, np.int64))
        finally:
            r.close()
    if not parts:
        return np.empty((0, 6)), np.empty(0, np.int64)
    return np.ascontiguousarray(np.concatenate(parts)), np.concatenate(tiles)


def seam_candidates(rows: np.ndarray, tile: np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """For each zone row that is a seam row (margin < key), the rows that may replace it when it is
    demoted: rows of its tile within its key of it, with a key from ``floor`` x its key to below it
    (rows its tile ordered soon after it, so that one merged at its key keeps ``floor`` x its key
    from the rows its tile ordered between them). CSR: ``cidx[cstart[i]:cstart[i + 1]]``."""
    from scipy.spatial import cKDTree

    n = rows.shape[0]
    key = rows[:, 1]
    lists: list[np.ndarray] = [np.empty(0, np.int64)] * n
    for t in np.unique(tile):
        mine = np.flatnonzero(tile == t)
        seam = mine[(rows[mine, 5] < key[mine]) & np.isfinite(key[mine]) & (key[mine] > 0)]
        if not seam.size:
            continue
        near = cKDTree(rows[mine, 2:5]).query_ball_point(rows[seam, 2:5], key[seam])
        for i, js in zip(seam, near, strict=True):
            j = mine[np.asarray(js, np.int64)]
            lists[i] = np.sort(j[(key[j] < key[i]) & (key[j] >= floor * key[i])])
    cstart = np.zeros(n + 1, np.int64)
    cstart[1:] = np.cumsum([len(x) for x in lists])
    cidx = np.concatenate(lists) if n else np.empty(0, np.int64)
    return cstart, cidx.astype(np.int64)


def _zone(work: Store, n_tiles: int, alpha: float) -> dict[str, np.ndarray]:
    """The zone (rows, tiles, sorted input indices and their rows, states, candidates: of a key at
    least ``KEY_FLOOR`` and ``alpha`` x the demoted row's, so that the rows of its tile keep alpha x
    their key from it as from the other tiles)."""
    rows, tile = _zone_rows(work, n_tiles)
    g = rows[:, 0].astype(np.int64)
    perm = np.argsort(g, kind="stable").astype(np.int64)
    cstart, cidx = seam_candidates(rows, tile, max(KEY_FLOOR, alpha))
    return {"rows": rows, "tile": tile, "g": np.ascontiguousarray(g[perm]), "perm": perm,
            "state": np.zeros(rows.shape[0], np.int64), "cstart": cstart, "cidx": cidx}


def _no_zone() -> dict[str, np.ndarray]:
    e = np.empty(0, np.int64)
    return {"rows": np.empty((0, 6)), "tile": e, "g": e, "perm": e, "state": e, "cstart": np.zeros(1, np.int64),
            "cidx": e}


def _accepted(head: np.ndarray, n_zone: int) -> tuple[np.ndarray, ...]:
    """The accepted points' coordinates and tiles (the head first, tile -1) and their hash grid,
    with room for every zone row."""
    from ..._kernels.tiled import table_size

    h = head.shape[0]
    cap = h + n_zone + 1
    ax = np.empty((cap, 3))
    ax[:h, 0], ax[:h, 1], ax[:h, 2] = head["x"], head["y"], head["z"]
    size = table_size(cap)
    return (ax, np.full(cap, -1, np.int64), np.full(size, -1, np.int64), np.full(size, -1, np.int64),
            np.full(cap, -1, np.int64))


def _first_blocks(readers: list[_StreamReader]) -> tuple[np.ndarray, ...]:
    """Every tile's first block of rows, read positions, lengths, and the heap of tiles by their
    first key (ties: the lower tile)."""
    n_tiles = len(readers)
    bufs = np.zeros((n_tiles, BUF, 6))
    bpos = np.zeros(n_tiles, np.int64)
    blen = np.zeros(n_tiles, np.int64)
    heap_rows = []
    for t, r in enumerate(readers):
        a = r.read(BUF)
        bufs[t, : a.shape[0]] = a
        blen[t] = a.shape[0]
        if a.shape[0]:
            heap_rows.append((-a[0, 1], t))
    heap_rows.sort()
    theap = np.array([[-k, t] for k, t in heap_rows], dtype=np.float64).reshape(-1, 2)
    return bufs, bpos, blen, theap


def _doubled(*arrays: np.ndarray) -> list[np.ndarray]:
    """The arrays of the demoted points, twice as long (the pool's length)."""
    grow = arrays[0].shape[0]
    return [np.concatenate([a, np.empty((grow + arrays[0].shape[0] - a.shape[0], *a.shape[1:]), a.dtype)])
            for a in arrays]


def _refill(reader: _StreamReader, t: int, bufs: np.ndarray, bpos: np.ndarray, blen: np.ndarray,
            theap: np.ndarray, tn: int) -> int:
    """Tile t's next block in its buffer (t at the top of the tile heap: re-sifted, or popped when
    its stream is done); returns the heap's size."""
    from ..._kernels.tiled import tile_heap_refresh, tile_pop

    a = reader.read(BUF)
    bufs[t, : a.shape[0]] = a
    bpos[t] = 0
    blen[t] = a.shape[0]
    return tile_heap_refresh(theap, tn, t, float(a[0, 1])) if a.shape[0] else tile_pop(theap, tn)


def merge_tiles(work: Store, n: int, n_tiles: int, seam_counts: list[int], alpha: float, lo: np.ndarray,
                min_cell: float, progress: ProgressCallback = None) -> dict[str, Any]:
    """Write ``order.i8`` (input index at each position) and ``key.f8`` (acceptance keys)."""
    from ..._kernels.tiled import seam_merge

    head = work.read_array(WL.HEAD_FILE, HEAD)
    h = head.shape[0]
    n_seam = int(sum(seam_counts))
    z = _zone(work, n_tiles, alpha) if alpha > 0 else _no_zone()
    ax, atile, tkeys, thead, nxt = _accepted(head, z["rows"].shape[0])
    dheap_key = np.empty(n_seam + 1)
    dheap_item = np.empty(n_seam + 1, np.int64)
    # a point may be deferred several times: the pool grows only by the deferrals
    dpool = np.empty((max(4 * n_seam, 1024), 7))
    dtile = np.empty(dpool.shape[0], np.int64)
    state = np.array([0.0, float(h), np.inf, 0.0, 0.0, float(min_cell), 0.0])
    params = np.array([ZONE, REACH if alpha > 0 else 0.0, GAP])  # (no repair: nothing indexed)
    readers = [_StreamReader(work, WL.stream(t)) for t in range(n_tiles)]
    bufs, bpos, blen, theap = _first_blocks(readers)
    tn = theap.shape[0]
    out_g = np.empty(W.BLOCK, np.int64)
    out_key = np.empty(W.BLOCK)
    written = 0
    deferred = 0
    fo, fk = work.writer(WL.ORDER), work.writer(WL.KEY)  # (committed once the count checks out)
    try:
        fo.write(head["g"].astype("<i8"))
        fk.write(np.full(h, np.inf))
        written = h
        report(progress, "merge", written, n)
        while True:
            if state[4] + 2 * n_seam + 16 > dpool.shape[0]:  # room for the next deferrals
                dpool, dtile, dheap_key, dheap_item = _doubled(dpool, dtile, dheap_key, dheap_item)
            code, t = seam_merge(bufs, bpos, blen, theap, tn, state, ax, atile, tkeys, thead, nxt,
                                 dheap_key, dheap_item, dpool, dtile, lo, alpha, out_g, out_key, z["rows"], z["tile"],
                                 z["g"], z["perm"], z["state"], z["cstart"], z["cidx"], params)
            k = int(state[0])
            if code == 2 or code == 0:
                fo.write(out_g[:k].astype("<i8"))
                fk.write(out_key[:k].astype("<f8"))
                written += k
                state[0] = 0.0
                report(progress, "merge", written, n)
                if code == 0:
                    break
                continue
            tn = _refill(readers[t], t, bufs, bpos, blen, theap, tn)  # code 1: tile t, at the top of the heap
        deferred = int(state[4])
        if written != n:
            raise RuntimeError(f"tiled merge wrote {written} of {n} points (tiles inconsistent with the input)")
        files = {WL.ORDER: fo.commit(), WL.KEY: fk.commit()}
    finally:
        for r in readers:
            r.close()
        fo.close()
        fk.close()
    return {"deferred": deferred, "replaced": int(state[6]), "zone_points": int(z["rows"].shape[0]),
            "seam_points": n_seam, "head": h, "files": files}


@timed_task
def merge_task(work: str, n: int, n_tiles: int, seam_counts: list[int], alpha: float, lo: np.ndarray,
               min_cell: float) -> dict[str, Any]:
    """The merge as one task (on a worker, so that the parent loads no kernel and passes over no
    point): :func:`merge_tiles`; returns the merge's marker. (The ranks: :mod:`.ranks`, tasks.)"""
    return merge_tiles(as_store(work), n, n_tiles, seam_counts, alpha, lo, min_cell)
