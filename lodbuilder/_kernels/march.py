"""Fast Marching in the voxel band and the farthest point ordering loops.

All lengths are in grid units (one unit = the voxel size h). Points are indexed in cell order
(sorted by the Morton key of their cell); ``cs[v]:cs[v + 1]`` are the points whose cell's lower corner
is voxel v.

Per-voxel state: arrival time ``T`` (float32, only ever lowered), the rank of the sample that set it
(``vlab``) and a round stamp: ``stamp == 2 * rnd`` means "trial in round rnd", ``2 * rnd + 1``
"accepted in round rnd", anything smaller "known from an earlier round". Nothing is re-initialised per
sample: a new sample marches only where it lowers ``T``. The upwind update reads its neighbours'
current values whatever their state: a trial value is an upper bound of its final value and the
update is monotone in its inputs, so this only lowers a voxel earlier; the voxel is updated again
when that neighbour is accepted, and skipping the state test halves the memory traffic per pop.
Fronts are kept in an indexed min-heap (decrease-key, no stale entries).

Per-point state: ``dq`` = min over the 8 corner voxels v of the point's cell of T[v] + |u - v| * cost
(an upper bound of the band distance to the samples), ``lq`` = the sample that achieved it, and the
candidate value ``val``: for the uniform metric the certified upper bound of the Euclidean distance to
the samples, min over time of max(dq, |u - u[sample lq]|); for a weighted metric the same with the
straight distance scaled by the mean cost of its two ends (so a constant cost only scales radii).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import JIT
from .grid import hash_find, lookup, morton
from .heaps import (
    iheap_pop,
    iheap_push,
    maxheap_build,
    maxheap_decrease,
    maxheap_pop,
    maxheap_sift_down,
)

SEED_RADIUS = 6.0  # voxels around a new sample that get their exact distance
SEED_QUEUE = 4096  # > the 905 voxel centres of a ball of radius 6


@nb.njit(**JIT)
def _solve(a, b, c, f):  # pragma: no cover - compiled
    """First-order upwind update |grad T| = f from the three axis minima."""
    if b < a:
        a, b = b, a
    if c < b:
        b, c = c, b
        if b < a:
            a, b = b, a
    t = a + f
    if t <= b:
        return t
    t = 0.5 * (a + b + np.sqrt(2.0 * f * f - (a - b) * (a - b)))
    if t <= c:
        return t
    s = a + b + c
    q = a * a + b * b + c * c
    return (s + np.sqrt(max(s * s - 3.0 * (q - f * f), 0.0))) / 3.0


@nb.njit(**JIT)
def _norm(dx, dy, dz):  # pragma: no cover - compiled
    # helpers take scalars only: an array argument in a hot loop costs atomic reference counting
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@nb.njit(**JIT)
def march_round(
    src, lab, rnd, u, coord, nbr, cs, cellof, hkeys, hvals, vcost, pcost,
    T, vlab, stamp, seen, dq, lq, rank, dstamp, dirty, nd, hk, hv, hpos,
):  # pragma: no cover - compiled
    """Propagate the front of sources ``src`` (point indices) labelled ``lab`` where it lowers T.

    Updates dq/lq of points near lowered voxels and appends their cells to ``dirty`` (returns the new
    count, the heap arrays and the number of pops).
    """
    trial = 2 * rnd
    acc = 2 * rnd + 1
    n = 0
    queue = np.empty(SEED_QUEUE, np.int32)
    for s in range(src.shape[0]):
        # exact distances to the band voxels within SEED_RADIUS of the source that are connected
        # to its cell inside that ball (a breadth-first walk over the neighbour table)
        i = src[s]
        mark = np.int32(rnd * src.shape[0] + s)
        v0 = lookup(hkeys, hvals, int(np.floor(u[i, 0])), int(np.floor(u[i, 1])), int(np.floor(u[i, 2])))
        seen[v0] = mark
        queue[0] = v0
        qn = 1
        qi = 0
        while qi < qn:
            v = queue[qi]
            qi += 1
            d = _norm(u[i, 0] - coord[v, 0], u[i, 1] - coord[v, 1], u[i, 2] - coord[v, 2])
            t = np.float32(d * vcost[v])
            if t < T[v]:
                T[v] = t
                vlab[v] = lab
                stamp[v] = trial
                n = iheap_push(hk, hv, hpos, n, t, v)
            for j in range(6):
                w = nbr[v, j]
                if w < 0 or seen[w] == mark or qn == SEED_QUEUE:
                    continue
                seen[w] = mark
                if _norm(u[i, 0] - coord[w, 0], u[i, 1] - coord[w, 1], u[i, 2] - coord[w, 2]) <= SEED_RADIUS:
                    queue[qn] = w
                    qn += 1
    pops = 0
    while n > 0:
        t, v, n = iheap_pop(hk, hv, hpos, n)
        stamp[v] = acc
        pops += 1
        tv = np.float64(T[v])
        lv = vlab[v]
        cx = np.float64(coord[v, 0])
        cy = np.float64(coord[v, 1])
        cz = np.float64(coord[v, 2])
        # points of the 8 cells that have v as a corner
        wx = nbr[v, 0]
        for a in range(2):
            wa = v if a == 0 else wx
            if wa < 0:
                continue
            for b in range(2):
                wb = wa if b == 0 else nbr[wa, 2]
                if wb < 0:
                    continue
                for c in range(2):
                    w = wb if c == 0 else nbr[wb, 4]
                    if w < 0:
                        continue
                    cell = cellof[w]
                    if cell < 0:
                        continue
                    for p in range(cs[w], cs[w + 1]):
                        if rank[p] >= 0:
                            continue
                        dd = tv + _norm(u[p, 0] - cx, u[p, 1] - cy, u[p, 2] - cz) * pcost[p]
                        if dd < dq[p]:
                            dq[p] = dd
                            lq[p] = lv
                            if dstamp[cell] != rnd:
                                dstamp[cell] = rnd
                                dirty[nd] = cell
                                nd += 1
        # march to the 6 neighbours
        for j in range(6):
            m = nbr[v, j]
            if m < 0 or stamp[m] == acc:
                continue
            # the smaller neighbour value along each axis (written out: passing T to a helper
            # here costs two atomic reference-count operations per call)
            am = np.inf
            for ax in range(3):
                va = np.inf
                na = nbr[m, 2 * ax]
                if na >= 0:
                    va = T[na]
                nb_ = nbr[m, 2 * ax + 1]
                if nb_ >= 0 and T[nb_] < va:
                    va = T[nb_]
                if ax == 0:
                    am = va
                elif ax == 1:
                    bm = va
                else:
                    cm = va
            tn = np.float32(_solve(np.float64(am), np.float64(bm), np.float64(cm), vcost[m]))
            if tn < T[m]:
                T[m] = tn
                vlab[m] = lv
                stamp[m] = trial
                n = iheap_push(hk, hv, hpos, n, tn, m)
    return nd, pops


@nb.njit(**JIT)
def _cell_key(cell, cellv, cs, rank, val):  # pragma: no cover - compiled
    w = cellv[cell]
    best = -1.0
    for p in range(cs[w], cs[w + 1]):
        if rank[p] < 0 and val[p] > best:
            best = val[p]
    return best


@nb.njit(**JIT)
def _cell_tables(cs):  # pragma: no cover - compiled
    """The voxels that hold points (cells): cell -> voxel, voxel -> cell (-1), point -> cell."""
    nv = cs.shape[0] - 1
    ncell = 0
    for v in range(nv):
        if cs[v + 1] > cs[v]:
            ncell += 1
    cellv = np.empty(ncell, np.int64)
    cellof = np.full(nv, -1, np.int32)
    pcell = np.empty(cs[nv], np.int64)
    c = 0
    for v in range(nv):
        if cs[v + 1] > cs[v]:
            cellof[v] = c
            cellv[c] = v
            for p in range(cs[v], cs[v + 1]):
                pcell[p] = c
            c += 1
    return cellv, cellof, pcell


@nb.njit(**JIT)
def grid_phase(
    u, coord, nbr, cs, hkeys, hvals, vcost, pcost, weighted, seeds, k_max, rho_stop, r_stop,
):  # pragma: no cover - compiled
    """Farthest point ordering under the band metric until the radius falls below ``r_stop``.

    Returns (order, radius, parent, k, val, lq, rank, pops) where ``k`` points are ordered; the other
    points' ``val``/``lq`` seed the Euclidean tail. ``rho_stop < 0`` means no density stop.
    """
    m = u.shape[0]
    nv = coord.shape[0]
    T = np.full(nv, np.inf, np.float32)
    vlab = np.full(nv, -1, np.int64)
    stamp = np.zeros(nv, np.int32)
    cellv, cellof, pcell = _cell_tables(cs)
    ncell = cellv.shape[0]
    dq = np.full(m, np.inf)
    val = np.full(m, np.inf)
    lq = np.full(m, -1, np.int64)
    rank = np.full(m, -1, np.int64)
    dstamp = np.full(ncell, -1, np.int64)
    dirty = np.empty(ncell, np.int64)
    ckey = np.full(ncell, np.inf)  # heap order
    heap = np.arange(ncell).astype(np.int64)
    hpos = np.empty(ncell, np.int64)
    hn = ncell
    maxheap_build(ckey, heap, hpos, hn)
    hk = np.empty(nv, np.float32)
    hv = np.empty(nv, np.int32)
    hpos_v = np.full(nv, -1, np.int32)
    seen = np.full(nv, -1, np.int32)
    order = np.empty(k_max, np.int64)
    radius = np.empty(k_max, np.float64)
    parent = np.empty(k_max, np.int64)
    src = np.empty(1, np.int64)
    pops = 0
    k = 0
    nseed = seeds.shape[0]
    while k < k_max:
        if k < nseed:
            i = seeds[k]
            rad = np.inf
            par = -1
        else:
            if hn == 0:
                break
            top = heap[0]
            kk = ckey[0]
            if kk < 0.0 or kk <= rho_stop or kk < r_stop:
                break
            w = cellv[top]
            i = -1
            best = -1.0
            for p in range(cs[w], cs[w + 1]):
                if rank[p] < 0 and val[p] > best:
                    best = val[p]
                    i = p
            rad = val[i]
            par = lq[i]
        rank[i] = k
        order[k] = i
        radius[k] = rad
        parent[k] = par
        ci = pcell[i]
        # an exhausted cell (key -1) sinks and is dropped when it reaches the top
        maxheap_decrease(ckey, heap, hpos, ci, _cell_key(ci, cellv, cs, rank, val), hn)
        src[0] = i
        nd, pp = march_round(
            src, k, k + 1, u, coord, nbr, cs, cellof, hkeys, hvals, vcost, pcost,
            T, vlab, stamp, seen, dq, lq, rank, dstamp, dirty, 0, hk, hv, hpos_v,
        )
        pops += pp
        for j in range(nd):
            cc = dirty[j]
            w = cellv[cc]
            best = -1.0
            for p in range(cs[w], cs[w + 1]):
                if rank[p] >= 0:
                    continue
                s = order[lq[p]]
                e = _norm(u[p, 0] - u[s, 0], u[p, 1] - u[s, 1], u[p, 2] - u[s, 2])
                if weighted:
                    e *= 0.5 * (pcost[p] + pcost[s])
                cand = dq[p] if dq[p] > e else e
                if cand < val[p]:
                    val[p] = cand
                if val[p] > best:
                    best = val[p]
            maxheap_decrease(ckey, heap, hpos, cc, best, hn)
        # drop exhausted cells from the top
        while hn > 0 and ckey[0] < 0.0:
            hn = maxheap_pop(ckey, heap, hpos, hn)
        k += 1
    return order, radius, parent, k, val, lq, rank, pops


@nb.njit(**JIT)
def multi_source_distance(u, coord, nbr, cs, hkeys, hvals, vcost, pcost, sources):  # pragma: no cover
    """dq of every point for one march from all ``sources`` at once (for tests and analysis)."""
    m = u.shape[0]
    nv = coord.shape[0]
    T = np.full(nv, np.inf, np.float32)
    vlab = np.full(nv, -1, np.int64)
    stamp = np.zeros(nv, np.int32)
    cellof = np.zeros(nv, np.int32)
    ncell = 1
    dq = np.full(m, np.inf)
    lq = np.full(m, -1, np.int64)
    rank = np.full(m, -1, np.int64)
    dstamp = np.full(ncell, -1, np.int64)
    dirty = np.empty(ncell, np.int64)
    hk = np.empty(nv, np.float32)
    hv = np.empty(nv, np.int32)
    nd, pops = march_round(
        sources, 0, 1, u, coord, nbr, cs, cellof, hkeys, hvals, vcost, pcost,
        T, vlab, stamp, np.full(nv, -1, np.int32), dq, lq, rank, dstamp, dirty, 0, hk, hv,
        np.full(nv, -1, np.int32),
    )
    return dq, lq, pops


@nb.njit(**JIT)
def euclid_tail(
    u, cs, hkeys, hvals, chk, chv, rstart, rend, levels, pcost, weighted, cmin, d, lab, rank,
    order, radius, parent, k0, k_max, rho_stop,
):  # pragma: no cover - compiled
    """Finish a farthest point ordering with exact Euclidean distances among near neighbours.

    ``d`` holds upper bounds of every unordered point's distance to the ordered ones (all finite),
    first tightened to the exact distance to the point's labelled sample ``order[lab]``. Inserting a
    point q only lowers points within d[q] (/ cmin when weighted). Candidates are kept per cell in a
    max-heap keyed by an upper bound of the cell's largest d, refreshed only when the cell reaches the
    top (keys only decrease, so a stale key never hides the true maximum). Ball queries scan voxel cells for small balls and the coarse
    cells of :func:`coarse_runs` (side 2^j >= the ball radius) for larger ones, so a query looks up at
    most 27 cells while the radius is within the coarse levels. Returns the new count.
    """
    cellv = _cell_tables(cs)[0]
    ncell = cellv.shape[0]
    m = u.shape[0]
    for p in range(m):
        if rank[p] < 0 and lab[p] >= 0:
            # tighten to the exact distance to the labelled sample (still an upper bound)
            s = order[lab[p]]
            e = _norm(u[p, 0] - u[s, 0], u[p, 1] - u[s, 1], u[p, 2] - u[s, 2])
            if weighted:
                e *= 0.5 * (pcost[p] + pcost[s])
            if e < d[p]:
                d[p] = e
    ckey = np.empty(ncell)
    for c in range(ncell):
        ckey[c] = _cell_key(c, cellv, cs, rank, d)
    heap = np.arange(ncell).astype(np.int64)
    hpos = np.empty(ncell, np.int64)
    hn = ncell
    maxheap_build(ckey, heap, hpos, hn)
    k = k0
    while k < k_max and hn > 0:
        # keys are lazy upper bounds: refresh the top until its stored key is its true key
        top = heap[0]
        kk = _cell_key(top, cellv, cs, rank, d)
        if kk != ckey[0]:
            ckey[0] = kk
            if kk < 0.0:
                hn = maxheap_pop(ckey, heap, hpos, hn)
            else:
                maxheap_sift_down(ckey, heap, hpos, 0, hn)
            continue
        if kk <= rho_stop:
            break
        w = cellv[top]
        i = -1
        for p in range(cs[w], cs[w + 1]):
            if rank[p] < 0 and d[p] == kk:
                i = p
                break
        rank[i] = k
        order[k] = i
        radius[k] = kk
        parent[k] = lab[i]
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
        for x in range(x0, x1 + 1):
            for y in range(y0, y1 + 1):
                for z in range(z0, z1 + 1):
                    if j == 0:
                        v = lookup(hkeys, hvals, x, y, z)
                        if v < 0:
                            continue
                        p0 = cs[v]
                        p1 = cs[v + 1]
                    else:
                        if x < 0 or y < 0 or z < 0:
                            continue
                        run = hash_find(chk, chv, (morton(x, y, z) << 3) | j)
                        if run < 0:
                            continue
                        p0 = rstart[run]
                        p1 = rend[run]
                    for p in range(p0, p1):
                        if rank[p] >= 0:
                            continue
                        s = i
                        dd = _norm(u[p, 0] - u[s, 0], u[p, 1] - u[s, 1], u[p, 2] - u[s, 2])
                        if weighted:
                            dd *= 0.5 * (pcost[p] + pcost[s])
                        if dd < d[p]:
                            d[p] = dd
                            lab[p] = k
        k += 1
    return k
