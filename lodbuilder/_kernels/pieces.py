"""Pieces of the band that no sample has reached yet ("dormant" pieces), for the grid phase.

A dormant piece's points hold, as their value, an upper bound of their Euclidean distance to the
samples (the band distance to them is infinite): exact for the samples up to ``psync[c]``, the
ones the piece was last refreshed against. Values only decrease, so a stale value is an upper
bound and the candidate heap (keys only decrease) stays valid; the grid phase refreshes a dormant
piece when one of its points reaches the top, and takes the point when the refreshed value is
still the largest: the piece then enters at its exact Euclidean distance to the samples (see
:func:`lodbuilder._kernels.march.grid_phase`).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import JIT
from .heaps import maxheap_decrease
from .topology import _cell_key, anchor_of


@nb.njit(**JIT)
def piece_tables(piece, npiece, u):  # pragma: no cover - compiled
    """CSR of the points of every piece (``pstart``, ``pidx``) and each piece's box (grid units:
    min x, y, z, max x, y, z)."""
    m = piece.shape[0]
    pstart = np.zeros(npiece + 1, np.int64)
    for p in range(m):
        pstart[piece[p] + 1] += 1
    for c in range(npiece):
        pstart[c + 1] += pstart[c]
    fill = pstart[:-1].copy()
    pidx = np.empty(m, np.int32)
    box = np.empty((npiece, 6))
    box[:, :3] = np.inf
    box[:, 3:] = -np.inf
    for p in range(m):
        c = piece[p]
        pidx[fill[c]] = p
        fill[c] += 1
        for a in range(3):
            if u[p, a] < box[c, a]:
                box[c, a] = u[p, a]
            if u[p, a] > box[c, 3 + a]:
                box[c, 3 + a] = u[p, a]
    return pstart, pidx, box


@nb.njit(**JIT)
def refresh_piece(
    c, k, order, u, val, lq, rank, pstart, pidx, pbox, psync, pmax, weighted, pcost, cmin,
    cs, cellv, cellof, ckey, heap, hpos, hn, cmark, stamp,
):  # pragma: no cover - compiled
    """Lower the values of dormant piece ``c``'s points to their Euclidean distance to the samples
    ``order[psync[c]:k]`` (scaled by the mean cost of the two ends when ``weighted``), then the
    keys of their cells. A sample farther from the piece's box than the piece's largest value
    (``pmax``; over ``cmin`` when weighted) lowers nothing and is skipped."""
    for j in range(psync[c], k):
        q = order[j]
        dd = 0.0
        for a in range(3):
            g = pbox[c, a] - u[q, a]
            if u[q, a] - pbox[c, 3 + a] > g:
                g = u[q, a] - pbox[c, 3 + a]
            if g > 0.0:
                dd += g * g
        reach = pmax[c] / cmin if weighted else pmax[c]
        if dd >= reach * reach:
            continue
        best = -1.0
        for t in range(pstart[c], pstart[c + 1]):
            p = pidx[t]
            if rank[p] >= 0:
                continue
            ex = u[p, 0] - u[q, 0]
            ey = u[p, 1] - u[q, 1]
            ez = u[p, 2] - u[q, 2]
            e = np.sqrt(ex * ex + ey * ey + ez * ez)
            if weighted:
                e *= 0.5 * (pcost[p] + pcost[q])
            if e < val[p]:
                val[p] = e
                lq[p] = j
            if val[p] > best:
                best = val[p]
        pmax[c] = best
    psync[c] = k
    for t in range(pstart[c], pstart[c + 1]):
        p = pidx[t]
        cell = cellof[anchor_of(cs, np.int64(p))]
        if cmark[cell] == stamp:
            continue
        cmark[cell] = stamp
        maxheap_decrease(ckey, heap, hpos, cell, _cell_key(np.int64(cell), cellv, cs, rank, val), hn)


@nb.njit(**JIT)
def first_entries(piece, order, npiece):  # pragma: no cover - compiled
    """The position in ``order`` at which each piece's first point appears, ascending, for the
    pieces that appear (``np.sort(np.unique(piece[order], return_index=True)[1])`` in one pass:
    no sort of the N labels)."""
    seen = np.zeros(npiece, np.bool_)
    out = np.empty(min(npiece, order.shape[0]), np.int64)
    n = 0
    for k in range(order.shape[0]):
        c = piece[order[k]]
        if not seen[c]:
            seen[c] = True
            out[n] = k
            n += 1
    return out[:n]
