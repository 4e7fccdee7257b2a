"""Merging the tile orderings into one order, and the exact covering radii of that order.

**Merge.** The head (the coarse global level) comes first, in its own order. Then the tile streams
are merged by descending key (an external k-way merge: each tile's stream is read block by block,
never whole). Seam repair: a point closer to a tile boundary than its key (a *seam point*) is
checked, when its turn comes, against the points of other tiles (and the head) accepted so far;
if one lies within ``alpha`` times its key it waits: its key becomes (distance / ``alpha``) and it
is merged again at that key, when the check is repeated (a lazy greedy over the seam points only).
Every accepted point is therefore at least ``alpha`` times its acceptance key from every earlier
point of another tile; inside a tile the tile's own farthest point order keeps its points apart.

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

BUF = 1 << 16  # rows per tile buffer in the merge, at most
#: bytes of all the tiles' buffers together (the buffers of 256 tiles at BUF rows were 805 MB)
BUF_BYTES = 64 << 20


def buffer_rows(n_tiles: int) -> int:
    """Rows of each tile's buffer in the merge: all of them within BUF_BYTES (at least 1,024 rows
    each, at most BUF)."""
    return min(BUF, max(1024, BUF_BYTES // (STREAM.itemsize * max(n_tiles, 1))))


class _StreamReader:
    """A tile's stream (compressed: :func:`.workdir.put_zipped`) read ``rows`` records at a time."""

    def __init__(self, store: Store, name: str) -> None:
        self.f = store.open(name)
        self.rows = W.unzip_reader(self.f, f"{store.url}/{name}")

    def read(self, rows: int) -> np.ndarray:
        return self.rows(rows * STREAM.itemsize).view("<f8").reshape(-1, 6)

    def close(self) -> None:
        self.f.close()


def merge_tiles(work: Store, n: int, n_tiles: int, seam_counts: list[int], alpha: float, lo: np.ndarray,
                min_cell: float, progress: ProgressCallback = None) -> dict[str, Any]:
    """Write ``order.i8`` (input index at each position) and ``key.f8`` (acceptance keys)."""
    from ..._kernels.tiled import seam_merge, table_size, tile_heap_refresh, tile_pop

    head = work.read_array(WL.HEAD_FILE, HEAD)
    h = head.shape[0]
    n_seam = int(sum(seam_counts))
    cap_acc = h + n_seam + 1
    ax = np.empty((cap_acc, 3))
    ax[:h, 0], ax[:h, 1], ax[:h, 2] = head["x"], head["y"], head["z"]
    atile = np.full(cap_acc, -1, np.int64)
    size = table_size(cap_acc)
    tkeys = np.full(size, -1, np.int64)
    thead = np.full(size, -1, np.int64)
    nxt = np.full(cap_acc, -1, np.int64)
    dheap_key = np.empty(n_seam + 1)
    dheap_item = np.empty(n_seam + 1, np.int64)
    # a point may be deferred several times: the pool grows only by the deferrals
    dpool = np.empty((max(4 * n_seam, 1024), 6))
    dtile = np.empty(dpool.shape[0], np.int64)
    state = np.array([0.0, float(h), np.inf, 0.0, 0.0, float(min_cell)])
    readers = [_StreamReader(work, WL.stream(t)) for t in range(n_tiles)]
    buf = buffer_rows(n_tiles)
    bufs = np.zeros((n_tiles, buf, 6))
    bpos = np.zeros(n_tiles, np.int64)
    blen = np.zeros(n_tiles, np.int64)
    heap_rows = []
    for t, r in enumerate(readers):
        a = r.read(buf)
        bufs[t, : a.shape[0]] = a
        blen[t] = a.shape[0]
        if a.shape[0]:
            heap_rows.append((-a[0, 1], t))
    heap_rows.sort()
    theap = np.array([[-k, t] for k, t in heap_rows], dtype=np.float64).reshape(-1, 2)
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
                grow = dpool.shape[0] * 2
                dpool = np.concatenate([dpool, np.empty((grow - dpool.shape[0], 6))])
                dtile = np.concatenate([dtile, np.empty(grow - dtile.shape[0], np.int64)])
                dheap_key = np.concatenate([dheap_key, np.empty(grow - dheap_key.shape[0])])
                dheap_item = np.concatenate([dheap_item, np.empty(grow - dheap_item.shape[0], np.int64)])
            code, t = seam_merge(bufs, bpos, blen, theap, tn, state, ax, atile, tkeys, thead, nxt,
                                 dheap_key, dheap_item, dpool, dtile, lo, alpha, out_g, out_key)
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
            a = readers[t].read(buf)  # code 1: refill tile t (at the top of the tile heap)
            bufs[t, : a.shape[0]] = a
            bpos[t] = 0
            blen[t] = a.shape[0]
            if a.shape[0]:
                tn = tile_heap_refresh(theap, tn, t, float(a[0, 1]))
            else:
                tn = tile_pop(theap, tn)
        deferred = int(state[4])
        if written != n:
            raise RuntimeError(f"tiled merge wrote {written} of {n} points (tiles inconsistent with the input)")
        files = {WL.ORDER: fo.commit(), WL.KEY: fk.commit()}
    finally:
        for r in readers:
            r.close()
        fo.close()
        fk.close()
    return {"deferred": deferred, "seam_points": n_seam, "head": h, "files": files}


@timed_task
def merge_task(work: str, n: int, n_tiles: int, seam_counts: list[int], alpha: float, lo: np.ndarray,
               min_cell: float) -> dict[str, Any]:
    """The merge as one task (on a worker, so that the parent loads no kernel and passes over no
    point): :func:`merge_tiles`; returns the merge's marker. (The ranks: :mod:`.ranks`, tasks.)"""
    return merge_tiles(as_store(work), n, n_tiles, seam_counts, alpha, lo, min_cell)
