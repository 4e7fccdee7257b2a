"""Merging the tile orderings into one order, and the exact covering radii of that order.

**Merge.** The head (the coarse global level) comes first, in its own order. Then the tile streams
are merged by descending key (an external k-way merge: each tile's stream is read block by block,
never whole), except the *seam zone*: the rows closer to a face their tile shares with another
than ``ZONE`` times their key. Two tiles that ordered their sides of a face without seeing each
other's points there (a tile sees only the points its neighbours ordered before it) may both put a
point at the same spot; merged by their keys both would come, near-duplicates. The zone is merged
instead as a farthest point ordering in one Euclidean metric across the face (a lazy greedy): a
zone point comes when its distance to the points accepted so far (the head, the zone, and the rows
within (``ZONE`` + 1) x their key of a shared face, kept in a hash grid) times its *stretch* is the
largest of all candidates, that product being its key. The stretch (:func:`stretch`, from 1 up to
(1 + alpha) / (2 alpha)) is its tile's key over its Euclidean distance to the point its tile ordered
before it nearest to it: the tiles' keys are band distances, longer than Euclidean ones on a slope,
and a zone measured in plain Euclidean distances came late beside the other rows of its tile (on a
wavy sheet in 16 tiles: covering at equal size 1.22 x the in-memory build's, against 1.08 with
the stretch). A wide zone matters too: the zone's points are the only candidates the greedy can
bring early in place of a near-duplicate left for later, so a thin zone (2 x key) left holes beside
it (1.16 x on that sheet, 1.08 at 8 x key). The zone is read once before the merge (a surface's
worth of rows: a few times the points along the tiles' faces at the finest spacing).

Guarantees. A zone point is at least its key over its stretch, so at least 2 alpha / (1 + alpha)
times its key, from every earlier point of another tile (every such point within its key lies within
that distance of the shared face, so in the grid); a row outside the zone is at least ``ZONE`` times
its key from any point of another tile. Every level's covering radius is at most twice the key of
its last point: a point lies within that key of a point of its tile's order (or a seed) of a larger
key, which is accepted, or is a zone point within the key of an accepted point. So points of
different tiles are at least alpha / (1 + alpha) times the level's radius apart (0.5 at alpha 1,
where the stretch is 1; 0.2 at 0.25). ``alpha`` 0: no zone, the tiles' keys merged as they are.

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
#: the seam zone: the rows within ZONE x their key of a face their tile shares (see the module)
ZONE = 8.0


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


def _zone_rows(work: Store, n_tiles: int, zone: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The zone rows of every tile's stream (margin < ``zone`` x key), in tile and stream order,
    their tiles, and the rows the zone measures against (key, x, y, z, tile: margin < (``zone`` +
    1) x key, the zone rows among them): one read of the streams, block by block, keeping only
    those rows."""
    zparts, tparts, rparts = [], [], []
    for t in range(n_tiles):
        r = _StreamReader(work, WL.stream(t))
        try:
            while r.left:
                a = r.read(16 * BUF)
                zparts.append(a[a[:, 5] < zone * a[:, 1]])
                tparts.append(np.full(zparts[-1].shape[0], t))
                b = a[a[:, 5] < (zone + 1.0) * a[:, 1]]
                rparts.append(np.c_[b[:, 1:5], np.full(b.shape[0], t)])
        finally:
            r.close()
    zrows = np.concatenate(zparts) if zparts else np.empty((0, 6))
    ztile = np.concatenate(tparts) if tparts else np.empty(0, np.int64)
    reach = np.concatenate(rparts) if rparts else np.empty((0, 5))
    return np.ascontiguousarray(zrows), ztile, reach


def stretch(zrows: np.ndarray, ztile: np.ndarray, reach: np.ndarray, head_xyz: np.ndarray, cap: float) -> np.ndarray:
    """Each zone point's key over its Euclidean distance to the nearest point ordered before it by
    its tile (a head point or a row of ``reach`` (key, x, y, z, tile) of its tile with a larger
    key, within its key): how much longer the tiles' band distances are than Euclidean ones there (>= 1; 1 when no such
    point is within its key). The zone's Euclidean distances are multiplied by it, so that zone
    points and the other rows of a tile come at the same level in one metric."""
    from scipy.spatial import cKDTree

    out = np.ones(zrows.shape[0])
    if not zrows.shape[0]:
        return out
    xyz = np.concatenate([head_xyz, reach[:, 1:4]])
    key = np.concatenate([np.full(head_xyz.shape[0], np.inf), reach[:, 0]])
    tile = np.concatenate([np.full(head_xyz.shape[0], -1.0), reach[:, 4]])
    k = zrows[:, 1]
    ok = np.flatnonzero(np.isfinite(k) & (k > 0))
    near = cKDTree(xyz).query_ball_point(zrows[ok, 2:5], k[ok])
    lens = np.fromiter((len(x) for x in near), np.int64, ok.size)
    if not lens.sum():
        return out
    who = np.repeat(ok, lens)
    j = np.concatenate([np.asarray(x, np.int64) for x in near if len(x)])
    before = (key[j] > k[who]) & ((tile[j] == ztile[who]) | (tile[j] < 0))
    who, j = who[before], j[before]
    e = np.linalg.norm(xyz[j] - zrows[who, 2:5], axis=1)
    emin = np.full(zrows.shape[0], np.inf)
    np.minimum.at(emin, who, e)
    has = np.isfinite(emin) & (emin > 0)
    out[has] = np.clip(k[has] / emin[has], 1.0, cap)
    return out


def _zone_heap(rows: np.ndarray, head_xyz: np.ndarray, span: float) -> tuple[np.ndarray, np.ndarray]:
    """The zone heap's first bounds: each zone point's distance to the nearest head point times its
    stretch (every later distance to the accepted points is at most that), in heap order
    (descending, ties: the smaller item first, a valid max-heap)."""
    from scipy.spatial import cKDTree

    if head_xyz.shape[0] and rows.shape[0]:
        ub = cKDTree(head_xyz).query(rows[:, 2:5])[0] * rows[:, 5]
    else:
        ub = np.full(rows.shape[0], span)
    items = np.lexsort((np.arange(rows.shape[0]), -ub)).astype(np.int64)
    return np.ascontiguousarray(ub[items]), items


def _zone(work: Store, n_tiles: int, zone: float, alpha: float, head: np.ndarray, min_cell: float
          ) -> dict[str, np.ndarray]:
    """The seam zone's rows (their margin column replaced by their stretch) and heap, and the
    accepted points' array and hash grid (the head in it), sized for every row the zone measures
    against."""
    from ..._kernels.tiled import table_size

    h = head.shape[0]
    if zone > 0:
        zrows, ztile, reach = _zone_rows(work, n_tiles, zone)
    else:
        zrows, ztile, reach = np.empty((0, 6)), np.empty(0, np.int64), np.empty((0, 5))
    hxyz = np.stack([head["x"], head["y"], head["z"]], axis=1).astype(np.float64)
    # (the cap keeps the spacing bound: see the module)
    zrows[:, 5] = stretch(zrows, ztile, reach, hxyz, (1 + alpha) / (2 * alpha) if alpha > 0 else 1.0)
    zub, zitem = _zone_heap(zrows, hxyz, min_cell * (1 << 20))
    cap_acc = h + reach.shape[0] + 1
    ax = np.empty((cap_acc, 3))
    ax[:h] = hxyz
    size = table_size(cap_acc)
    return {"rows": zrows, "ub": zub, "item": zitem, "ax": ax, "tkeys": np.full(size, -1, np.int64),
            "thead": np.full(size, -1, np.int64), "nxt": np.full(cap_acc, -1, np.int64)}


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


def merge_tiles(work: Store, n: int, n_tiles: int, seam_counts: list[int], alpha: float, lo: np.ndarray,
                min_cell: float, progress: ProgressCallback = None) -> dict[str, Any]:
    """Write ``order.i8`` (input index at each position) and ``key.f8`` (acceptance keys).
    ``seam_counts``: each tile's rows with margin < key (reported); ``alpha`` 0: no seam zone (a
    plain merge by the tiles' keys)."""
    from ..._kernels.tiled import seam_merge, tile_heap_refresh, tile_pop

    head = work.read_array(WL.HEAD_FILE, HEAD)
    h = head.shape[0]
    zone = ZONE if alpha > 0 else 0.0
    z = _zone(work, n_tiles, zone, alpha, head, min_cell)
    zrows, zub, zitem, ax, tkeys, thead, nxt = (z[k] for k in ("rows", "ub", "item", "ax", "tkeys", "thead", "nxt"))
    state = np.array([0.0, float(h), np.inf, float(zrows.shape[0]), 0.0, float(min_cell), 0.0, 0.0])
    readers = [_StreamReader(work, WL.stream(t)) for t in range(n_tiles)]
    bufs, bpos, blen, theap = _first_blocks(readers)
    tn = theap.shape[0]
    out_g = np.empty(W.BLOCK, np.int64)
    out_key = np.empty(W.BLOCK)
    written = 0
    fo, fk = work.writer(WL.ORDER), work.writer(WL.KEY)  # (committed once the count checks out)
    try:
        fo.write(head["g"].astype("<i8"))
        fk.write(np.full(h, np.inf))
        written = h
        report(progress, "merge", written, n)
        while True:
            code, t = seam_merge(bufs, bpos, blen, theap, tn, state, ax, tkeys, thead, nxt, zub, zitem, zrows,
                                 lo, zone, out_g, out_key)
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
            a = readers[t].read(BUF)  # code 1: refill tile t (at the top of the tile heap)
            bufs[t, : a.shape[0]] = a
            bpos[t] = 0
            blen[t] = a.shape[0]
            if a.shape[0]:
                tn = tile_heap_refresh(theap, tn, t, float(a[0, 1]))
            else:
                tn = tile_pop(theap, tn)
        if written != n:
            raise RuntimeError(f"tiled merge wrote {written} of {n} points (tiles inconsistent with the input)")
        files = {WL.ORDER: fo.commit(), WL.KEY: fk.commit()}
    finally:
        for r in readers:
            r.close()
        fo.close()
        fk.close()
    return {"deferred": int(state[7]), "promoted": int(state[6]), "zone_points": int(zrows.shape[0]),
            "zone_evaluations": int(state[4]), "seam_points": int(sum(seam_counts)), "head": h, "files": files}


@timed_task
def merge_task(work: str, n: int, n_tiles: int, seam_counts: list[int], alpha: float, lo: np.ndarray,
               min_cell: float) -> dict[str, Any]:
    """The merge as one task (on a worker, so that the parent loads no kernel and passes over no
    point): :func:`merge_tiles`; returns the merge's marker. (The ranks: :mod:`.ranks`, tasks.)"""
    return merge_tiles(as_store(work), n, n_tiles, seam_counts, alpha, lo, min_cell)
