"""The Euclidean tail: finishing a farthest point ordering with exact distances among neighbours.

Below the hand-over radius the band cannot tell apart points that share a voxel; the ordering goes
on with exact (weighted) Euclidean distances, candidates per cell in a max-heap with lazy keys. All
lengths in grid units (one unit = the voxel size h); points in cell order (see :mod:`.march`).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import INLINE, JIT
from .grid import _slot, morton
from .march import _chord_ok, _norm

GROUP_POINTS = 16  # candidates are kept per run of consecutive cells holding this many points (see euclid_tail)
FAR_MARGIN = 1.0 + 1e-12  # a point is skipped before the square root only when surely not nearer
BOX_SLACK = 1e-6  # grid units: a cell is skipped when its box lies farther than the reach + this
# (far above the rounding of coordinates below 2^21, so no point it holds could have been lowered)


@nb.njit(**INLINE)
def _key(c, cstart, ud):  # pragma: no cover - compiled
    """The largest value of an unordered point of cell c (ordered points hold -1), -1 if none."""
    best = -1.0
    for p in range(cstart[c], cstart[c + 1]):
        if ud[p, 3] > best:
            best = ud[p, 3]
    return best


@nb.njit(**INLINE)
def _sift_down(hkey, heap, i, n):  # pragma: no cover - compiled
    """Restore the 4-ary max-heap of (key, smaller item first on ties) below position i, after
    its key decreased. No item -> position index: the tail only ever touches the top."""
    kv = hkey[i]
    it = heap[i]
    while True:
        c = 4 * i + 1
        if c >= n:
            break
        best = c
        for cc in range(c + 1, min(c + 4, n)):
            if hkey[cc] > hkey[best] or (hkey[cc] == hkey[best] and heap[cc] < heap[best]):
                best = cc
        if hkey[best] < kv or (hkey[best] == kv and heap[best] > it):
            break
        hkey[i] = hkey[best]
        heap[i] = heap[best]
        i = best
    hkey[i] = kv
    heap[i] = it


@nb.njit(**JIT)
def _cell_heap(cs, ud):  # pragma: no cover - compiled
    """The groups' point ranges (group c holds points cstart[c]:cstart[c + 1]: a group is a run of
    consecutive voxels in voxel order holding GROUP_POINTS points or more, the last one fewer),
    the first voxel of each that holds a point, and their max-heap by key (keys in heap order)."""
    nv = cs.shape[0] - 1
    ncell = 0
    held = 0
    for v in range(nv):
        held += cs[v + 1] - cs[v]
        if held >= GROUP_POINTS or (v == nv - 1 and held > 0):
            ncell += 1
            held = 0
    cellv = np.empty(ncell, np.int32)
    cstart = np.empty(ncell + 1, np.int32)
    c = 0
    held = 0
    first = -1
    for v in range(nv):
        if first < 0 and cs[v + 1] > cs[v]:
            first = v
        held += cs[v + 1] - cs[v]
        if held >= GROUP_POINTS or (v == nv - 1 and held > 0):
            cellv[c] = first
            cstart[c] = cs[first]
            c += 1
            held = 0
            first = -1
    cstart[ncell] = cs[nv]
    ckey = np.empty(ncell)
    heap = np.arange(ncell).astype(np.int32)
    for c in range(ncell):
        ckey[c] = _key(c, cstart, ud)
    for i in range((ncell - 2) // 4, -1, -1):
        _sift_down(ckey, heap, np.int64(i), ncell)
    return cstart, cellv, ckey, heap


@nb.njit(**JIT)
def euclid_tail(
    ud, nbr, cs, rkey, ridx, rstart, rend, levels, pcost, weighted, cmin, psep, pnrm, slope, lab,
    rank, order, radius, parent, k0, k_max, rho_stop, tseed, tkey, tpos,
):  # pragma: no cover - compiled
    """Finish a farthest point ordering with exact Euclidean distances among near neighbours.

    ``ud`` holds every point's grid coordinates and, in its last column, its value d: an upper
    bound of the unordered point's distance to the ordered ones, first
    tightened to the exact distance to the point's labelled sample ``order[lab]``. Inserting a
    point q only lowers points within its value (/ cmin when weighted). Candidates are kept per group
    of consecutive cells (GROUP_POINTS points: a heap of one entry per cell was larger than the
    caches, a miss per level of every sift) in a max-heap keyed by an upper bound of the group's
    largest d, refreshed only when the group reaches the top (keys only decrease, so a stale key
    never hides the true maximum). Ties go to the smaller group, then the smaller point: the
    smaller point, as with one entry per cell. Where sheets come close,
    ``psep`` (per point, or one inf for none) bounds the reach: a point is lowered by a sample only
    if they are closer than both their ``psep`` (a fraction of the gap to the other sheet) and the
    chord's sine to both points' sheets (normals ``pnrm``) is at most ``slope``. The ball query
    is written out in :func:`tail_loop`; ordered points hold -1 in d meanwhile. Timed seeds (``tseed`` by
    non-increasing ``tkey``, from ``tpos[0]`` on; see :func:`.march.grid_phase`) join as soon as
    the largest distance is at most their key, and the ones left when every point is ordered come
    last. Returns the new count.
    """
    cstart, cellv, ckey, heap = tail_start(ud, cs, pcost, weighted, psep, pnrm, slope, lab, rank, order)
    hn = np.full(1, ckey.shape[0], np.int64)
    return tail_loop(
        ud, nbr, cs, rkey, ridx, rstart, rend, levels, pcost, weighted, cmin, psep, pnrm, slope, lab,
        rank, order, radius, parent, k0, k_max, rho_stop, tseed, tkey, tpos, cstart, cellv, ckey, heap, hn,
    )


@nb.njit(**JIT)
def tail_start(ud, cs, pcost, weighted, psep, pnrm, slope, lab, rank, order):  # pragma: no cover - compiled
    """The start of :func:`euclid_tail`: the values tightened, the cells' heap built; returns
    (cstart, cellv, ckey, heap) for :func:`tail_loop`."""
    m = ud.shape[0]
    thin = psep.shape[0] == m
    for p in range(m):
        if rank[p] >= 0:
            ud[p, 3] = -1.0  # ordered: never a candidate, never lowered (no rank lookups below)
        elif lab[p] >= 0:
            # tighten to the exact distance to the labelled sample (still an upper bound)
            s = order[lab[p]]
            e = _norm(ud[p, 0] - ud[s, 0], ud[p, 1] - ud[s, 1], ud[p, 2] - ud[s, 2])
            if thin and not _chord_ok(
                ud[p, 0] - ud[s, 0], ud[p, 1] - ud[s, 1], ud[p, 2] - ud[s, 2], e, psep[p], psep[s],
                pnrm[p, 0], pnrm[p, 1], pnrm[p, 2], pnrm[s, 0], pnrm[s, 1], pnrm[s, 2], slope,
            ):
                continue  # the band's value may go around a fold the straight line crosses
            if weighted:
                e *= 0.5 * (pcost[p] + pcost[s])
            if e < ud[p, 3]:
                ud[p, 3] = e
    return _cell_heap(cs, ud)


@nb.njit(**JIT)
def tail_loop(
    ud, nbr, cs, rkey, ridx, rstart, rend, levels, pcost, weighted, cmin, psep, pnrm, slope, lab,
    rank, order, radius, parent, k0, k_max, rho_stop, tseed, tkey, tpos, cstart, cellv, ckey, heap, hn_out,
):  # pragma: no cover - compiled
    """The loop of :func:`euclid_tail` from the heap of :func:`tail_start` (``hn_out[0]`` cells in
    it; the new count is written back): stopping at ``rho_stop`` and going on with the same heap
    orders as one call does. Returns the new count of ordered points.

    The heap's sift, the cell's key and the ball query are written out here, not called:
    a helper that takes arrays costs an atomic increment and decrement per array and call (numba's
    reference counts, which LLVM cannot prune around the helper's loops), about 13 per sample."""
    m = ud.shape[0]
    thin = psep.shape[0] == m
    hn = hn_out[0]
    k = k0
    mask = ridx.shape[0] - 1
    while k < k_max and hn > 0:
        # keys are lazy upper bounds: refresh the top until its stored key is its true key
        top = heap[0]
        kk = -1.0  # (_key written out)
        for p in range(cstart[top], cstart[top + 1]):
            if ud[p, 3] > kk:
                kk = ud[p, 3]
        if kk < 0.0 or kk != ckey[0]:
            if kk < 0.0:  # no candidate left in the cell (none, or only timed seeds): pop it
                hn -= 1
                if hn == 0:
                    continue
                kv = ckey[hn]
                it = heap[hn]
            else:
                kv = kk
                it = top
            # sift (kv, it) down from the top (_sift_down written out)
            q = np.int64(0)
            while True:
                c = 4 * q + 1
                if c >= hn:
                    break
                best = c
                for cc in range(c + 1, min(c + 4, hn)):
                    if ckey[cc] > ckey[best] or (ckey[cc] == ckey[best] and heap[cc] < heap[best]):
                        best = cc
                if ckey[best] < kv or (ckey[best] == kv and heap[best] > it):
                    break
                ckey[q] = ckey[best]
                heap[q] = heap[best]
                q = best
            ckey[q] = kv
            heap[q] = it
            continue
        if kk <= rho_stop:
            break
        if tpos[0] < tseed.shape[0] and tkey[tpos[0]] >= kk:
            i = tseed[tpos[0]]
            radius[k] = tkey[tpos[0]]
            tpos[0] += 1
            parent[k] = -1
            lo = np.int64(0)  # the voxel whose point range holds i (anchor_of written out)
            hi = np.int64(cs.shape[0] - 1)
            while hi - lo > 1:
                mid = (lo + hi) >> 1
                if cs[mid] <= i:
                    lo = mid
                else:
                    hi = mid
            w0 = lo
        else:
            i = -1
            for p in range(cstart[top], cstart[top + 1]):
                if ud[p, 3] == kk:
                    i = p
                    break
            w0 = np.int64(cellv[top])  # (the group's first voxel with a point: on to i's)
            while cs[w0 + 1] <= i:
                w0 += 1
            radius[k] = kk
            parent[k] = lab[i]
        rank[i] = k
        order[k] = i
        ud[i, 3] = -1.0
        reach = kk / cmin if weighted else kk
        # lower the values of the points within reach of i. The cells searched: the voxel cells
        # around i's when the reach is under a voxel (walked through the neighbour table), else the
        # coarse cells of side 2^j >= the reach (at most 3 a side while the reach is within the
        # coarse levels); a cell whose box lies beyond the reach is skipped
        j = 0
        side = 1.0
        while j < levels and side < reach:
            j += 1
            side *= 2.0
        ux, uy, uz = ud[i, 0], ud[i, 1], ud[i, 2]
        x0 = int(np.floor((ux - reach) / side))
        x1 = int(np.floor((ux + reach) / side))
        y0 = int(np.floor((uy - reach) / side))
        y1 = int(np.floor((uy + reach) / side))
        z0 = int(np.floor((uz - reach) / side))
        z1 = int(np.floor((uz + reach) / side))
        fx = int(np.floor(ux))
        fy = int(np.floor(uy))
        fz = int(np.floor(uz))
        lim = reach + BOX_SLACK
        lim2 = lim * lim
        for x in range(x0, x1 + 1):
            gx = _box_gap(ux, x * side, side)
            for y in range(y0, y1 + 1):
                gy = _box_gap(uy, y * side, side)
                for z in range(z0, z1 + 1):
                    gz = _box_gap(uz, z * side, side)
                    if gx * gx + gy * gy + gz * gz > lim2:
                        continue
                    if j == 0:
                        # walk from i's cell: steps up first, then down, so that every voxel on
                        # the way is a corner of one of the two cells (and so exists)
                        w = w0
                        dx, dy, dz = x - fx, y - fy, z - fz
                        if dx > 0 and w >= 0:
                            w = nbr[w, 1]
                        if dy > 0 and w >= 0:
                            w = nbr[w, 3]
                        if dz > 0 and w >= 0:
                            w = nbr[w, 5]
                        if dx < 0 and w >= 0:
                            w = nbr[w, 0]
                        if dy < 0 and w >= 0:
                            w = nbr[w, 2]
                        if dz < 0 and w >= 0:
                            w = nbr[w, 4]
                        if w < 0:
                            continue
                        p0 = cs[w]
                        p1 = cs[w + 1]
                    else:
                        if x < 0 or y < 0 or z < 0:
                            continue
                        key = (morton(x, y, z) << 3) | j
                        s = _slot(key, mask)  # (hash_find written out)
                        run = -1
                        while True:
                            r = ridx[s]
                            if r < 0:
                                break
                            if rkey[r] == key:
                                run = r
                                break
                            s = (s + 1) & mask
                        if run < 0:
                            continue
                        p0 = rstart[run]
                        p1 = rend[run]
                    for p in range(p0, p1):
                        dp = ud[p, 3]
                        if dp < 0.0:
                            continue  # ordered, or a timed seed
                        ex = ud[p, 0] - ux
                        ey = ud[p, 1] - uy
                        ez = ud[p, 2] - uz
                        d2 = ex * ex + ey * ey + ez * ez
                        if not weighted and d2 > dp * dp * FAR_MARGIN:
                            continue  # surely no nearer (most points of the coarse cells)
                        dd = np.sqrt(d2)
                        if thin and not _chord_ok(
                            ex, ey, ez, dd, psep[p], psep[i], pnrm[p, 0], pnrm[p, 1], pnrm[p, 2],
                            pnrm[i, 0], pnrm[i, 1], pnrm[i, 2], slope,
                        ):
                            continue  # across a gap or a tight fold: not a surface distance
                        if weighted:
                            dd *= 0.5 * (pcost[p] + pcost[i])
                        if dd < dp:
                            ud[p, 3] = dd
                            lab[p] = k
        k += 1
    if hn == 0:  # every candidate is ordered: the timed seeds not taken yet come last
        while k < k_max and tpos[0] < tseed.shape[0]:
            i = tseed[tpos[0]]
            rank[i] = k
            order[k] = i
            radius[k] = tkey[tpos[0]]
            parent[k] = -1
            tpos[0] += 1
            k += 1
    hn_out[0] = hn
    return k


@nb.njit(**INLINE)
def _box_gap(c, lo, side):  # pragma: no cover - compiled
    """How far the coordinate c lies outside [lo, lo + side] (0 inside)."""
    if c < lo:
        return lo - c
    if c > lo + side:
        return c - lo - side
    return 0.0
