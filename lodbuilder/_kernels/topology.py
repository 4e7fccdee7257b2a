"""The band's topology as the ordering sees it: the voxels that hold points (cells), the voxel that
holds a point, which corner of each point's cell is its nearest marchable voxel, and how many
connected pieces of the band hold points."""

from __future__ import annotations

import numba as nb
import numpy as np

from . import INLINE, JIT


@nb.njit(**INLINE)
def _cell_corners(nbr, a, corner):  # pragma: no cover - compiled
    """The 8 corner voxels (x + 2 y + 4 z offsets) of the cell anchored at voxel a, into ``corner``
    (-1 where the band has none)."""
    for c in range(8):
        w = a
        for ax in range(3):
            if (c >> ax) & 1 and w >= 0:
                w = nbr[w, 2 * ax + 1]
        corner[c] = w


@nb.njit(**INLINE)
def _nearest_of_cell(u, cs, vcost, a, corner, out):  # pragma: no cover - compiled
    """:func:`nearest_corners` of the points of the cell anchored at a (its corners: ``corner``)."""
    for p in range(cs[a], cs[a + 1]):
        fx = np.floor(u[p, 0])
        fy = np.floor(u[p, 1])
        fz = np.floor(u[p, 2])
        best = np.inf
        out[p] = 255
        for c in range(8):
            w = corner[c]
            if w < 0 or vcost[w] == np.inf:
                continue
            dx = u[p, 0] - fx - (c & 1)
            dy = u[p, 1] - fy - ((c >> 1) & 1)
            dz = u[p, 2] - fz - (c >> 2)
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            if d < best:
                best = d
                out[p] = c


@nb.njit(**JIT)
def nearest_corners(u, nbr, cs, vcost):  # pragma: no cover - compiled
    """Per point: which corner (x + 2 y + 4 z offsets) of its cell is the nearest marchable voxel
    (255: none)."""
    m = u.shape[0]
    out = np.full(m, 255, np.uint8)
    corner = np.empty(8, np.int64)
    nv = cs.shape[0] - 1
    for a in range(nv):
        if cs[a + 1] == cs[a]:
            continue
        _cell_corners(nbr, a, corner)
        _nearest_of_cell(u, cs, vcost, a, corner, out)
    return out


@nb.njit(**JIT)
def nearest_corners_since(u, nbr, cs, vcost, old_vcost, old_near):  # pragma: no cover - compiled
    """:func:`nearest_corners` for the voxel costs ``vcost``, knowing them for ``old_vcost``
    (``old_near``): a cell none of whose corners became marchable or not since keeps its points'
    corners (a band cut down near a few thin points recomputes only there)."""
    out = old_near.copy()
    corner = np.empty(8, np.int64)
    nv = cs.shape[0] - 1
    for a in range(nv):
        if cs[a + 1] == cs[a]:
            continue
        _cell_corners(nbr, a, corner)
        changed = False
        for c in range(8):
            w = corner[c]
            if w >= 0 and (vcost[w] == np.inf) != (old_vcost[w] == np.inf):
                changed = True
                break
        if changed:
            _nearest_of_cell(u, cs, vcost, a, corner, out)
    return out


@nb.njit(**JIT)
def point_pieces(nbr, cs, near, vcost):  # pragma: no cover - compiled
    """The piece of every point (point order) and the number of pieces: the connected piece of the
    band (marchable voxels, 6-neighbours) that holds the point's nearest marchable corner, which a
    march from any point of the piece reaches; a point without a marchable corner is a piece of
    its own. Pieces are numbered in point order of their first point."""
    nv = nbr.shape[0]
    lab = np.full(nv, -1, np.int32)
    queue = np.empty(nv, np.int32)
    piece = np.empty(cs[nv], np.int32)
    ncomp = 0
    for a in range(nv):
        for p in range(cs[a], cs[a + 1]):
            c = near[p]
            if c == 255:
                piece[p] = ncomp
                ncomp += 1
                continue
            w = a
            for ax in range(3):
                if (c >> ax) & 1:
                    w = nbr[w, 2 * ax + 1]
            if lab[w] >= 0:
                piece[p] = lab[w]
                continue
            lab[w] = ncomp
            queue[0] = w
            qn = 1
            qi = 0
            while qi < qn:
                v = queue[qi]
                qi += 1
                for j in range(6):
                    x = nbr[v, j]
                    if x >= 0 and lab[x] < 0 and vcost[x] < np.inf:
                        lab[x] = ncomp
                        queue[qn] = x
                        qn += 1
            piece[p] = ncomp
            ncomp += 1
    return piece, ncomp


@nb.njit(**INLINE)
def anchor_of(cs, i):  # pragma: no cover - compiled
    """The voxel whose point range holds point i (cs is non-decreasing): the last v with
    cs[v] <= i. Written out rather than np.searchsorted: one compiled version for every caller."""
    lo = np.int64(0)
    hi = np.int64(cs.shape[0] - 1)
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if cs[mid] <= i:
            lo = mid
        else:
            hi = mid
    return lo


@nb.njit(**INLINE)
def _cell_key(cell, cellv, cs, rank, val):  # pragma: no cover - compiled
    w = cellv[cell]
    best = -1.0
    for p in range(cs[w], cs[w + 1]):
        if rank[p] < 0 and val[p] > best:
            best = val[p]
    return best


@nb.njit(**JIT)
def cell_tables(cs):  # pragma: no cover - compiled
    """The voxels that hold points (cells): cell -> voxel, voxel -> cell (-1)."""
    nv = cs.shape[0] - 1
    ncell = 0
    for v in range(nv):
        if cs[v + 1] > cs[v]:
            ncell += 1
    cellv = np.empty(ncell, np.int32)
    cellof = np.full(nv, -1, np.int32)
    c = 0
    for v in range(nv):
        if cs[v + 1] > cs[v]:
            cellof[v] = c
            cellv[c] = v
            c += 1
    return cellv, cellof
