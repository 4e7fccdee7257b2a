"""Every input point's position in the merged order (the inverse of the order's pieces), by tasks.

The inverse is a scatter: position k goes to input index order[k], anywhere in the scan. One
process doing it over every point is a random write per point (about 0.2 us a point, most of it
waiting on memory and pages). Here it is an external transpose in two rounds of tasks:

1. :func:`rank_band` (one task per band of ``BAND`` positions of the merged order): the band's
   ``(input index, position)`` pairs sorted by read block (the raw blocks of the read phase), one
   file per band (``rankp.<k>.bin``), and how many pairs go to each block;
2. :func:`rank_block` (one task per read block): its pairs from every band (one slice of each
   band's file: the parent adds up the counts), scattered into ``rank.<b>.i8`` (the positions of
   the block's input indices, in input order). Memory: one block.

A read block's own task (the write's permutation) reads its ``rank.<b>.i8`` whole;
:func:`gather_ranks` finds the positions of any input indices (a tile's covering pass).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ...progress import ProgressCallback
from . import layout as WL
from .merge import order_files
from .pool import collect, submit
from .store import as_store
from .sums import done, get_json, mark
from .timing import timed_task
from .workdir import gather, segment

#: positions of the merged order per task of the first round
BAND = 1 << 19
#: a pair of the transpose: input index, position
PAIR = np.dtype([("g", "<i8"), ("k", "<i8")])


@timed_task
def rank_band(work: str, band: int, k0: int, k1: int, starts: list[int]) -> dict[str, Any]:
    """Round 1 for positions ``k0 .. k1`` (``starts``: the first input index of every read block)."""
    w = as_store(work)
    g = segment(w, order_files(w), "<i8", k0, k1)
    blk = np.searchsorted(np.asarray(starts, np.int64), g, "right") - 1
    srt = np.argsort(blk.astype(np.int32), kind="stable")  # radix sort
    pairs = np.empty(g.shape[0], PAIR)
    pairs["g"], pairs["k"] = g[srt], k0 + srt
    files = {WL.rank_pairs(band): w.put(WL.rank_pairs(band), pairs)}
    return {"band": band, "counts": np.bincount(blk, minlength=len(starts)).tolist(), "files": files}


@timed_task
def rank_block(work: str, b: int, g0: int, m: int, slices: list[list[int]]) -> dict[str, Any]:
    """Round 2 for read block ``b`` (input indices ``g0 .. g0 + m``): ``slices`` ``[band, first
    pair, pairs]`` of its pairs in each band's file."""
    w = as_store(work)
    rank = np.full(m, -1, np.int64)
    got = 0
    for band, a, c in slices:
        p = w.read_array(WL.rank_pairs(band), PAIR, a, c)
        off = p["g"] - g0
        if p.shape[0] != c or (c and (off.min() < 0 or off.max() >= m)):
            raise RuntimeError(f"{WL.rank_pairs(band)} does not hold the {c} pairs of block {b + 1} its counts say")
        rank[off] = p["k"]
        got += c
    if got != m or (rank < 0).any():
        raise RuntimeError(f"the merged order holds {got} input indices of block {b + 1}, not each of its {m} once")
    return {"block": b, "files": {WL.rank_file(b): w.put(WL.rank_file(b), rank)}}


def ranks_phase(ex: Any, work: Any, name: str, n: int, blocks: list[list[int]],
                progress: ProgressCallback = None) -> dict[str, Any]:
    """Both rounds as tasks (finished pieces a resume finds are not redone); returns the ranks'
    marker: the read blocks' first input indices and the rank files."""
    doc = done(work, "ranks")
    if doc is not None:
        return doc
    starts = [int(blk[3]) for blk in blocks]
    sizes = [int(blk[2]) - int(blk[1]) for blk in blocks]
    bands = [(k0, min(n, k0 + BAND)) for k0 in range(0, n, BAND)]
    first = {b: d for b in range(len(bands)) if (d := done(work, WL.rank_pairs_piece(b))) is not None}
    calls = [(b, rank_band, (work, b, *bands[b], starts)) for b in range(len(bands)) if b not in first]
    where = "the ranks of positions {} to {}".format
    collect(submit(ex, calls), lambda b: where(*bands[b]), name, n, progress, "ranks",
            lambda r: first.__setitem__(r["band"], mark(work, WL.rank_pairs_piece(r["band"]), r)),
            lambda r: bands[r["band"]][1] - bands[r["band"]][0], sum(k1 - k0 for k0, k1 in (bands[b] for b in first)))
    counts = np.array([first[b]["counts"] for b in range(len(bands))], np.int64).reshape(len(bands), len(blocks))
    offsets = np.cumsum(counts, axis=1) - counts
    second = {b: d for b in range(len(blocks)) if (d := done(work, WL.rank_piece(b))) is not None}
    calls2: list[tuple[int, Any, tuple]] = [(j, rank_block, (work, j, starts[j], sizes[j],
                              [[b, int(offsets[b, j]), int(counts[b, j])] for b in range(len(bands)) if counts[b, j]]))
             for j in range(len(blocks)) if j not in second]
    collect(submit(ex, calls2), lambda j: f"the ranks of read block {j + 1}", name, len(blocks), None, "ranks",
            lambda r: second.__setitem__(r["block"], mark(work, WL.rank_piece(r["block"]), r)))
    files = {k: v for j in range(len(blocks)) for k, v in second[j]["files"].items()}
    doc = mark(work, "ranks", {"starts": starts, "files": files})
    for b in range(len(bands)):  # the pairs are read by no one now
        as_store(work).delete(WL.rank_pairs(b))
        as_store(work).delete(WL.marker(WL.rank_pairs_piece(b)))
    return doc


def gather_ranks(work: Any, g: np.ndarray) -> np.ndarray:
    """The positions of input indices ``g`` (any order), from the read blocks' rank files."""
    starts = np.asarray((get_json(work, WL.marker("ranks")) or {})["starts"], np.int64)
    blk = np.searchsorted(starts, g, "right") - 1
    by = np.argsort(blk, kind="stable")
    cuts = np.searchsorted(blk[by], np.arange(starts.shape[0] + 1))
    out = np.empty(g.shape[0], np.int64)
    for j in np.flatnonzero(np.diff(cuts)):
        sel = by[cuts[j]:cuts[j + 1]]
        out[sel] = gather((as_store(work), WL.rank_file(int(j))), "<i8", (), g[sel] - starts[j])
    return out
