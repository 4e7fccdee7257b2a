"""Merging the tile orderings into one order, and the exact covering radii of that order.

**Merge.** The head (the coarse global level) comes first, in its own order. Then the tile streams
merged by descending key (ties: the lower tile first, a tile's rows in its order). Seam repair: a
point closer to a tile boundary than its key (a *seam point*) is checked, when its turn comes,
against the seam points of other tiles (and the head) accepted so far; if one lies within ``alpha``
times its key it waits: its key becomes (distance / ``alpha``) and it is merged again at that key,
after every tile row of an equal key, when the check is repeated (a lazy greedy over the seam
points only). Every accepted point is therefore at least ``alpha`` times its acceptance key from
every earlier point of another tile; inside a tile the tile's own farthest point order keeps its
points apart.

No process passes over every point. Only seam points take part in the repair and only seam points
are checked against; and of those only the *linked* ones: two seam points of different tiles meet
only if they are closer than ``alpha`` times the smaller of their keys (the point checked has the
smaller key at its check, its key only falls, and the point it meets was accepted at a key at least
as large), and a point that meets no other tile's seam point and no head point is accepted at its
key and never found by another's check. So tasks over groups of tiles (:func:`seam_links`, beside
each other) each read their tiles' seam points (``seam.<t>.bin``) and those of the tiles within
reach, and keep the linked ones (``links.<j>.bin``: 4,939 of the 21.56M-point survey's 327,926
seam points in 197 tiles); the repair is decided by merging the linked points alone (one task,
:func:`seam_repair`), in the same relative order as in the whole merge: the same decisions, the
same demotions in the same order. Its outcome is the list of deferred points with their
acceptance keys, in merged order (``deferred.bin``: by descending acceptance key), and the same
points by the keys their tiles gave them (``dropped.bin``, descending); the histograms of both, in
its marker, give each band its slice of each file. Every other row's place follows from its key alone: the merged
order is cut into bands of keys (:func:`lodbuilder.build.tiled.layout.hist_bins`; the tiles'
histograms of their keys, in their order markers, size the bands: whole bins, about BAND_ROWS rows
each), and one task per band (:func:`merge_band`) reads each tile's rows of the band (a contiguous
run of its stream, located by the histograms; the stream holds input indices and keys, in frames
within one key bin each, eight fine bins: a band decompresses its own frames and at most one frame
at each end that it shares with the next band: :func:`.workdir.put_stream`)
in chunks, leaves out the deferred ones (its slice of ``dropped.bin``), adds the deferred points
whose acceptance key falls in the band (its slice of ``deferred.bin``: no band reads every deferred
point), and merges them by descending key (ties:
the lower tile, then the deferred points) in buffers of a bounded size. The order is stored as pieces
(``merged.<j>.i8``: the head, then each band's input indices) listed with their positions in the
merge's marker (:func:`order_files`). The bands' tasks run side by side; the result is the order
the one k-way merge of every tile stream gave (tests/test_tiled_seams.py checks both against the
naive merge).

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

from ...errors import BuildError
from ...progress import ProgressCallback
from . import layout as WL
from . import workdir as W
from .layout import HEAD, STREAM
from .store import Store, as_store
from .timing import timed_task

log = logging.getLogger(__name__)

BUF = 1 << 16  # rows per tile buffer in the seam repair, at most
#: rows of the merged order per band task, about (whole key bins; a bin holding more is one band)
BAND_ROWS = 1 << 20
#: bytes of all the tiles' buffers together (the buffers of 256 tiles at BUF rows were 805 MB)
BUF_BYTES = 64 << 20
#: seam rows per task of the seam links, about (whole tiles): 20 tasks for the 21.56M-point survey's
#: 327,926 seam points in 197 tiles
LINK_ROWS = 1 << 14
#: the seam links' slack: a pair a relative 1e-9 farther apart than the check's radius is linked too
#: (a link too many costs the repair a row, a link missed would change its outcome)
LINK_SLACK = 1e-9
_FIELDS: tuple[str, ...] = tuple(STREAM.names or ())


def buffer_rows(n_tiles: int) -> int:
    """Rows of each tile's buffer in the merge: all of them within BUF_BYTES (at least 1,024 rows
    each, at most BUF)."""
    return min(BUF, max(1024, BUF_BYTES // (STREAM.itemsize * max(n_tiles, 1))))


class _ArrayReader:
    """Rows of a STREAM array (in memory), as the merge kernel's (m, 6) float64 rows."""

    def __init__(self, rows: np.ndarray) -> None:
        self.rows, self.pos = rows, 0

    def rows_left(self) -> int:
        return self.rows.shape[0] - self.pos

    def read(self, rows: int) -> np.ndarray:
        a = self.rows[self.pos:self.pos + rows]
        self.pos += a.shape[0]
        return np.stack([a[f] for f in _FIELDS], axis=1) if a.shape[0] else np.zeros((0, 6))


def _first_buffers(readers: list[Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """The merge kernel's buffers filled with each source's first rows, and its heap of the sources
    by their first key (ties: the lower source): bufs, bpos, blen, theap, tn. A buffer holds no more
    rows than the largest source has (a band of the merge over 197 tiles holds some 1,700 rows of
    each: buffers of buffer_rows' 7,100 rows were 67 MB to allocate per band)."""
    buf = min(buffer_rows(len(readers)), max([r.rows_left() for r in readers] + [1]))
    bufs = np.zeros((len(readers), buf, 6))
    bpos, blen = np.zeros(len(readers), np.int64), np.zeros(len(readers), np.int64)
    heap_rows = []
    for t, r in enumerate(readers):
        a = r.read(buf)
        bufs[t, : a.shape[0]] = a
        blen[t] = a.shape[0]
        if a.shape[0]:
            heap_rows.append((-a[0, 1], t))
    heap_rows.sort()
    theap = np.array([[-k, t] for k, t in heap_rows], dtype=np.float64).reshape(-1, 2)
    return bufs, bpos, blen, theap, int(theap.shape[0])


def _refill(readers: list[Any], t: int, bufs: np.ndarray, bpos: np.ndarray, blen: np.ndarray, theap: np.ndarray,
            tn: int) -> int:
    """Source ``t``'s buffer (at the top of the heap) read again; returns the heap's new size."""
    from ..._kernels.tiled import tile_heap_refresh, tile_pop

    a = readers[t].read(bufs.shape[1])
    bufs[t, : a.shape[0]] = a
    bpos[t] = 0
    blen[t] = a.shape[0]
    return int(tile_heap_refresh(theap, tn, t, float(a[0, 1])) if a.shape[0] else tile_pop(theap, tn))


def seam_merge(streams: list[np.ndarray], head: np.ndarray, alpha: float, lo: np.ndarray,
               min_cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The k-way merge with the seam repair of ``streams`` (STREAM rows by descending key, one array
    a tile, tiles in order; here the tiles' linked seam points), after the ``head`` (HEAD rows,
    accepted first): the input index and acceptance key of every stream row, in merged order."""
    from ..._kernels.tiled import seam_merge as kernel
    from ..._kernels.tiled import table_size

    readers = [_ArrayReader(s) for s in streams]
    n_rows = sum(r.rows_left() for r in readers)
    h = head.shape[0]
    cap_acc = h + n_rows + 1
    ax = np.empty((cap_acc, 3))
    ax[:h, 0], ax[:h, 1], ax[:h, 2] = head["x"], head["y"], head["z"]
    atile = np.full(cap_acc, -1, np.int64)
    size = table_size(cap_acc)
    tkeys, thead, nxt = np.full(size, -1, np.int64), np.full(size, -1, np.int64), np.full(cap_acc, -1, np.int64)
    # a point may be deferred several times: the pool grows only by the deferrals
    dheap_key, dheap_item = np.empty(n_rows + 1), np.empty(n_rows + 1, np.int64)
    dpool, dtile = np.empty((max(4 * n_rows, 1024), 6)), np.empty(max(4 * n_rows, 1024), np.int64)
    state = np.array([0.0, float(h), np.inf, 0.0, 0.0, float(min_cell)])
    bufs, bpos, blen, theap, tn = _first_buffers(readers)
    out_g, out_key = np.empty(W.BLOCK, np.int64), np.empty(W.BLOCK)
    got_g, got_key = [], []
    while True:
        if state[4] + 2 * n_rows + 16 > dpool.shape[0]:  # room for the next deferrals
            grow = dpool.shape[0] * 2
            dpool = np.concatenate([dpool, np.empty((grow - dpool.shape[0], 6))])
            dtile = np.concatenate([dtile, np.empty(grow - dtile.shape[0], np.int64)])
            dheap_key = np.concatenate([dheap_key, np.empty(grow - dheap_key.shape[0])])
            dheap_item = np.concatenate([dheap_item, np.empty(grow - dheap_item.shape[0], np.int64)])
        code, t = kernel(bufs, bpos, blen, theap, tn, state, ax, atile, tkeys, thead, nxt,
                         dheap_key, dheap_item, dpool, dtile, lo, alpha, out_g, out_key)
        if code in (0, 2):
            k = int(state[0])
            got_g.append(out_g[:k].copy())
            got_key.append(out_key[:k].copy())
            state[0] = 0.0
            if code == 0:
                break
            continue
        tn = _refill(readers, t, bufs, bpos, blen, theap, tn)  # code 1: tile t (at the top) is empty
    g, key = np.concatenate(got_g), np.concatenate(got_key)
    if g.shape[0] != n_rows:
        raise RuntimeError(f"the seam merge gave {g.shape[0]} of {n_rows} points (tiles inconsistent with the input)")
    return g, key


def link_groups(stats: list[dict[str, Any]], boxes: list[tuple[np.ndarray, np.ndarray]] | None, alpha: float,
                rows: int | None = None) -> list[tuple[list[int], list[int]]]:
    """The seam links' groups of tiles (``stats``: the tiles' order markers, with their seam rows
    ``n_seam`` and key histograms; ``boxes``: each tile's (lo, hi), None: every tile may meet every
    other): consecutive tiles of about ``rows`` (:data:`LINK_ROWS`) seam rows in all (neighbours in
    the plan's k-d split), each group with the other tiles whose box comes within ``alpha`` times
    the largest finite key of one of its tiles of that tile's box (the only tiles whose seam points
    its seam points can meet: a point checks within ``alpha`` times its key; the tiles near the
    group's bounding box first: O(groups x tiles)). None with ``alpha`` 0 (the repair defers
    nothing)."""
    n, rows = len(stats), LINK_ROWS if rows is None else rows
    if alpha <= 0 or n == 0:
        return []
    top = [WL.hist_ceiling(max([b for b in s["key_hist"][0] if b != WL.BIN_INF] or [WL.BIN_ZERO])) for s in stats]
    reach = alpha * np.asarray(top) * (1 + LINK_SLACK)
    if boxes is not None:
        lo, hi = np.array([b[0] for b in boxes], float), np.array([b[1] for b in boxes], float)
    seam = np.cumsum([int(s.get("n_seam", 0)) for s in stats])
    groups, first = [], 0
    while first < n:  # (whole tiles, at least one a group)
        end = max(first + 1, int(np.searchsorted(seam, (seam[first - 1] if first else 0) + rows)) + 1)
        mine = list(range(first, min(end, n)))
        if boxes is None:
            near = np.arange(n)
        else:
            near = _within(lo, hi, lo[first:end].min(axis=0), hi[first:end].max(axis=0), reach[first:end].max())
            near = np.unique(np.concatenate([near[_within(lo[near], hi[near], lo[u], hi[u], reach[u])] for u in mine]))
        groups.append((mine, [int(u) for u in near if not first <= u < end]))
        first = end
    return groups


def _within(lo: np.ndarray, hi: np.ndarray, blo: np.ndarray, bhi: np.ndarray, reach: float) -> np.ndarray:
    """The boxes (``lo``, ``hi``: one a row) that come within ``reach`` of the box ``blo``-``bhi``."""
    gap = np.maximum(np.maximum(lo - bhi, blo - hi), 0.0)
    return np.flatnonzero(np.sqrt((gap * gap).sum(axis=1)) <= reach)


@timed_task
def seam_links(work: str, j: int, tiles: list[int], reads: list[int], alpha: float, lo: np.ndarray,
               min_cell: float) -> dict[str, Any]:
    """Group ``j``'s seam links (see the module): of the seam points of ``tiles`` and of ``reads``
    (the tiles whose points theirs can meet, :func:`link_groups`), those that the seam repair must
    merge: both points of a pair of different tiles closer than ``alpha`` times the smaller of their
    keys where the later of the two (by key, then tile, then row: the order every group takes) is in
    ``tiles`` (so every such pair is found by the group of its later point's tile), and the points of
    ``tiles`` within ``alpha`` times their key of a head point (a hash grid from ``lo``, cells of at
    least ``min_cell``: :func:`lodbuilder._kernels.tiled.seam_links`). Writes ``links.<j>.bin``
    (LINK records: the points' tiles, rows and seam rows)."""
    from ..._kernels.tiled import seam_links as kernel
    from ..._kernels.tiled import table_size

    w = as_store(work)
    every = sorted({*tiles, *reads})
    seams = [w.read_array(WL.seam(t), STREAM) for t in every]
    head = w.read_array(WL.HEAD_FILE, HEAD)
    rows = np.concatenate(seams or [np.zeros(0, STREAM)])
    tile = np.repeat(np.asarray(every, np.int64), [s.shape[0] for s in seams])
    row = np.concatenate([np.arange(s.shape[0]) for s in seams] or [np.zeros(0, np.int64)])
    srt = np.lexsort((row, tile, -rows["key"]))  # (by key, then tile and row: the same in every group)
    h = head.shape[0]
    xyz = np.empty((h + srt.shape[0], 3))
    xyz[:h, 0], xyz[:h, 1], xyz[:h, 2] = head["x"], head["y"], head["z"]
    xyz[h:, 0], xyz[h:, 1], xyz[h:, 2] = rows["x"][srt], rows["y"][srt], rows["z"][srt]
    key = np.concatenate([np.full(h, np.inf), rows["key"][srt]])
    tid = np.concatenate([np.full(h, -1, np.int64), tile[srt]])
    own = np.concatenate([np.zeros(h, bool), np.isin(tile[srt], tiles)])
    linked = np.zeros(key.shape[0], bool)
    size = table_size(key.shape[0])
    kernel(xyz, key, tid, own, alpha, LINK_SLACK, np.asarray(lo, np.float64), float(min_cell),
           np.full(size, -1, np.int64), np.full(size, -1, np.int64), np.full(key.shape[0], -1, np.int64), linked)
    at = srt[linked[h:]]
    out = np.empty(at.shape[0], WL.LINK)
    out["t"], out["row"] = tile[at], row[at]
    for f in _FIELDS:
        out[f] = rows[f][at]
    return {"group": j, "seam_rows": int(sum(s.shape[0] for t, s in zip(every, seams, strict=True) if t in tiles)),
            "links": int(out.shape[0]), "files": {WL.links(j): w.put(WL.links(j), out)}}


def _linked_streams(w: Store, n_groups: int) -> list[np.ndarray]:
    """The groups' linked seam points (each once), as one STREAM array a tile in the tiles' order
    (each in its seam file's order: its stream's)."""
    c = np.concatenate([w.read_array(WL.links(j), WL.LINK) for j in range(n_groups)] or [np.zeros(0, WL.LINK)])
    c = c[np.lexsort((c["row"], c["t"]))]
    first = np.ones(c.shape[0], bool)
    first[1:] = (c["t"][1:] != c["t"][:-1]) | (c["row"][1:] != c["row"][:-1])
    c = c[first]
    out = np.empty(c.shape[0], STREAM)
    for f in _FIELDS:
        out[f] = c[f]
    return np.split(out, np.flatnonzero(np.diff(c["t"])) + 1) if c.shape[0] else []


@timed_task
def seam_repair(work: str, n_groups: int, alpha: float, lo: np.ndarray, min_cell: float) -> dict[str, Any]:
    """The seam repair (see the module): the linked seam points of the ``n_groups`` groups
    (:func:`seam_links`) merged after the head; writes the order's first piece (the head),
    ``deferred.bin`` (the deferred points and their acceptance keys, in merged order) and
    ``dropped.bin`` (the same points and the keys their tiles gave them, by descending key).
    Returns the piece's marker (with the histograms of both keys)."""
    w = as_store(work)
    head = w.read_array(WL.HEAD_FILE, HEAD)
    streams = _linked_streams(w, n_groups)
    g, key = seam_merge(streams, head, alpha, lo, min_cell)
    rows = np.concatenate(streams or [np.zeros(0, STREAM)])
    # each row's key in the tiles, in merged order: g is a permutation of the rows' input indices
    # (one point a row), so the rows and the merged points sorted by input index line up
    was = np.empty(g.shape[0])
    was[np.argsort(g, kind="stable")] = rows["key"][np.argsort(rows["g"], kind="stable")]
    late = key < was  # (an accepted point keeps its key; a deferred one is accepted below it)
    d = np.empty(int(late.sum()), WL.DEFER)
    d["g"], d["key"] = g[late], key[late]
    # the same points by the keys their tiles gave them (the bands that leave them out), descending
    gone = np.empty(d.shape[0], WL.DEFER)
    gone["g"], gone["key"] = d["g"], was[late]
    gone = gone[np.lexsort((gone["g"], -gone["key"]))]
    files = {WL.merged(0): W.put_framed(w, WL.merged(0), head["g"].astype("<i8")), WL.DEFERRED: w.put(WL.DEFERRED, d),
             WL.DROPPED: w.put(WL.DROPPED, gone)}
    return {"head": int(head.shape[0]), "seam_links": int(g.shape[0]), "deferred": int(d.shape[0]),
            "key_hist": WL.key_hist(d["key"]), "drop_hist": WL.key_hist(gone["key"]), "files": files}


class _RangeReader:
    """Rows ``a .. z`` of a tile's stream (KEYS records; or rows given whole), in chunks, without
    the rows whose input index is in ``drop`` (sorted), as the merge kernel's (m, 6) float64 rows
    (input index, key, no position, an infinite margin: no row is a seam point, :func:`merge_band`
    merges by key alone)."""

    def __init__(self, store: Store | None, name: str, a: int, z: int, drop: np.ndarray, bins: list[int],
                 rows: np.ndarray | None = None) -> None:
        self.store, self.name, self.pos, self.end, self.drop, self.rows = store, name, a, z, drop, rows
        self.bins = bins
        self.framed = W.FramedReader(store, name, WL.KEYS) if store is not None else None  # (compressed)

    def rows_left(self) -> int:
        return self.end - self.pos

    def read(self, m: int) -> np.ndarray:
        while self.pos < self.end:
            k = min(m, self.end - self.pos)
            if self.rows is not None:
                s = self.rows[self.pos:self.pos + k]
            else:
                assert self.framed is not None
                s = self.framed.read(self.pos, k)
                b = WL.hist_bins(s["key"][[0, -1]]) if s.shape[0] else None
                if s.shape[0] != k or b is None or b[0] > self.bins[1] or b[1] < self.bins[0]:
                    raise RuntimeError(f"{self.name}: rows {self.pos}..{self.end} are not the rows its histogram says")
            self.pos += k
            if self.drop.size:
                at = np.minimum(np.searchsorted(self.drop, s["g"]), self.drop.shape[0] - 1)
                s = s[self.drop[at] != s["g"]]
            if s.shape[0]:
                out = np.zeros((s.shape[0], 6))
                out[:, 0], out[:, 1], out[:, 5] = s["g"], s["key"], np.inf
                return out
        return np.zeros((0, 6))


@timed_task
def merge_band(work: str, j: int, rows: list[list[int]], bins: list[int], added: list[int],
               dropped: list[int]) -> dict[str, Any]:
    """Band ``j`` of the merge (see the module): ``rows`` ``[tile, first, end]`` of the tiles'
    streams whose keys fall in the bins ``bins`` (lowest, highest), tiles in order, without the
    deferred points among them (rows ``dropped`` ``[first, end]`` of ``dropped.bin``); then the
    deferred points accepted in those bins (rows ``added`` of ``deferred.bin``) after them. A k-way
    merge by key (ties: the lower tile, then the deferred points) with buffers of a bounded size,
    whatever the band's rows. Writes ``merged.<j>.i8``."""
    from ..._kernels.tiled import seam_merge as kernel
    from ..._kernels.tiled import table_size

    w = as_store(work)
    add = w.read_array(WL.DEFERRED, WL.DEFER, added[0], added[1] - added[0])
    gone = w.read_array(WL.DROPPED, WL.DEFER, dropped[0], dropped[1] - dropped[0])
    for name, part in ((WL.DEFERRED, add), (WL.DROPPED, gone)):
        b = WL.hist_bins(part["key"])
        if b.size and (b.min() < bins[0] or b.max() > bins[1]):
            raise RuntimeError(f"{name}: rows {part.shape[0]} of band {j} are not the rows its histogram says")
    drop = np.sort(gone["g"])
    readers = [_RangeReader(w, WL.stream(t), a, z, drop, bins) for t, a, z in rows]
    if add.shape[0]:
        extra = np.zeros(add.shape[0], WL.KEYS)
        extra["g"], extra["key"] = add["g"], add["key"]
        readers.append(_RangeReader(None, WL.DEFERRED, 0, add.shape[0], np.zeros(0, np.int64), bins, extra))
    bufs, bpos, blen, theap, tn = _first_buffers(readers)
    one = np.zeros(1, np.int64)  # (no row is a seam point: the seam structures stay empty)
    state = np.array([0.0, 0.0, np.inf, 0.0, 0.0, 1.0])
    size = table_size(1)
    out_g, out_key = np.empty(W.BLOCK, np.int64), np.empty(W.BLOCK)
    f = W.Framed(w.writer(WL.merged(j)))  # (compressed in frames of rows: read by workdir.segment)
    count = 0
    try:
        while True:
            code, t = kernel(bufs, bpos, blen, theap, tn, state, np.zeros((1, 3)), one - 1, np.full(size, -1, np.int64),
                             np.full(size, -1, np.int64), one - 1, np.empty(1), one.copy(), np.empty((1, 6)), one.copy(),
                             np.zeros(3), 0.0, out_g, out_key)
            if code in (0, 2):
                k = int(state[0])
                f.write(out_g[:k].astype("<i8"))
                count += k
                state[0] = 0.0
                if code == 0:
                    break
                continue
            tn = _refill(readers, t, bufs, bpos, blen, theap, tn)  # code 1: source t (at the top) is empty
        files = {WL.merged(j): f.commit()}
    finally:
        f.close()
    return {"band": j, "count": count, "files": files}


def plan_bands(hists: list[list[list[int]]], deferred: list[list[int]], band_rows: int,
               dropped: list[list[int]] | None = None) -> list[tuple[list[list[int]], list[int], list[int], list[int]]]:
    """The merge's bands from the tiles' key histograms (``[bins, counts]`` each), the deferred
    points' histogram of their acceptance keys and that of the keys their tiles gave them
    (``dropped``; none: no deferred point): ``(rows, bins, added, dropped)`` per band (the
    arguments of :func:`merge_band`: ``added`` and ``dropped`` the band's rows ``[first, end]`` of
    ``deferred.bin`` and ``dropped.bin``, each by descending key), in merged order; each about
    ``band_rows`` rows of whole bins (a bin holding more is a band of its own: its task merges in
    bounded memory, but takes longer)."""
    all_bins = np.unique(np.concatenate([np.asarray(h[0], np.int64) for h in [*hists, deferred]] or [np.zeros(0, np.int64)]))
    desc = all_bins[::-1]
    c = np.zeros((len(hists), desc.shape[0]), np.int64)
    for t, (b, k) in enumerate(hists):
        c[t, desc.shape[0] - 1 - np.searchsorted(all_bins, np.asarray(b, np.int64))] = k
    dc = np.zeros(desc.shape[0], np.int64)
    dc[desc.shape[0] - 1 - np.searchsorted(all_bins, np.asarray(deferred[0], np.int64))] = deferred[1]
    above = np.cumsum(c, axis=1) - c  # rows of each tile in the bins before each bin (larger keys)
    total = c.sum(axis=0) + dc
    gc = np.zeros(desc.shape[0], np.int64)  # (the dropped rows' bins are among the tiles')
    gone = dropped or [[], []]
    gc[desc.shape[0] - 1 - np.searchsorted(all_bins, np.asarray(gone[0], np.int64))] = gone[1]
    if gc.sum() != dc.sum() or not np.isin(np.asarray(gone[0], np.int64), all_bins).all():
        raise RuntimeError("the merge's deferred and dropped points do not match")
    dstart, gstart = np.cumsum(dc) - dc, np.cumsum(gc) - gc
    bands: list[tuple[list[list[int]], list[int], list[int], list[int]]] = []

    def rows(i0: int, i1: int, tiles: range) -> list[list[int]]:  # bins desc[i0..i1] of these tiles
        return [[t, int(above[t, i0]), int(above[t, i1] + c[t, i1])] for t in tiles if c[t, i0:i1 + 1].sum()]

    i = 0
    while i < desc.shape[0]:  # whole bins, about band_rows rows a band (a larger bin alone)
        j, acc = i + 1, int(total[i])
        while j < desc.shape[0] and acc + total[j] <= band_rows:
            acc += int(total[j])
            j += 1
        bands.append((rows(i, j - 1, range(len(hists))), [int(desc[j - 1]), int(desc[i])],
                      [int(dstart[i]), int(dstart[j - 1] + dc[j - 1])], [int(gstart[i]), int(gstart[j - 1] + gc[j - 1])]))
        i = j
    return bands


def merge_phase(ex: Any, work: Any, name: str, n: int, stats: list[dict[str, Any]], alpha: float, lo: np.ndarray,
                min_cell: float, progress: ProgressCallback = None, band_rows: int = BAND_ROWS,
                boxes: list[tuple[np.ndarray, np.ndarray]] | None = None) -> dict[str, Any]:
    """The merge as tasks: the seam links of groups of tiles side by side (``boxes``: the tiles'
    (lo, hi), see :func:`link_groups`), the seam repair, then the bands side by side (finished
    pieces a resume finds are not redone). Returns the merge's marker: ``order`` (the pieces of the merged order,
    ``[name, first position, end]``), the counts of seam points and deferred points, and the files."""
    from .pool import collect, submit
    from .sums import done, mark

    def old() -> BuildError:
        return BuildError(f"scan {name!r}: its work directory was left by an older lodbuilder; run the build "
                          "again with --force")

    if any("key_hist" not in s or WL.stream(t) not in s.get("files", {}) for t, s in enumerate(stats)):
        raise old()
    seams = done(work, WL.SEAMS_PIECE)
    if seams is None:
        groups = link_groups(stats, boxes, alpha)
        found = {j for j in range(len(groups)) if done(work, WL.links_piece(j)) is not None}
        links = [(j, seam_links, (work, j, *groups[j], alpha, lo, min_cell)) for j in range(len(groups)) if j not in found]
        collect(submit(ex, links), lambda j: f"the seam links of tiles {groups[j][0][0] + 1}-{groups[j][0][-1] + 1}",
                name, len(groups), None, "merge",
                lambda r: mark(work, WL.links_piece(r["group"]), r))
        args = (work, len(groups), alpha, lo, min_cell)
        (seams,) = collect(submit(ex, [(0, seam_repair, args)]), lambda _: "the seam repair", name, 1, None, "merge")
        mark(work, WL.SEAMS_PIECE, seams)
    if "key_hist" not in seams or "drop_hist" not in seams:
        raise old()
    bands = plan_bands([s["key_hist"] for s in stats], seams["key_hist"], band_rows, seams["drop_hist"])
    got = {j: d for j in range(1, len(bands) + 1) if (d := done(work, WL.merged_piece(j))) is not None}
    calls = [(j, merge_band, (work, j, *bands[j - 1])) for j in range(1, len(bands) + 1) if j not in got]
    collect(submit(ex, calls), lambda j: f"band {j} of the merge", name, n, progress, "merge",
            lambda r: got.__setitem__(r["band"], mark(work, WL.merged_piece(r["band"]), r)),
            lambda r: r["count"], int(seams["head"]) + sum(d["count"] for d in got.values()))
    order, k = [[WL.merged(0), 0, int(seams["head"])]], int(seams["head"])
    for j in range(1, len(bands) + 1):
        order.append([WL.merged(j), k, k + int(got[j]["count"])])
        k += int(got[j]["count"])
    if k != n:
        raise RuntimeError(f"tiled merge placed {k} of {n} points (tiles inconsistent with the input)")
    # (deferred.bin and dropped.bin are listed by the seam repair's marker alone: deleted with this marker written)
    files = {WL.merged(0): seams["files"][WL.merged(0)], **{f: v for d in got.values() for f, v in d["files"].items()}}
    return {"deferred": seams["deferred"], "seam_points": sum(int(s.get("n_seam", 0)) for s in stats),
            "seam_links": seams.get("seam_links"),
            "head": seams["head"],
            "order": order, "files": files}


def order_files(work: Any) -> list[tuple[str, int, int]]:
    """The pieces of the merged order (name, first position, end), from the merge's marker."""
    from .sums import get_json

    return [(f, int(a), int(z)) for f, a, z in (get_json(work, WL.marker("merge")) or {})["order"]]
