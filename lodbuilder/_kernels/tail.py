"""The Euclidean tail: finishing a farthest point ordering with exact distances among neighbours.

Below the hand-over radius the band cannot tell apart points that share a voxel; the ordering goes
on with exact (weighted) Euclidean distances, candidates per cell in a max-heap with lazy keys. All
lengths in grid units (one unit = the voxel size h); points in cell order (see :mod:`.march`).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import JIT
from .grid import hash_find, morton
from .heaps import maxheap_build, maxheap_pop, maxheap_sift_down
from .march import _chord_ok, _norm
from .topology import _cell_key, anchor_of, cell_tables

FAR_MARGIN = 1.0 + 1e-12  # a point is skipped before the square root only when surely not nearer


@nb.njit(**JIT)
def euclid_tail(
    u, nbr, cs, rkey, ridx, rstart, rend, levels, pcost, weighted, cmin, psep, pnrm, slope, d, lab,
    rank, order, radius, parent, k0, k_max, rho_stop, tseed, tkey, tpos,
):  # pragma: no cover - compiled
    """Finish a farthest point ordering with exact Euclidean distances among near neighbours.

    ``d`` holds upper bounds of every unordered point's distance to the ordered ones, first
    tightened to the exact distance to the point's labelled sample ``order[lab]``. Inserting a
    point q only lowers points within d[q] (/ cmin when weighted). Candidates are kept per cell in a
    max-heap keyed by an upper bound of the cell's largest d, refreshed only when the cell reaches the
    top (keys only decrease, so a stale key never hides the true maximum). Where sheets come close,
    ``psep`` (per point, or one inf for none) bounds the reach: a point is lowered by a sample only
    if they are closer than both their ``psep`` (a fraction of the gap to the other sheet) and the
    chord's sine to both points' sheets (normals ``pnrm``) is at most ``slope``. A ball
    query walks the
    neighbour table to the at most 8 cells around the point when the ball is smaller than a voxel,
    and otherwise scans the coarse cells of :func:`coarse_runs` (side 2^j >= the ball's diameter),
    at most 27 of them while the radius is within the coarse levels. Timed seeds (``tseed`` by
    non-increasing ``tkey``, from ``tpos[0]`` on; see :func:`.march.grid_phase`) join as soon as
    the largest distance is at most their key, and the ones left when every point is ordered come
    last. Returns the new count.
    """
    cellv, cellof = cell_tables(cs)
    ncell = cellv.shape[0]
    m = u.shape[0]
    thin = psep.shape[0] == m
    for p in range(m):
        if rank[p] < 0 and lab[p] >= 0:
            # tighten to the exact distance to the labelled sample (still an upper bound)
            s = order[lab[p]]
            e = _norm(u[p, 0] - u[s, 0], u[p, 1] - u[s, 1], u[p, 2] - u[s, 2])
            if thin and not _chord_ok(
                u[p, 0] - u[s, 0], u[p, 1] - u[s, 1], u[p, 2] - u[s, 2], e, psep[p], psep[s],
                pnrm[p, 0], pnrm[p, 1], pnrm[p, 2], pnrm[s, 0], pnrm[s, 1], pnrm[s, 2], slope,
            ):
                continue  # the band's value may go around a fold the straight line crosses
            if weighted:
                e *= 0.5 * (pcost[p] + pcost[s])
            if e < d[p]:
                d[p] = e
    ckey = np.empty(ncell)
    for c in range(ncell):
        ckey[c] = _cell_key(np.int64(c), cellv, cs, rank, d)
    heap = np.arange(ncell).astype(np.int32)
    hpos = np.empty(ncell, np.int32)
    hn = ncell
    maxheap_build(ckey, heap, hpos, hn)
    k = k0
    while k < k_max and hn > 0:
        # keys are lazy upper bounds: refresh the top until its stored key is its true key
        top = heap[0]
        kk = _cell_key(np.int64(top), cellv, cs, rank, d)
        if kk != ckey[0]:
            ckey[0] = kk
            if kk < 0.0:
                hn = maxheap_pop(ckey, heap, hpos, hn)
            else:
                maxheap_sift_down(ckey, heap, hpos, np.int64(0), hn)
            continue
        if kk < 0.0:  # no candidate left in the cell (only timed seeds)
            hn = maxheap_pop(ckey, heap, hpos, hn)
            continue
        if kk <= rho_stop:
            break
        if tpos[0] < tseed.shape[0] and tkey[tpos[0]] >= kk:
            i = tseed[tpos[0]]
            radius[k] = tkey[tpos[0]]
            tpos[0] += 1
            w0 = anchor_of(cs, np.int64(i))
            parent[k] = -1
        else:
            w0 = cellv[top]
            i = -1
            for p in range(cs[w0], cs[w0 + 1]):
                if rank[p] < 0 and d[p] == kk:
                    i = p
                    break
            radius[k] = kk
            parent[k] = lab[i]
        rank[i] = k
        order[k] = i
        reach = kk / cmin if weighted else kk
        j = 0
        side = 1.0
        while j < levels and side < 2.0 * reach:
            j += 1
            side *= 2.0
        x0 = int(np.floor((u[i, 0] - reach) / side))
        x1 = int(np.floor((u[i, 0] + reach) / side))
        y0 = int(np.floor((u[i, 1] - reach) / side))
        y1 = int(np.floor((u[i, 1] + reach) / side))
        z0 = int(np.floor((u[i, 2] - reach) / side))
        z1 = int(np.floor((u[i, 2] + reach) / side))
        fx = int(np.floor(u[i, 0]))
        fy = int(np.floor(u[i, 1]))
        fz = int(np.floor(u[i, 2]))
        for x in range(x0, x1 + 1):
            for y in range(y0, y1 + 1):
                for z in range(z0, z1 + 1):
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
                        run = hash_find(ridx, rkey, (morton(x, y, z) << 3) | j)
                        if run < 0:
                            continue
                        p0 = rstart[run]
                        p1 = rend[run]
                    for p in range(p0, p1):
                        if rank[p] >= 0:
                            continue
                        ex = u[p, 0] - u[i, 0]
                        ey = u[p, 1] - u[i, 1]
                        ez = u[p, 2] - u[i, 2]
                        d2 = ex * ex + ey * ey + ez * ez
                        if not weighted and d2 > d[p] * d[p] * FAR_MARGIN:
                            continue  # surely no nearer (most points of the coarse cells)
                        dd = np.sqrt(d2)
                        if thin and not _chord_ok(
                            ex, ey, ez, dd, psep[p], psep[i], pnrm[p, 0], pnrm[p, 1], pnrm[p, 2],
                            pnrm[i, 0], pnrm[i, 1], pnrm[i, 2], slope,
                        ):
                            continue  # across a gap or a tight fold: not a surface distance
                        if weighted:
                            dd *= 0.5 * (pcost[p] + pcost[i])
                        if dd < d[p]:
                            d[p] = dd
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
    return k
