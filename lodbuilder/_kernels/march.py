"""Fast Marching in the voxel band and the farthest point ordering loops.

All lengths are in grid units (one unit = the voxel size h). Points are indexed in cell order
(sorted by the Morton key of their cell); ``cs[v]:cs[v + 1]`` are the points whose cell's lower corner
(anchor) is voxel v. Voxels with ``vcost == inf`` are corners kept only to find cells: the front never
enters them.

Per-voxel state: arrival time ``T`` (float32, only ever lowered), the rank of the sample that set it
(``vlab``) and a round stamp: ``stamp == 2 * rnd`` means "trial in round rnd", ``2 * rnd + 1``
"accepted in round rnd", anything smaller "known from an earlier round" (T and the stamp are packed
in one int64 per voxel, ``ts``: the march reads both of a neighbour at once). Nothing is re-initialised per
sample: a new sample marches only where it lowers ``T``. The front pops the smallest T first and,
among equal T (float32 ties happen), the smaller voxel index first: which of two tied voxels in line
is accepted first decides whether a neighbour's update is second order.

Seeding: the voxels within SEED_RADIUS of a new sample (less late in the ordering: see
:func:`seed_reach`), connected to its nearest voxel inside that
ball, that also *see* the sample get their exact distance, and so do the points of their cells. A
voxel sees the sample when the voxel one step back toward the sample's nearest voxel does (taken in
order of distance from it): the straight segment then stays in the band, so no exact distance is given across a gap
or through the inside of a fold. These voxels are frozen (marked accepted at once, so the march
never lowers them) and popped in order like the others.

Update: second-order upwind (one-sided differences (3 T - 4 T1 + T2) / 2 along an axis) where the
first and the next voxel upwind were both accepted in this round (so they hold this sample's field)
and the second is not above the first; first order otherwise and wherever the second-order solution
is not upwind (smaller than a value it used). A first-order
update may read a neighbour's trial value (an upper bound of its final value; the update is monotone
in its inputs, so this only lowers a voxel earlier, and it is updated again when that neighbour is
accepted); a second-order one only reads a known second neighbour.

Batches: a march of BATCH_SOURCES or more fronts kept apart (a tile's head seeds, timed seeds joining
at once) keeps its voxels in buckets of width BATCH_T instead of the heap, and marches the lowest
bucket's voxels at once, in voxel order (other marches pop one entry at a time, as above). Its fronts
take turns all over the band, and popped one by one each pop missed the caches (about 2.2 us a pop
with 300 fronts against 0.6 with one, the same voxels marched, on a loaded machine); in voxel order
neighbouring voxels of a front are marched together (1.1 us a pop with 300 fronts), and a bucket
costs no heap sift (a further 0.84-1.03 x, 0.9 x typically). A voxel of a batch may read a neighbour
of its batch not yet accepted (its trial value, an upper bound, as above), so values move a little:
0.1-0.6 % above the one-by-one march's on average, at single points up to 5 % below and 7 % above it.

Per-point state: ``dq`` = the smallest T[v] + |u - v| * cost over the marchable corners v of the
point's cell (or the exact distance near a sample), ``lq`` = the sample that achieved it, and the
candidate value ``val``: for the uniform metric the certified upper bound of the Euclidean distance
to the samples, min over time of max(dq, |u - u[sample lq]|); for a weighted metric the same with the
straight distance scaled by the mean cost of its two ends (so a constant cost only scales radii).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import INLINE, JIT
from .grid import unmorton
from .heaps import (
    ITEM_MASK,
    bits_f32,
    check_maxheap,
    check_minheap,
    f32_bits,
    iheap_pop,
    iheap_push,
    maxheap_build,
    maxheap_decrease,
    maxheap_pop,
)
from .pieces import piece_tables, refresh_piece
from .tiled import stable_argsort
from .topology import _cell_key, anchor_of, cell_tables

SEED_RADIUS = 6.0  # voxels around a new sample that get their exact distance
SEED_SLACK = 1.75  # > sqrt(3): every corner of a cell holding a point within r of a sample is within r + this
SEED_QUEUE = 4096  # > the 905 voxel centres of a ball of radius 6
HALF = 8  # the ball's voxels lie within HALF of the sample's nearest voxel along each axis
CUBE = 2 * HALF + 1
NBUCKET = 8 * (HALF + 1) * 2  # eighths of a voxel up to beyond the ball's reach
BATCH_T = 0.5  # voxels (at the sources' cost): a march of fronts kept apart queues them in buckets this wide ...
BATCH_MAX = 1 << 16  # ... and marches up to this many of a bucket at once, in voxel order (see the module docstring) ...
BATCH_SOURCES = 16  # ... when it has at least this many fronts (with 3 a batch cost 1.1-1.25 x, with 10 0.85-0.97 x)
NBUCKETS = 1 << 12  # a batched march's buckets, in a ring: values up to this many batch_t above the lowest


_STAMP = np.int64(0xFFFFFFFF)
T_INF = np.int64(int(np.float32(np.inf).view(np.int32)) << 32)  # T = inf, stamp 0: a voxel not reached


@nb.njit(**JIT)
def _tval(e):  # pragma: no cover - compiled
    """The arrival time of a packed voxel state (float32 bits above the round stamp)."""
    return bits_f32(e >> 32)


@nb.njit(**JIT)
def _packed(t, st):  # pragma: no cover - compiled
    """The packed voxel state of arrival time t (float32, >= 0) and round stamp st (>= 0)."""
    return (f32_bits(t) << 32) | np.int64(st)


#: which corner (x + 2 y + 4 z) of the k-th cell of :func:`corner_voxels` v is
CORNER_OF = (0, 4, 2, 6, 1, 5, 3, 7)


@nb.njit(**INLINE)
def corner_voxels(nbr, v):  # pragma: no cover - compiled
    """The 8 voxels whose cells have voxel v as a corner: v, then its neighbours along -z, -y,
    -y-z, -x, -x-z, -x-y, -x-y-z (the k-th is 4 dx + 2 dy + dz steps down), -1 where the band has
    none (``nbr``: the -x, +x, -y, +y, -z, +z neighbour table)."""
    w1 = np.int64(nbr[v, 4])
    w2 = np.int64(nbr[v, 2])
    w3 = np.int64(nbr[w2, 4]) if w2 >= 0 else np.int64(-1)
    w4 = np.int64(nbr[v, 0])
    w5 = np.int64(nbr[w4, 4]) if w4 >= 0 else np.int64(-1)
    w6 = np.int64(nbr[w4, 2]) if w4 >= 0 else np.int64(-1)
    w7 = np.int64(nbr[w6, 4]) if w6 >= 0 else np.int64(-1)
    return (np.int64(v), w1, w2, w3, w4, w5, w6, w7)


@nb.njit(**JIT)
def corner_cells(nbr, cellof, cmask):  # pragma: no cover - compiled
    """Fill ``cmask`` (uint8, one per voxel; at least as long as ``nbr``) with which of each voxel's
    8 cells hold points: bit k set when the k-th voxel of :func:`corner_voxels` exists and is a
    cell (``cellof >= 0``). The march and the seeding then skip a voxel's cells without walking
    to them: most voxels of a band lie off the surface, their 8 cells empty (57 % of an airborne
    tile's, 47 % of a sheet's), and each step of the walk is a cache miss."""
    for v in range(nbr.shape[0]):
        corners = corner_voxels(nbr, v)
        b = 0
        for k in range(8):
            w = corners[k]
            if w >= 0 and cellof[w] >= 0:
                b |= 1 << k
        cmask[v] = b


@nb.njit(**INLINE)  # (its one call site is the march's hottest loop: 15 % of the grid phase as a call)
def _update(a1, a2, b1, b2, c1, c2, f):  # pragma: no cover - compiled
    """Upwind solution of |grad T| = f from the three axes' (first, second) upwind values.

    ``x1`` is the smaller neighbour value along an axis (inf: none), ``x2`` the next value beyond it
    when the second-order difference may be used (inf: first order on that axis).
    """
    if b1 < a1:
        a1, a2, b1, b2 = b1, b2, a1, a2
    if c1 < b1:
        b1, b2, c1, c2 = c1, c2, b1, b2
        if b1 < a1:
            a1, a2, b1, b2 = b1, b2, a1, a2
    second = a2 < np.inf or b2 < np.inf or c2 < np.inf
    ff = f * f
    if second:
        sa = 0.0
        sb = 0.0
        sc = 0.0
        sol = np.inf
        ok = True
        for k in range(3):
            t1 = a1 if k == 0 else (b1 if k == 1 else c1)
            t2 = a2 if k == 0 else (b2 if k == 1 else c2)
            if t1 >= sol:  # this axis is not upwind of the solution
                break
            if t2 < np.inf:
                al = 2.25
                be = (4.0 * t1 - t2) / 3.0
            else:
                al = 1.0
                be = t1
            na = sa + al
            nb_ = sb + al * be
            nc = sc + al * be * be
            disc = nb_ * nb_ - na * (nc - ff)
            if disc < 0.0:
                ok = False
                break
            t = (nb_ + np.sqrt(disc)) / na
            if t < t1:
                ok = False
                break
            sa, sb, sc, sol = na, nb_, nc, t
        if ok and sol < np.inf:
            return sol
    # first order
    t = a1 + f
    if t <= b1:
        return t
    t = 0.5 * (a1 + b1 + np.sqrt(2.0 * ff - (a1 - b1) * (a1 - b1)))
    if t <= c1:
        return t
    s = a1 + b1 + c1
    q = a1 * a1 + b1 * b1 + c1 * c1
    return (s + np.sqrt(max(s * s - 3.0 * (q - ff), 0.0))) / 3.0


@nb.njit(**JIT)
def _norm(dx, dy, dz):  # pragma: no cover - compiled
    # helpers take scalars only: an array argument in a hot loop costs atomic reference counting
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@nb.njit(**JIT)
def _chord_ok(cx, cy, cz, c, sa, sb, ax, ay, az, bx, by, bz, slope):  # pragma: no cover - compiled
    """Whether the chord (cx, cy, cz) of length c between two points of thin parts (separations
    sa, sb; unit normals a, b, zero when unknown) is a fair surface distance."""
    if c >= sa or c >= sb:
        return False
    lim = slope * c
    return abs(cx * ax + cy * ay + cz * az) <= lim and abs(cx * bx + cy * by + cz * bz) <= lim


@nb.njit(**JIT)
def seed_scratch():  # pragma: no cover - compiled
    """Work arrays of the seeding, allocated once per ordering (not once per sample)."""
    return (
        np.empty(SEED_QUEUE, np.int32),
        np.empty(SEED_QUEUE, np.int64),
        np.empty(SEED_QUEUE, np.int64),
        np.empty(SEED_QUEUE, np.int64),
        np.empty(SEED_QUEUE, np.float64),
        np.full(CUBE * CUBE * CUBE, -1, np.int32),  # ball-local index of the voxels near v0
        np.zeros(SEED_QUEUE, np.bool_),
        np.empty(SEED_QUEUE, np.int32),
        np.zeros(NBUCKET, np.int64),
    )


@nb.njit(**INLINE)
def seed_reach(rad, cmin, weighted):  # pragma: no cover - compiled
    """The radius of the exact seeding of a sample entering at radius ``rad`` (grid units; least
    point cost ``cmin`` when ``weighted``): SEED_RADIUS, or less once every unordered point's value
    is at most ``rad``. A sample only lowers a point whose value dq (<= its candidate value <=
    ``rad``, the largest one) is above the point's distance to it (its weighted distance: at least
    cmin x the distance), so the points it can lower lie within rad (/ cmin); the corners of their
    cells lie within SEED_SLACK more, and they all get their exact distance from a ball of that
    radius as from the full one. Only voxels farther out, which give such points no value, are
    left to the march."""
    reach = rad / cmin if weighted else rad
    return min(np.float64(SEED_RADIUS), reach + SEED_SLACK)


@nb.njit(**JIT)
def _seed_sample(
    i, lb, mark, rnd, acc, u, keys, nbr, cs, cellof, vcost, pcost, weighted, foot, pnrm, slope, thin,
    ts, vlab, dq, lq, rank, dstamp, cmark, dirty, nd, hkv, hpos, n, scratch, reach, cmask,
):  # pragma: no cover - compiled
    """Seed the front of sample ``i`` (label ``lb``): exact distances in the ball of radius
    ``reach`` (at most SEED_RADIUS) around it (see the module docstring); returns the front heap's
    new size and the dirty count. ``cmask``: see :func:`corner_cells`."""
    qv, qx, qy, qz, qd, cube, vis, srt, nbk = scratch
    ci = 1.0
    if weighted:
        ci = pcost[i]
    # the sample's nearest voxel: a corner of its cell (all corners are voxels)
    a = anchor_of(cs, np.int64(i))
    v0 = a
    for ax in range(3):
        if u[i, ax] - np.floor(u[i, ax]) >= 0.5 and v0 >= 0:
            v0 = nbr[v0, 2 * ax + 1]
    if v0 < 0 or vcost[v0] == np.inf:
        v0 = -1  # not marchable: take the first marchable corner
        for c in range(8):
            w = a
            for ax in range(3):
                if (c >> ax) & 1 and w >= 0:
                    w = nbr[w, 2 * ax + 1]
            if w >= 0 and vcost[w] < np.inf:
                v0 = w
                break
    if v0 < 0:
        return n, nd
    x0, y0, z0 = unmorton(keys[v0])
    # the sample relative to v0 (all ball coordinates below are relative to v0)
    sx = u[i, 0] - x0
    sy = u[i, 1] - y0
    sz = u[i, 2] - z0
    # the marchable voxels within the reach connected to v0 inside the ball (breadth first;
    # ``cube`` maps the voxels near v0 to their place in the queue, -1 when not taken; a
    # neighbour's coordinates are its voxel's plus one step, no decoding)
    cube[HALF + CUBE * (HALF + CUBE * HALF)] = 0
    qv[0] = v0
    qx[0] = 0
    qy[0] = 0
    qz[0] = 0
    qn = 1
    qi = 0
    while qi < qn:
        v = qv[qi]
        vx, vy, vz = qx[qi], qy[qi], qz[qi]
        qi += 1
        for j in range(6):
            w = nbr[v, j]
            if w < 0 or qn == SEED_QUEUE or vcost[w] == np.inf:
                continue
            step = 2 * (j & 1) - 1
            x = vx + step if j < 2 else vx
            y = vy + step if (j >> 1) == 1 else vy
            z = vz + step if j >= 4 else vz
            cw = (x + HALF) + CUBE * ((y + HALF) + CUBE * (z + HALF))
            if cube[cw] >= 0:
                continue
            if _norm(sx - x, sy - y, sz - z) <= reach:
                cube[cw] = qn
                qv[qn] = w
                qx[qn] = x
                qy[qn] = y
                qz[qn] = z
                qn += 1
    # line of sight: in order of distance from v0, a voxel sees the sample when the voxel one
    # step back toward v0 (strictly nearer v0, so already decided) does: the straight segment
    # then stays in the band (no exact distance across a gap or through the inside of a fold)
    # (a counting sort in steps of 1/8 voxel: the step back is at least 0.13 nearer, so it
    # always falls in an earlier bucket)
    nbk[:] = 0
    for q in range(qn):
        qd[q] = _norm(np.float64(qx[q]), np.float64(qy[q]), np.float64(qz[q]))
        nbk[int(qd[q] * 8.0) + 1] += 1
    for b in range(1, NBUCKET):
        nbk[b] += nbk[b - 1]
    for q in range(qn):
        b = int(qd[q] * 8.0)
        srt[nbk[b]] = q
        nbk[b] += 1
    for t in range(qn):
        q = srt[t]
        v = qv[q]
        x, y, z = qx[q], qy[q], qz[q]
        if q == 0:
            ok = True
        else:
            # one step back toward v0 (the sample itself may lie just outside a one-sided band)
            d = qd[q]
            bx = int(np.floor(x - x / d + 0.5))
            by = int(np.floor(y - y / d + 0.5))
            bz = int(np.floor(z - z / d + 0.5))
            pq = cube[(bx + HALF) + CUBE * ((by + HALF) + CUBE * (bz + HALF))]
            ok = pq >= 0 and pq != q and vis[pq]
        if ok and thin:
            f = foot[v]
            ok = _chord_ok(
                u[f, 0] - u[i, 0], u[f, 1] - u[i, 1], u[f, 2] - u[i, 2],
                _norm(u[f, 0] - u[i, 0], u[f, 1] - u[i, 1], u[f, 2] - u[i, 2]), np.float32(np.inf),
                np.float32(np.inf),
                pnrm[f, 0], pnrm[f, 1], pnrm[f, 2], pnrm[i, 0], pnrm[i, 1], pnrm[i, 2], slope,
            )
        vis[q] = ok
        if not ok and q != 0:  # (v0 is seeded whatever the chord rule says: the sample reads its
            continue  # own distance from it; it lends its line of sight only where the rule holds)
        t_ = np.float32(_norm(sx - x, sy - y, sz - z) * 0.5 * (ci + vcost[v]))
        if t_ < _tval(ts[v]):
            ts[v] = _packed(t_, acc)  # exact: frozen (the march never lowers it), but still popped
            vlab[v] = lb
            n = iheap_push(hkv, hpos, n, t_, v)
        # the points of the 8 cells that have v as a corner get their exact distance (each
        # cell once per sample)
        bits = np.int64(cmask[v])
        if bits == 0:
            continue  # none of them holds a point
        corners = corner_voxels(nbr, v)
        for k in range(8):
            if not (bits >> k) & 1:
                continue
            w = corners[k]
            cell = cellof[w]
            if cmark[cell] == mark:
                continue
            cmark[cell] = mark
            for p in range(cs[w], cs[w + 1]):
                if rank[p] >= 0:
                    continue
                e = _norm(u[p, 0] - u[i, 0], u[p, 1] - u[i, 1], u[p, 2] - u[i, 2])
                if thin and not _chord_ok(
                    u[p, 0] - u[i, 0], u[p, 1] - u[i, 1], u[p, 2] - u[i, 2], e,
                    np.float32(np.inf), np.float32(np.inf), pnrm[p, 0], pnrm[p, 1], pnrm[p, 2], pnrm[i, 0], pnrm[i, 1],
                    pnrm[i, 2], slope,
                ):
                    continue
                if weighted:
                    e *= 0.5 * (pcost[p] + ci)
                if e < dq[p]:
                    dq[p] = e
                    lq[p] = lb
                    if dstamp[cell] != rnd:
                        dstamp[cell] = rnd
                        dirty[nd] = cell
                        nd += 1
    for q in range(qn):
        cube[(qx[q] + HALF) + CUBE * ((qy[q] + HALF) + CUBE * (qz[q] + HALF))] = -1
        vis[q] = False
    return n, nd


_LINK_LOW = np.int64(0xFFFFFFFF)


@nb.njit(**INLINE)
def _bucket_push(bhead, link, hkv, hpos, n, cur, v, t, inv_t):  # pragma: no cover - compiled
    """Queue voxel ``v`` of value ``t`` (float32) in a batched march: in bucket ``floor(t * inv_t)``
    (at least ``cur``, the lowest that may hold a voxel) when that is one of the NBUCKETS from
    ``cur`` on, else in the heap (``hkv``, ``hpos``, size ``n``: the overflow, moved to the buckets
    as they reach it). Returns (1 when v was not in a bucket before and is now, else 0; the heap's
    size).

    Each bucket is a doubly linked list of voxels: ``bhead[b % NBUCKETS]`` its first,
    ``link[v]`` the next (low 32 bits) and the previous (high 32 bits) voxel, each plus one (0:
    none). ``hpos[v]``: v's position in the heap (>= 0), -1 when v is not queued, -2 while it waits
    in the batch being marched (its lowered value is read when it is marched: it is not queued
    again), -3 - k in bucket slot k. A voxel is queued at most once, as in the heap alone."""
    s = np.int64(hpos[v])
    if s == -2:
        return 0, n
    if s >= 0:
        return 0, iheap_push(hkv, hpos, n, t, v)  # (lowered in the heap)
    b = np.int64(np.float64(t) * inv_t)
    if b < cur:
        b = cur  # (an update below the current bucket: marched with its next batch)
    elif b >= cur + NBUCKETS:
        return 0, iheap_push(hkv, hpos, n, t, v)  # (not in a bucket: one is only ever lowered)
    code = -3 - (b & (NBUCKETS - 1))
    if s == code:
        return 0, n
    queued = 1
    if s <= -3:  # moved down from bucket slot -3 - s
        queued = 0
        nx = (link[v] & _LINK_LOW) - 1
        pv = (link[v] >> 32) - 1
        if pv >= 0:
            link[pv] = (link[pv] & ~_LINK_LOW) | (nx + 1)
        else:
            bhead[-3 - s] = nx
        if nx >= 0:
            link[nx] = (link[nx] & _LINK_LOW) | ((pv + 1) << 32)
    slot = -3 - code
    nx = bhead[slot]
    link[v] = nx + 1  # (no previous: the bucket's new first voxel)
    if nx >= 0:
        link[nx] = (link[nx] & _LINK_LOW) | ((v + 1) << 32)
    bhead[slot] = v
    hpos[v] = code
    return queued, n


@nb.njit(**INLINE)
def _bucket_take(bhead, link, hpos, cur, batch):  # pragma: no cover - compiled
    """Move up to ``batch.shape[0]`` voxels of bucket ``cur`` into ``batch`` (their hpos -2);
    returns how many."""
    slot = cur & (NBUCKETS - 1)
    v = bhead[slot]
    m = 0
    while v >= 0 and m < batch.shape[0]:
        batch[m] = v
        m += 1
        hpos[v] = -2
        v = (link[v] & _LINK_LOW) - 1
    bhead[slot] = v
    if v >= 0:
        link[v] = link[v] & _LINK_LOW
    return m


@nb.njit(**JIT)
def march_round(
    src, lab, rnd, u, keys, nbr, cs, cellof, near, vcost, pcost, weighted, foot, pnrm, slope,
    ts, vlab, dq, lq, rank, dstamp, cmark, dirty, nd, hkv, hpos, scratch, debug, mark0, reach, cmask, apart,
    batch_t,
):  # pragma: no cover - compiled
    """Propagate the front of sources ``src`` (point indices) labelled ``lab + s`` where it lowers T
    (exact distances within ``reach`` of each source: see :func:`seed_reach`).
    ``mark0 + s`` marks the cells seeded from source s (unique over the ordering: ``rnd * len(src)``
    for one source a round, negative for the bulk rounds of :func:`grid_loop`).

    Updates dq/lq of points near lowered voxels and appends their cells to ``dirty``; returns the
    new count of dirty cells and the number of pops. Where sheets come close (``pnrm``: per point
    normals, zero elsewhere; a single row when there is no thin part; ``foot``: each voxel's nearest
    point), a straight distance is exact only along a chord within ``slope`` of both ends' sheets
    (around a tight fold the chord is much shorter than the surface).

    With ``apart`` (several sources joining at once), each source's front is marched apart from the
    others in the one march: an update reads only the neighbours its own front holds (its label),
    as one march per source would, and a voxel keeps the smallest of the fronts' values. An update
    that mixes two fronts where they meet gives values that are neither front's: on a 1M-point sheet
    in 16 (64) tiles the levels after the head covered 1.054 (1.072) x the in-memory build, against
    1.030 (1.052) with one march per seed and with the fronts apart. Such a march marches its voxels
    in buckets of width ``batch_t`` (see the module docstring; 0: one at a time from the heap, as a
    single source's).
    """
    trial = np.int32(2 * rnd)
    acc = np.int32(2 * rnd + 1)
    thin = pnrm.shape[0] == u.shape[0] and foot.shape[0] == keys.shape[0]
    exact_seeds = not thin and not weighted  # a seeded voxel's points hold their exact distance
    n = np.int64(0)  # not a literal: a literal argument compiles another version of a helper
    for s in range(src.shape[0]):
        n, nd = _seed_sample(
            np.int64(src[s]), np.int32(lab + s), np.int32(mark0 + s), rnd, acc, u, keys, nbr, cs,
            cellof, vcost, pcost, weighted, foot, pnrm, slope, thin, ts, vlab, dq, lq, rank, dstamp,
            cmark, dirty, nd, hkv, hpos, n, scratch, reach, cmask,
        )
    pops = 0
    # the voxels popped and not yet marched (a batch: one voxel, or in a batched march the voxels of
    # the lowest bucket of width ``batch_t``, marched in voxel order; see the module docstring)
    batched = apart and batch_t > 0.0 and src.shape[0] >= BATCH_SOURCES
    batch = np.empty(BATCH_MAX if batched else 1, np.int64)
    # a batched march's queue: buckets of voxels (see :func:`_bucket_push`) instead of the heap
    bhead = np.full(NBUCKETS if batched else 0, -1, np.int64)
    link = np.empty(ts.shape[0] if batched else 0, np.int64)
    inv_t = 0.0
    if batched:
        # buckets of batch_t voxels at the fronts' cost: the sources' mean cost (a weighted march's
        # values scale with its cost; batch_t units regardless of it batched half the band at
        # costs of 0.001 and nothing at costs of 1,000)
        cbar = 1.0
        if weighted:
            cbar = 0.0
            for s in range(src.shape[0]):
                cbar += pcost[src[s]]
            cbar /= src.shape[0]
        inv_t = 1.0 / (batch_t * cbar)
    cur = np.int64(0)  # the lowest bucket that may hold a voxel
    nq = 0  # voxels in the buckets (see _bucket_push)
    if batched and n > 0:
        # the seeded voxels: from the heap to the buckets at once when the buckets reach them all
        # (their values are within the seeding's reach; else they move as the buckets reach them)
        cur = np.int64(np.float64(_tval(hkv[0])) * inv_t)
        top = 0.0
        for q in range(n):
            top = max(top, np.float64(_tval(hkv[q])))
        if np.int64(top * inv_t) < cur + NBUCKETS:
            for q in range(n):
                e = hkv[q]
                v = np.int64(e & ITEM_MASK)
                hpos[v] = -1
                qq, _ = _bucket_push(bhead, link, hkv, hpos, np.int64(0), cur, v, _tval(e), inv_t)
                nq += qq
            n = 0
    nbat = 0
    bi = 0
    while True:
        if bi == nbat:
            bi = 0
            nbat = 0
            if batched:
                if nq == 0:
                    if n == 0:
                        break
                    cur = max(cur, np.int64(np.float64(_tval(hkv[0])) * inv_t))
                # the heap's voxels that the buckets reach move to them
                while n > 0 and np.int64(np.float64(_tval(hkv[0])) * inv_t) < cur + NBUCKETS:
                    t0, v0, n = iheap_pop(hkv, hpos, n)
                    q, n = _bucket_push(bhead, link, hkv, hpos, n, cur, np.int64(v0), t0, inv_t)
                    nq += q
                while bhead[cur & (NBUCKETS - 1)] < 0:
                    cur += 1
                nbat = _bucket_take(bhead, link, hpos, cur, batch)
                nq -= nbat
                if nbat > 1:
                    # (not np.sort: see the JIT options in __init__, numba's sorts in one kernel only)
                    batch[:nbat] = batch[:nbat][stable_argsort(batch[:nbat])]
            else:
                if n == 0:
                    break
                if debug and not check_minheap(hkv, hpos, n):
                    return nd, -1  # the front heap is broken (no raise: it would compile exception code)
                # the smallest entry (iheap_pop written out: as an inlined helper it cost six
                # atomic reference counts per pop, 4 % of the grid phase)
                e0 = hkv[0]
                v = np.int64(e0 & ITEM_MASK)
                hpos[v] = -1
                n -= 1
                if n > 0:
                    last = hkv[n]
                    i = np.int64(0)
                    while True:
                        c = 4 * i + 1  # (a 4-ary heap: see .heaps)
                        if c >= n:
                            break
                        ec = hkv[c]
                        for cc in range(c + 1, min(c + 4, n)):
                            if hkv[cc] < ec:
                                c = cc
                                ec = hkv[cc]
                        if ec > last:
                            break
                        hkv[i] = ec
                        hpos[ec & ITEM_MASK] = i
                        i = c
                    hkv[i] = last
                    hpos[last & ITEM_MASK] = i
                batch[0] = v
                nbat = 1
        v = batch[bi]
        bi += 1
        if batched:
            hpos[v] = -1  # (marched now: see _bucket_push)
        ev = ts[v]
        ts[v] = (ev & ~_STAMP) | np.int64(acc)
        pops += 1
        tv = np.float64(_tval(ev))
        lv = vlab[v]
        # seeded this round (frozen at its exact distance): the seeding gave every point of its
        # 8 cells its exact distance to the sample, which no estimate below undercuts (a quarter
        # of the pops, nearly all of them late in the ordering): only its neighbours are left
        bits = np.int64(cmask[v])  # which of its 8 cells hold points (:func:`corner_cells`)
        if bits != 0 and not (exact_seeds and (ev & _STAMP) == acc):
            gn = -1.0  # the front's direction at v: computed when a point first needs it
            gx = 0.0
            gy = 0.0
            gz = 0.0
            sv = src[lv - lab]  # the sample whose front this is (only this round's voxels pop)
            csv = 1.0
            if weighted:
                csv = pcost[sv]
            # points of the 8 cells that have v as a corner
            corners = corner_voxels(nbr, v)
            for k in range(8):
                if not (bits >> k) & 1:
                    continue
                w = corners[k]
                cell = cellof[w]
                corner = CORNER_OF[k]  # v is this corner of the cell
                p0 = cs[w]
                # v's coordinates: the cell's anchor (the floor of any of its points' coordinates)
                # plus the corner (reading v's key instead was a cache miss per pop)
                cx = np.floor(u[p0, 0]) + (corner & 1)
                cy = np.floor(u[p0, 1]) + ((corner >> 1) & 1)
                cz = np.floor(u[p0, 2]) + (corner >> 2)
                for p in range(p0, cs[w + 1]):
                    if rank[p] >= 0:
                        continue
                    ex = u[p, 0] - cx
                    ey = u[p, 1] - cy
                    ez = u[p, 2] - cz
                    if near[p] == corner and gn < 0.0:
                        # the front's direction at v (upwind differences; upwind neighbours
                        # are known)
                        for ax in range(3):
                            na = nbr[v, 2 * ax]
                            nb_ = nbr[v, 2 * ax + 1]
                            ta = np.float64(_tval(ts[na])) if na >= 0 else np.inf
                            tb = np.float64(_tval(ts[nb_])) if nb_ >= 0 else np.inf
                            g = 0.0
                            if ta < tb and ta < tv:
                                g = tv - ta
                            elif tb < tv:
                                g = tb - tv
                            if ax == 0:
                                gx = g
                            elif ax == 1:
                                gy = g
                            else:
                                gz = g
                        gn = _norm(gx, gy, gz)
                        if gn > 0.0:
                            gx /= gn
                            gy /= gn
                            gz /= gn
                    if gn > 0.0 and near[p] == corner:
                        # v is the point's nearest marchable voxel: first-order Taylor along
                        # the front, never below the straight distance to the sample (a lower
                        # bound)
                        dd = gx * ex + gy * ey + gz * ez
                        if weighted:
                            dd *= pcost[p]
                        dd += tv
                        e = _norm(u[p, 0] - u[sv, 0], u[p, 1] - u[sv, 1], u[p, 2] - u[sv, 2])
                        if weighted:
                            e *= min(pcost[p], csv)
                        if e > dd:
                            dd = e
                    else:
                        dd = _norm(ex, ey, ez)  # an upper bound
                        if weighted:
                            dd *= pcost[p]
                        dd += tv
                    # written out as in _seed_sample: the same lines as an inlined helper that takes
                    # the arrays made the grid phase of 1M points 3.3 -> 5.1 s (reference counting)
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
            if m < 0:
                continue
            em = ts[m]
            if (em & _STAMP) == acc:
                continue
            fm = vcost[m]
            if fm == np.inf:
                continue
            # per axis: the smaller neighbour value, and the next one beyond it when it may
            # serve a second-order difference (written out: passing the state to a helper here
            # costs atomic reference counting)
            for ax in range(3):
                na = nbr[m, 2 * ax]
                nb_ = nbr[m, 2 * ax + 1]
                ea = T_INF
                eb = T_INF
                if na >= 0 and not (apart and vlab[na] != lv):
                    ea = ts[na]
                if nb_ >= 0 and not (apart and vlab[nb_] != lv):
                    eb = ts[nb_]
                ta = np.float64(_tval(ea))
                tb = np.float64(_tval(eb))
                if ta <= tb:
                    n1 = na
                    t1 = ta
                    e1 = ea
                    dj = 2 * ax
                else:
                    n1 = nb_
                    t1 = tb
                    e1 = eb
                    dj = 2 * ax + 1
                t2 = np.inf
                if t1 < np.inf and (e1 & _STAMP) == acc:
                    n2 = nbr[n1, dj]
                    if n2 >= 0 and not (apart and vlab[n2] != lv):
                        e2 = ts[n2]
                        if (e2 & _STAMP) == acc:
                            tt = np.float64(_tval(e2))
                            if tt <= t1:
                                t2 = tt
                if ax == 0:
                    a1 = t1
                    a2 = t2
                elif ax == 1:
                    b1 = t1
                    b2 = t2
                else:
                    c1 = t1
                    c2 = t2
            tn = np.float32(_update(a1, a2, b1, b2, c1, c2, np.float64(fm)))
            if tn < _tval(em):
                ts[m] = _packed(tn, trial)
                vlab[m] = lv
                if batched:
                    q, n = _bucket_push(bhead, link, hkv, hpos, n, cur, m, tn, inv_t)
                    nq += q
                else:
                    n = iheap_push(hkv, hpos, n, tn, m)
    return nd, pops


@nb.njit(**JIT)
def grid_state(u, keys, cs, k_max, tseed, piece, npiece):  # pragma: no cover - compiled
    """The state of a grid-phase ordering before its first point (:func:`grid_loop` goes on from
    it): a tuple of arrays, element 26 the counters (points ordered, candidate heap size,
    piece refreshes, pops), element 27 the voxels' occupied cells (:func:`corner_cells`; filled
    by the first :func:`grid_loop`, which sets its last byte)."""
    m = u.shape[0]
    nv = keys.shape[0]
    cellv, cellof = cell_tables(cs)
    ncell = cellv.shape[0]
    val = np.full(m, np.inf)
    ckey = np.full(ncell, np.inf)  # heap order
    heap = np.arange(ncell).astype(np.int32)
    hpos = np.empty(ncell, np.int32)
    maxheap_build(ckey, heap, hpos, ncell)
    for j in range(tseed.shape[0]):
        val[tseed[j]] = -1.0  # never a candidate
    pstart, pidx, pbox = piece_tables(piece, npiece, u)
    ctr = np.zeros(5, np.int64)  # k, hn, nref, pops, sources marched in bulk
    ctr[1] = ncell
    return (
        np.full(nv, T_INF, np.int64),  # 0 ts: packed voxel state, arrival time T and round stamp
        np.full(nv, -1, np.int32),  # 1 vlab
        cellv, cellof,  # 2, 3
        np.full(m, np.inf), val, np.full(m, -1, np.int32), np.full(m, -1, np.int32),  # 4 dq, 5 val, 6 lq, 7 rank
        np.full(ncell, -1, np.int32), np.full(ncell, -1, np.int32), np.empty(ncell, np.int32),  # 8 dstamp, 9 cmark, 10 dirty
        ckey, heap, hpos,  # 11, 12, 13
        np.empty(nv, np.int64), np.full(nv, -1, np.int32),  # 14 hkv, 15 hpos_v: the front heap
        np.empty(k_max, np.int32), np.empty(k_max, np.float64), np.empty(k_max, np.int32),  # 16 order, radius, parent
        np.zeros(npiece, np.bool_), np.zeros(npiece, np.int64), np.full(npiece, np.inf),  # 19 awake, psync, pmax
        pstart, pidx, pbox, np.full(ncell, -1, np.int64),  # 22, 23, 24, 25 pmark
        ctr,  # 26
        np.zeros(nv + 1, np.uint8),  # 27 cmask (+ a flag: filled)
    )


@nb.njit(**JIT)
def grid_phase(
    u, keys, nbr, cs, near, vcost, pcost, weighted, foot, pnrm, slope, seeds, k_max, rho_stop,
    r_stop, debug, tseed, tkey, tpos, piece, npiece,
):  # pragma: no cover - compiled
    """Farthest point ordering under the band metric until the radius falls below ``r_stop``.

    Returns (order, radius, parent, k, val, lq, rank, pops) where ``k`` points are ordered; the other
    points' ``val``/``lq`` seed the Euclidean tail. ``rho_stop < 0`` means no density stop. With
    ``debug`` the heaps are checked after every operation; pops is -1 (front heap) or -2
    (candidate heap) when one is found broken.

    Timed seeds: ``tseed`` (points, none of them a seed, by non-increasing ``tkey``, grid units) are
    never candidates; each joins the ordering (radius: its key) as soon as the largest candidate
    distance is at most its key, and its front is marched like a sample's. ``tpos[0]`` counts the timed seeds taken
    (the tail goes on from there).

    Pieces (``piece``: the band piece of every point, ``npiece`` of them): a piece no sample has
    reached is dormant; its points' values are Euclidean distances to the samples, refreshed
    lazily (:mod:`.pieces`) when one of them reaches the top of the candidate heap. When a
    refreshed point is still the farthest, it enters with its exact Euclidean distance as radius
    and the nearest sample as parent, and wakes its piece: from then on the piece's points are
    lowered by the march (along the surface) from its samples. Only the seeds have radius inf.
    Before returning, every dormant piece is refreshed (the tail and the stop radius see exact
    values).
    """
    st = grid_state(u, keys, cs, k_max, tseed, piece, npiece)
    bad = grid_loop(
        u, keys, nbr, cs, near, vcost, pcost, weighted, foot, pnrm, slope, seeds, k_max, rho_stop,
        r_stop, debug, tseed, tkey, tpos, piece, npiece, st, False,
    )
    ctr = st[26]
    if bad < 0:
        return st[16], st[17], st[18], ctr[0], st[5], st[6], st[7], bad  # debug: a broken heap
    grid_wake_all(u, cs, pcost, weighted, npiece, st)
    return st[16], st[17], st[18], ctr[0], st[5], st[6], st[7], ctr[3]


@nb.njit(**JIT)
def grid_wake_all(u, cs, pcost, weighted, npiece, st):  # pragma: no cover - compiled
    """Refresh every dormant piece of state ``st``: exact values for the tail and the stop radius."""
    cellv, cellof, val, lq, rank = st[2], st[3], st[5], st[6], st[7]
    ckey, heap, hpos, order = st[11], st[12], st[13], st[16]
    awake, psync, pmax, pstart, pidx, pbox, pmark, ctr = st[19], st[20], st[21], st[22], st[23], st[24], st[25], st[26]
    cmin = 1.0
    if weighted:
        cmin = pcost.min()
    k = np.int64(ctr[0])
    hn = np.int64(ctr[1])
    nref = ctr[2]
    for c in range(npiece):
        if not awake[c] and psync[c] < k:
            refresh_piece(
                c, k, order, u, val, lq, rank, pstart, pidx, pbox, psync, pmax, weighted, pcost,
                cmin, cs, cellv, cellof, ckey, heap, hpos, hn, pmark, np.int64(nref),
            )
            nref += 1
    ctr[2] = nref


@nb.njit(**JIT)
def grid_loop(
    u, keys, nbr, cs, near, vcost, pcost, weighted, foot, pnrm, slope, seeds, k_max, rho_stop,
    r_stop, debug, tseed, tkey, tpos, piece, npiece, st, bulk,
):  # pragma: no cover - compiled
    """The loop of :func:`grid_phase` on state ``st`` (:func:`grid_state`), from where it stopped
    until ``k_max`` points, ``rho_stop`` or ``r_stop``: stopping and going on with the same
    arguments orders as one call does. With ``bulk``, the timed seeds due at once (key at least the
    largest candidate distance) join together and their fronts are marched as one (one march over
    the band instead of one each; the values are the same kind of upper bounds, not the same
    numbers). Returns 0, or -1 / -2 when a debug check found the front / candidate heap broken."""
    ts, vlab, cellv, cellof, dq, val, lq, rank = st[0], st[1], st[2], st[3], st[4], st[5], st[6], st[7]
    dstamp, cmark, dirty, ckey, heap, hpos, hkv, hpos_v = st[8], st[9], st[10], st[11], st[12], st[13], st[14], st[15]
    order, radius, parent, awake, psync, pmax = st[16], st[17], st[18], st[19], st[20], st[21]
    pstart, pidx, pbox, pmark, ctr, cmask = st[22], st[23], st[24], st[25], st[26], st[27]
    nv = cmask.shape[0] - 1
    if cmask[nv] == 0:  # (once per ordering: grid_loop may be called again on the same state)
        corner_cells(nbr, cellof, cmask)
        cmask[nv] = 1
    src = np.empty(1, np.int32)
    scratch = seed_scratch()
    nd0 = np.int64(0)
    k = np.int64(ctr[0])
    hn = np.int64(ctr[1])
    nref = ctr[2]
    pops = ctr[3]
    nseed = seeds.shape[0]
    nt = tseed.shape[0]
    cmin = 1.0
    if weighted:
        cmin = pcost.min()
    bad = 0
    while k < k_max:
        if k < nseed and nseed - k > 1 and k_max >= nseed and not weighted:
            # the seeds (radius inf, all in the set before any candidate) marched together: one
            # march over the band instead of one each, which re-pops most voxels about ln(seeds)
            # times (a tile's 113-132 head seeds: 74 % of its grid phase's pops). Not for a weighted
            # metric: where two seeds' fronts meet, one march (their fronts mixed, and apart too)
            # keeps values a little above those of one march per seed, and the density floor's
            # promise (its first weighted radius at most rho0) needs the latter's (test_adaptive:
            # 4.03 against 4.0 with the fronts mixed; apart, it fails as well)
            nd, pp = _bulk_seeds(
                k, nseed, seeds, u, keys, nbr, cs, cellv, cellof, near, vcost, pcost, weighted, foot, pnrm, slope,
                ts, vlab, dq, val, lq, rank, dstamp, cmark, dirty, hkv, hpos_v, scratch, order, radius, parent,
                awake, piece, ctr, cmask, ckey, heap, hpos, hn,
            )
            k = np.int64(nseed)
            pops += pp
            _lower_dirty(nd, dirty, cellv, cs, rank, dq, val, order, lq, u, weighted, pcost, ckey, heap, hpos, hn)
            while hn > 0 and ckey[0] < 0.0:
                hn = maxheap_pop(ckey, heap, hpos, hn)
            continue
        if k < nseed:
            i = seeds[k]
            rad = np.inf
            par = -1
            ci = cellof[anchor_of(cs, np.int64(i))]
        else:
            if hn == 0:
                break
            top = heap[0]
            kk = ckey[0]
            timed = tpos[0] < nt and tkey[tpos[0]] >= kk and tkey[tpos[0]] >= r_stop and tkey[tpos[0]] > rho_stop
            if not timed and (kk < 0.0 or kk <= rho_stop or kk < r_stop):
                break
            if timed and bulk:
                k, nd, pp = _bulk_timed(
                    k, k_max, max(kk, r_stop), rho_stop, tseed, tkey, tpos, u, keys, nbr, cs, cellof, near, vcost, pcost, weighted, foot,
                    pnrm, slope, ts, vlab, dq, lq, rank, dstamp, cmark, dirty, hkv, hpos_v, scratch, order, radius,
                    parent, awake, piece, ctr, cmask,
                )
                pops += pp
                _lower_dirty(nd, dirty, cellv, cs, rank, dq, val, order, lq, u, weighted, pcost, ckey, heap, hpos, hn)
                while hn > 0 and ckey[0] < 0.0:
                    hn = maxheap_pop(ckey, heap, hpos, hn)
                continue
            if timed:
                i = tseed[tpos[0]]
                rad = tkey[tpos[0]]
                tpos[0] += 1
                par = -1  # not chosen by this ordering: no parent
                ci = cellof[anchor_of(cs, np.int64(i))]
            else:
                w = cellv[top]
                i = -1
                best = -1.0
                for p in range(cs[w], cs[w + 1]):
                    if rank[p] < 0 and val[p] > best:
                        best = val[p]
                        i = p
                if i < 0:  # only timed seeds left in the cell (its key was never refreshed)
                    maxheap_decrease(ckey, heap, hpos, top, -1.0, hn)
                    while hn > 0 and ckey[0] < 0.0:
                        hn = maxheap_pop(ckey, heap, hpos, hn)
                    continue
                c = piece[i]
                if not awake[c] and psync[c] < k:  # a dormant piece: its values may be stale
                    refresh_piece(
                        c, k, order, u, val, lq, rank, pstart, pidx, pbox, psync, pmax, weighted, pcost,
                        cmin, cs, cellv, cellof, ckey, heap, hpos, hn, pmark, np.int64(nref),
                    )
                    nref += 1
                    while hn > 0 and ckey[0] < 0.0:
                        hn = maxheap_pop(ckey, heap, hpos, hn)
                    continue
                rad = val[i]
                par = lq[i]
                ci = top
        rank[i] = k
        order[k] = i
        radius[k] = rad
        parent[k] = par
        awake[piece[i]] = True
        # an exhausted cell (key -1) sinks and is dropped when it reaches the top
        maxheap_decrease(ckey, heap, hpos, ci, _cell_key(np.int64(ci), cellv, cs, rank, val), hn)
        src[0] = i
        nd, pp = march_round(
            src, np.int64(k), np.int64(k + 1), u, keys, nbr, cs, cellof, near, vcost, pcost, weighted, foot, pnrm, slope,
            ts, vlab, dq, lq, rank, dstamp, cmark, dirty, nd0, hkv, hpos_v, scratch, debug, np.int64(k + 1),
            seed_reach(rad, cmin, weighted), cmask, False, 0.0,
        )
        if pp < 0:
            bad = -1  # debug: a broken heap
            break
        pops += pp
        _lower_dirty(nd, dirty, cellv, cs, rank, dq, val, order, lq, u, weighted, pcost, ckey, heap, hpos, hn)
        # drop exhausted cells from the top
        while hn > 0 and ckey[0] < 0.0:
            hn = maxheap_pop(ckey, heap, hpos, hn)
        if debug and not check_maxheap(ckey, heap, hpos, hn):
            bad = -2  # debug: a broken heap
            break
        k += 1
    ctr[0] = k
    ctr[1] = hn
    ctr[2] = nref
    ctr[3] = pops
    return bad


@nb.njit(**JIT)
def _lower_dirty(
    nd, dirty, cellv, cs, rank, dq, val, order, lq, u, weighted, pcost, ckey, heap, hpos, hn,
):  # pragma: no cover - compiled
    """The candidate values of the unordered points of the ``nd`` dirty cells after a march, and
    their cells' keys (after each sample of :func:`grid_loop` and each bulk march)."""
    for j in range(nd):
        cc = dirty[j]
        w = cellv[cc]
        best = -1.0
        for p in range(cs[w], cs[w + 1]):
            if rank[p] >= 0:
                continue
            if dq[p] < val[p]:  # (else max(dq, e) cannot lower val)
                s = order[lq[p]]
                e = _norm(u[p, 0] - u[s, 0], u[p, 1] - u[s, 1], u[p, 2] - u[s, 2])
                if weighted:
                    e *= 0.5 * (pcost[p] + pcost[s])
                cand = dq[p] if dq[p] > e else e
                if cand < val[p]:
                    val[p] = cand
            if val[p] > best:
                best = val[p]
        # maxheap_decrease(ckey, heap, hpos, cc, best, hn) written out: an inlined helper that
        # takes arrays costs an atomic increment and decrement per array and call (numba's
        # reference counts), here per dirty cell
        q = np.int64(hpos[cc])
        if q < 0:
            continue
        it = heap[q]
        while True:
            c = 4 * q + 1
            if c >= hn:
                break
            bc = c
            for c2 in range(c + 1, min(c + 4, hn)):
                if ckey[c2] > ckey[bc] or (ckey[c2] == ckey[bc] and heap[c2] < heap[bc]):
                    bc = c2
            if ckey[bc] < best or (ckey[bc] == best and heap[bc] > it):
                break
            ckey[q] = ckey[bc]
            heap[q] = heap[bc]
            hpos[heap[q]] = q
            q = bc
        ckey[q] = best
        heap[q] = it
        hpos[it] = q


@nb.njit(**JIT)
def _bulk_seeds(
    k, nseed, seeds, u, keys, nbr, cs, cellv, cellof, near, vcost, pcost, weighted, foot, pnrm, slope,
    ts, vlab, dq, val, lq, rank, dstamp, cmark, dirty, hkv, hpos_v, scratch, order, radius, parent, awake, piece,
    ctr, cmask, ckey, heap, hpos, hn,
):  # pragma: no cover - compiled
    """Order the seeds from position ``k`` on (radius inf, no parent) and march their fronts
    together (see :func:`grid_loop`); returns the dirty cells' count and the pops."""
    src = seeds[k:nseed].astype(np.int32)
    nd, pp = _join_in_bulk(
        k, src, np.full(src.shape[0], np.inf), u, keys, nbr, cs, cellof, near, vcost, pcost, weighted, foot, pnrm,
        slope, ts, vlab, dq, lq, rank, dstamp, cmark, dirty, hkv, hpos_v, scratch, order, radius, parent, awake,
        piece, ctr, cmask,
    )
    for s in range(src.shape[0]):  # their cells' keys (the march reads no key, nor val)
        ci = cellof[anchor_of(cs, np.int64(src[s]))]
        maxheap_decrease(ckey, heap, hpos, ci, _cell_key(np.int64(ci), cellv, cs, rank, val), hn)
    return nd, pp


@nb.njit(**JIT)
def _bulk_timed(
    k, k_max, kk, rho_stop, tseed, tkey, tpos, u, keys, nbr, cs, cellof, near, vcost, pcost, weighted, foot, pnrm, slope,
    ts, vlab, dq, lq, rank, dstamp, cmark, dirty, hkv, hpos_v, scratch, order, radius, parent, awake, piece, ctr,
    cmask,
):  # pragma: no cover - compiled
    """Order the timed seeds due at once (key >= ``kk``) from position ``k`` on and march their
    fronts together (see :func:`grid_loop`); returns the new count, the dirty cells' count and the pops."""
    j0 = tpos[0]
    j1 = j0
    while j1 < tseed.shape[0] and tkey[j1] >= kk and tkey[j1] > rho_stop and k + (j1 - j0) < k_max:
        j1 += 1
    tpos[0] = j1
    nd, pp = _join_in_bulk(
        k, tseed[j0:j1].astype(np.int32), tkey[j0:j1], u, keys, nbr, cs, cellof, near, vcost, pcost, weighted, foot,
        pnrm, slope, ts, vlab, dq, lq, rank, dstamp, cmark, dirty, hkv, hpos_v, scratch, order, radius, parent, awake,
        piece, ctr, cmask,
    )
    return k + (j1 - j0), nd, pp


@nb.njit(**JIT)
def _join_in_bulk(
    k, src, rad, u, keys, nbr, cs, cellof, near, vcost, pcost, weighted, foot, pnrm, slope,
    ts, vlab, dq, lq, rank, dstamp, cmark, dirty, hkv, hpos_v, scratch, order, radius, parent, awake, piece, ctr,
    cmask,
):  # pragma: no cover - compiled
    """Order points ``src`` at positions ``k``, ``k + 1``, ... with radii ``rad`` and no parent, and
    march their fronts in one march, apart (the full seeding ball each; see :func:`march_round`);
    returns the dirty cells' count and the pops."""
    ns = src.shape[0]
    for s in range(ns):
        i = src[s]
        rank[i] = k + s
        order[k + s] = i
        radius[k + s] = rad[s]
        parent[k + s] = -1
        awake[piece[i]] = True
    # the seeded cells' marks: from -(1 + c + ns) to -(2 + c) (c: sources marched in bulk before,
    # ctr[4]), below every single round's mark (>= 1) and the cells' initial -1
    mark0 = -(np.int64(1) + ctr[4] + ns)
    ctr[4] += ns
    return march_round(
        src, np.int64(k), np.int64(k + 1), u, keys, nbr, cs, cellof, near, vcost, pcost, weighted, foot, pnrm, slope,
        ts, vlab, dq, lq, rank, dstamp, cmark, dirty, np.int64(0), hkv, hpos_v, scratch, False, mark0,
        np.float64(SEED_RADIUS), cmask, True, BATCH_T,
    )


@nb.njit(**JIT)
def multi_source_distance(
    u, keys, nbr, cs, near, vcost, pcost, weighted, foot, pnrm, slope, sources, apart=False, batch=BATCH_T,
):  # pragma: no cover - compiled
    """dq of every point for one march from all ``sources`` at once (for tests and analysis; with
    ``apart``, the sources' fronts kept apart as when several join an ordering at once, popped in
    batches of ``batch``: see :func:`march_round`)."""
    m = u.shape[0]
    nv = keys.shape[0]
    cellv, cellof = cell_tables(cs)
    ncell = cellv.shape[0]
    dq = np.full(m, np.inf)
    lq = np.full(m, -1, np.int32)
    rank = np.full(m, -1, np.int32)
    lab0 = np.int64(0)  # variables, not literals: literal arguments compile another version
    rnd1 = np.int64(1)
    nd0 = np.int64(0)
    cmask = np.empty(nv, np.uint8)
    corner_cells(nbr, cellof, cmask)
    nd, pops = march_round(
        sources, lab0, rnd1, u, keys, nbr, cs, cellof, near, vcost, pcost, weighted, foot, pnrm, slope,
        np.full(nv, T_INF, np.int64), np.full(nv, -1, np.int32),
        dq, lq, rank, np.full(ncell, -1, np.int32), np.full(ncell, -1, np.int32),
        np.empty(ncell, np.int32), nd0, np.empty(nv, np.int64),
        np.full(nv, -1, np.int32), seed_scratch(), False, rnd1 * sources.shape[0], np.float64(SEED_RADIUS), cmask, apart,
        np.float64(batch),
    )
    for s in range(sources.shape[0]):
        dq[sources[s]] = 0.0
    return dq, lq, pops
