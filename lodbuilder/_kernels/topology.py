"""The band's topology as the ordering sees it: the voxels that hold points (cells), the voxel that
holds a point, which corner of each point's cell is its nearest marchable voxel, and how many
connected pieces of the band hold points."""

from __future__ import annotations

import numba as nb
import numpy as np

from . import INLINE, JIT
from .grid import BLOCK, BLOCK_BITS, lower_bound, morton, unmorton


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


@nb.njit(**JIT)
def band_marchable(u, irad2, rad, ostart, bkey, bstart, cand, cap_limit):  # pragma: no cover - compiled
    """The voxels :func:`lodbuilder._kernels.grid.band_voxels` keeps for a band of one radius
    (``rad``, ``irad2 = 1 / rad^2``: scalars, grid units), in the same order, and whether each is
    marchable, without each voxel's nearest point: what :func:`point_pieces` needs.

    The same blocks, cells, columns and z ranges as band_voxels; a voxel is marchable when some
    point of a cell in reach has ``e2 * irad2 <= 1`` (band_voxels' ``q2 = min(e2) * irad2 <= 1``:
    the same test, as a product by a positive constant rounds monotonically), so the search over a
    cell's points stops at the first such point and skips voxels already found marchable. Returns
    (keys, marchable as uint8, count); count is -1 when more than ``cap_limit`` voxels would be needed."""
    ncell = ostart.shape[0] - 1
    nb3 = BLOCK * BLOCK * BLOCK
    nblk = bkey.shape[0]
    ccx = np.empty(ncell, np.int32)
    ccy = np.empty(ncell, np.int32)
    ccz = np.empty(ncell, np.int32)
    for c in range(ncell):
        p0 = ostart[c]
        ccx[c] = int(np.floor(u[p0, 0]))
        ccy[c] = int(np.floor(u[p0, 1]))
        ccz[c] = int(np.floor(u[p0, 2]))
    ext = int(np.floor(rad))
    reach_blocks = (ext + 1 + BLOCK - 1) // BLOCK
    lut = np.empty(BLOCK, np.int64)
    for t in range(BLOCK):
        lut[t] = morton(t, 0, 0)  # (a coordinate's bits spread)
    rad2 = rad * rad
    # bit 0: q2 <= 1 (kept), bit 1: a corner of an occupied cell (kept), bit 2: marchable, i.e.
    # q2 <= 1 once rounded to float32, as build_band's costs test it (a corner a hair beyond r is)
    mk = np.zeros(nb3, np.uint8)
    cap = max(1024, 2 * u.shape[0])
    keys = np.empty(cap, np.int64)
    mo = np.empty(cap, np.uint8)
    count = 0
    for t in range(cand.shape[0]):
        blk = cand[t]
        bx, by, bz = unmorton(blk)
        x0 = bx * BLOCK
        y0 = by * BLOCK
        z0 = bz * BLOCK
        for li in range(nb3):
            mk[li] = 0
        touched = False
        for dx in range(-reach_blocks, reach_blocks + 1):
            for dy in range(-reach_blocks, reach_blocks + 1):
                for dz in range(-reach_blocks, reach_blocks + 1):
                    nx, ny, nz = bx + dx, by + dy, bz + dz
                    if nx < 0 or ny < 0 or nz < 0:
                        continue
                    nk = morton(nx, ny, nz)
                    jb = lower_bound(bkey, nk)
                    if jb >= nblk or bkey[jb] != nk:
                        continue
                    for c in range(bstart[jb], bstart[jb + 1]):
                        cx, cy, cz = ccx[c], ccy[c], ccz[c]
                        if cx + ext + 1 < x0 or cx - ext > x0 + BLOCK - 1:
                            continue
                        if cy + ext + 1 < y0 or cy - ext > y0 + BLOCK - 1:
                            continue
                        if cz + ext + 1 < z0 or cz - ext > z0 + BLOCK - 1:
                            continue
                        p0, p1 = ostart[c], ostart[c + 1]
                        for x in range(max(cx - ext, x0), min(cx + ext + 1, x0 + BLOCK - 1) + 1):
                            for y in range(max(cy - ext, y0), min(cy + ext + 1, y0 + BLOCK - 1) + 1):
                                corner = (x == cx or x == cx + 1) and (y == cy or y == cy + 1)
                                lxy = lut[x - x0] | (lut[y - y0] << 1)
                                # a column whose voxels within the cell's reach are all kept and
                                # marchable already: nothing the cell's points can change but corners
                                full = True
                                for z in range(max(cz - ext, z0), min(cz + ext + 1, z0 + BLOCK - 1) + 1):
                                    if mk[lxy | (lut[z - z0] << 2)] & 1 == 0:
                                        full = False
                                        break
                                if full:
                                    if corner:
                                        for z in range(max(cz, z0), min(cz + 1, z0 + BLOCK - 1) + 1):
                                            mk[lxy | (lut[z - z0] << 2)] |= 2
                                    continue
                                zlo = np.inf
                                zhi = -np.inf
                                for i in range(p0, p1):
                                    ex = u[i, 0] - x
                                    ey = u[i, 1] - y
                                    rest = rad2 - ex * ex - ey * ey
                                    if rest >= 0.0:
                                        w = np.sqrt(rest)
                                        zlo = min(zlo, u[i, 2] - w)
                                        zhi = max(zhi, u[i, 2] + w)
                                za = int(np.ceil(zlo)) if zlo <= zhi else cz + 2
                                zb = int(np.floor(zhi)) if zlo <= zhi else cz - 1
                                if corner:
                                    za = min(za, cz)
                                    zb = max(zb, cz + 1)
                                za = max(za, z0)
                                zb = min(zb, z0 + BLOCK - 1)
                                for z in range(za, zb + 1):
                                    li = lxy | (lut[z - z0] << 2)
                                    touched = True
                                    if corner and (z == cz or z == cz + 1):
                                        mk[li] |= 2
                                    if mk[li] & 1:
                                        continue
                                    for i in range(p0, p1):
                                        ex = u[i, 0] - x
                                        ey = u[i, 1] - y
                                        ez = u[i, 2] - z
                                        q2 = (ex * ex + ey * ey + ez * ez) * irad2
                                        if q2 <= 1.0:
                                            mk[li] |= 5
                                            break
                                        if np.float32(q2) <= 1.0:
                                            mk[li] |= 4
        if not touched:
            continue
        base = blk << (3 * BLOCK_BITS)
        for li in range(nb3):
            if mk[li] & 3 == 0:
                continue
            if count == cap:
                cap *= 2
                keys = np.concatenate((keys, np.empty(cap - count, np.int64)))
                mo = np.concatenate((mo, np.empty(cap - count, np.uint8)))
            keys[count] = base | li
            mo[count] = mk[li] >> 2
            count += 1
            if count > cap_limit:
                return keys, mo, -1
    return keys[:count].copy(), mo[:count].copy(), count
