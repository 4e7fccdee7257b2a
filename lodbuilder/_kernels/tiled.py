"""Kernels of the tiled (out-of-core) build: the seam-repairing k-way merge of tile orderings, the
exact covering pass over a tile and its halo, and the merge of per-tile covering events.

Spatial lookups use a hash grid of cubic cells (open addressing on the cell key, one linked list
of points per cell) that accepts insertions and is rebuilt when the cell size must change.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import JIT

# ------------------------------------------------------------------------------------ hash grid

_B = 21  # bits per axis of a cell key
_MASK = (1 << _B) - 1


@nb.njit(**JIT)
def cell_of(x, lo, cell):  # pragma: no cover - compiled
    c = np.int64(np.floor((x - lo) / cell))
    if c < 0:
        return np.int64(0)
    if c > _MASK:
        return np.int64(_MASK)
    return c


@nb.njit(**JIT)
def key3(cx, cy, cz):  # pragma: no cover - compiled
    return (cx << (2 * _B)) | (cy << _B) | cz


@nb.njit(**JIT)
def _hash(k, mask):  # pragma: no cover - compiled
    """Slot of cell key ``k``: MurmurHash3's 64-bit finaliser, every bit of the key mixed into the
    low bits the mask keeps. (A product's middle bits, as before, ignore the key's high bits, its
    x cell: the cells of a row along x shared one slot, 18-115 probes an insertion on a survey's
    seam points, where this takes 0.1-0.3.)"""
    x = np.uint64(k)
    x ^= x >> np.uint64(33)
    x *= np.uint64(0xFF51AFD7ED558CCD)
    x ^= x >> np.uint64(33)
    x *= np.uint64(0xC4CEB9FE1A85EC53)
    x ^= x >> np.uint64(33)
    return np.int64(x & np.uint64(mask))


@nb.njit(**JIT)
def grid_slot(tkeys, k, mask):  # pragma: no cover - compiled
    """Slot of cell key ``k`` in the table (the empty slot where it would go if absent)."""
    i = _hash(k, mask)
    while tkeys[i] != -1 and tkeys[i] != k:
        i = (i + 1) & mask
    return i


@nb.njit(**JIT)
def grid_insert(tkeys, thead, nxt, xyz, lo, cell, mask, j):  # pragma: no cover - compiled
    k = key3(cell_of(xyz[j, 0], lo[0], cell), cell_of(xyz[j, 1], lo[1], cell), cell_of(xyz[j, 2], lo[2], cell))
    s = grid_slot(tkeys, k, mask)
    if tkeys[s] == -1:
        tkeys[s] = k
        thead[s] = -1
    nxt[j] = thead[s]
    thead[s] = j


@nb.njit(**JIT)
def grid_rebuild(tkeys, thead, nxt, xyz, lo, cell, mask, n):  # pragma: no cover - compiled
    """The table emptied and points ``0 .. n-1`` inserted again (cells of size ``cell``), in the
    order of their slots: the table is written front to back (inserted one by one in their own
    order, each a cache miss, the rebuilds were most of the seam repair's time). A cell's chain
    may list its points in any order (its readers take the nearest)."""
    for s in range(tkeys.shape[0]):
        tkeys[s] = -1
    key = np.empty(n, np.int64)
    slot = np.empty(n, np.int64)
    for j in range(n):
        key[j] = key3(cell_of(xyz[j, 0], lo[0], cell), cell_of(xyz[j, 1], lo[1], cell), cell_of(xyz[j, 2], lo[2], cell))
        slot[j] = _hash(key[j], mask)
    for j in stable_argsort(slot):
        k = key[j]
        s = slot[j]
        while tkeys[s] != -1 and tkeys[s] != k:
            s = (s + 1) & mask
        if tkeys[s] == -1:
            tkeys[s] = k
            thead[s] = -1
        nxt[j] = thead[s]
        thead[s] = j


def table_size(n: int) -> int:
    """A power of two at least twice ``n`` (the hash table's load stays below one half)."""
    size = 1024
    while size < 2 * n:
        size *= 2
    return size


# ------------------------------------------------------------------------------------ heaps

@nb.njit(**JIT)
def _up(hkey, hitem, i):  # pragma: no cover - compiled
    """Max-heap sift up (ties: smaller item first)."""
    k = hkey[i]
    it = hitem[i]
    while i > 0:
        p = (i - 1) >> 1
        if hkey[p] > k or (hkey[p] == k and hitem[p] < it):
            break
        hkey[i] = hkey[p]
        hitem[i] = hitem[p]
        i = p
    hkey[i] = k
    hitem[i] = it


@nb.njit(**JIT)
def _down(hkey, hitem, i, n):  # pragma: no cover - compiled
    k = hkey[i]
    it = hitem[i]
    while True:
        c = 2 * i + 1
        if c >= n:
            break
        if c + 1 < n and (hkey[c + 1] > hkey[c] or (hkey[c + 1] == hkey[c] and hitem[c + 1] < hitem[c])):
            c += 1
        if hkey[c] < k or (hkey[c] == k and hitem[c] > it):
            break
        hkey[i] = hkey[c]
        hitem[i] = hitem[c]
        i = c
    hkey[i] = k
    hitem[i] = it


# ------------------------------------------------------------------------------------ seam merge

@nb.njit(**JIT)
def _nearest_other(ax, atile, tkeys, thead, nxt, mask, lo, cell, px, py, pz, ptile, radius):  # pragma: no cover
    """Distance from p to the nearest indexed point of another tile (or the head) within ``radius``
    (inf if none)."""
    best = np.inf
    cx0 = cell_of(px - radius, lo[0], cell)
    cx1 = cell_of(px + radius, lo[0], cell)
    cy0 = cell_of(py - radius, lo[1], cell)
    cy1 = cell_of(py + radius, lo[1], cell)
    cz0 = cell_of(pz - radius, lo[2], cell)
    cz1 = cell_of(pz + radius, lo[2], cell)
    for cx in range(cx0, cx1 + 1):
        for cy in range(cy0, cy1 + 1):
            for cz in range(cz0, cz1 + 1):
                s = grid_slot(tkeys, key3(cx, cy, cz), mask)
                if tkeys[s] == -1:
                    continue
                j = thead[s]
                while j >= 0:
                    if atile[j] != ptile:
                        dx = ax[j, 0] - px
                        dy = ax[j, 1] - py
                        dz = ax[j, 2] - pz
                        d = np.sqrt(dx * dx + dy * dy + dz * dz)
                        if d < best:
                            best = d
                    j = nxt[j]
    return best


@nb.njit(**JIT)
def seam_merge(bufs, bpos, blen, theap, tn, state, ax, atile, tkeys, thead, nxt,
               dheap_key, dheap_item, dpool, dtile, lo, alpha, out_g, out_key):  # pragma: no cover
    """Merge tile streams by descending key, repairing seams (see lodbuilder.build.tiled.merge).

    ``bufs`` (T, B, 6): per tile, rows (g, key, x, y, z, margin) of its stream; ``bpos``/``blen``
    the read position and length of each buffer. ``theap``/``tn``: max-heap (T, 2) of the tiles
    with rows left, by their next key (ties: lower tile); the caller refills the buffer of the top
    tile when asked (and pops the tile from the heap when its file is done, :func:`tile_pop`). ``state`` (float64):
    [n_out, n_acc, cell, n_dem, n_demoted_total, min_cell]. ``ax``/``atile``: accepted seam
    points (and the head, tile -1), indexed in the hash grid (``tkeys``/``thead``/``nxt``).
    ``dheap_*``: max-heap of demoted points (slots into ``dpool`` (D, 6) rows and ``dtile``).

    Returns (code, t): 0 = all merged; 1 = the buffer of tile t (at the top of the tile heap) needs
    a refill; 2 = the output buffer is full.
    """
    n_out = np.int64(state[0])
    n_acc = np.int64(state[1])
    cell = state[2]
    n_dem = np.int64(state[3])
    min_cell = state[5]
    mask = tkeys.shape[0] - 1
    cap = out_g.shape[0]
    while True:
        if n_out >= cap:
            state[0] = n_out
            state[1] = n_acc
            state[2] = cell
            state[3] = n_dem
            return 2, -1
        # next candidate: the top tile stream or the top demoted point
        ks = -1.0
        t = -1
        if tn > 0:
            t = np.int64(theap[0, 1])
            if bpos[t] >= blen[t]:  # exhausted buffer: a refill (the caller pops a finished tile)
                state[0] = n_out
                state[1] = n_acc
                state[2] = cell
                state[3] = n_dem
                return 1, t
            ks = bufs[t, bpos[t], 1]
        kd = dheap_key[0] if n_dem > 0 else -1.0
        if ks < 0.0 and kd < 0.0:
            break
        if ks >= kd:
            row = bufs[t, bpos[t]]
            g = np.int64(row[0])
            key = row[1]
            px = row[2]
            py = row[3]
            pz = row[4]
            margin = row[5]
            ptile = t
            bpos[t] += 1
            if bpos[t] < blen[t]:
                theap[0, 0] = bufs[t, bpos[t], 1]
                _tile_sift(theap, tn)
            # else: the stale key keeps tile t on top; the next turn asks for its refill
        else:
            slot = dheap_item[0]
            key = dheap_key[0]
            n_dem -= 1
            if n_dem > 0:
                dheap_key[0] = dheap_key[n_dem]
                dheap_item[0] = dheap_item[n_dem]
                _down(dheap_key, dheap_item, 0, n_dem)
            g = np.int64(dpool[slot, 0])
            px = dpool[slot, 2]
            py = dpool[slot, 3]
            pz = dpool[slot, 4]
            margin = dpool[slot, 5]
            ptile = dtile[slot]
        seam = margin < key
        if seam and alpha > 0.0 and np.isfinite(key):
            radius = alpha * key
            if key < 0.5 * cell and key > 0.0:
                cell = max(key, min_cell)
                grid_rebuild(tkeys, thead, nxt, ax, lo, cell, mask, n_acc)
            d = _nearest_other(ax, atile, tkeys, thead, nxt, mask, lo, cell, px, py, pz, ptile, radius)
            if d < radius:
                # too close to an accepted point of another tile: wait until the radius allows it
                slot = np.int64(state[4])
                state[4] += 1
                dpool[slot, 0] = g
                dpool[slot, 1] = d / alpha
                dpool[slot, 2] = px
                dpool[slot, 3] = py
                dpool[slot, 4] = pz
                dpool[slot, 5] = margin
                dtile[slot] = ptile
                dheap_key[n_dem] = d / alpha
                dheap_item[n_dem] = slot
                _up(dheap_key, dheap_item, n_dem)
                n_dem += 1
                continue
        out_g[n_out] = g
        out_key[n_out] = key
        n_out += 1
        if seam:
            ax[n_acc, 0] = px
            ax[n_acc, 1] = py
            ax[n_acc, 2] = pz
            atile[n_acc] = ptile
            if cell < np.inf:
                grid_insert(tkeys, thead, nxt, ax, lo, cell, mask, n_acc)
            n_acc += 1
    state[0] = n_out
    state[1] = n_acc
    state[2] = cell
    state[3] = n_dem
    return 0, -1


@nb.njit(**JIT)
def seam_links(xyz, key, tile, own, alpha, slack, lo, min_cell, tkeys, thead, nxt, linked):  # pragma: no cover
    """Mark the seam points that can meet another tile's (see lodbuilder.build.tiled.merge).

    ``xyz``/``key``/``tile``: points by descending key (the head's first, key inf, tile -1); each
    point of ``own`` with a finite key above 0 is compared with every point before it (whose key
    is at least its own) within ``alpha`` x its key x (1 + ``slack``): both are marked in
    ``linked`` where their tiles differ. The points before it are kept in the hash grid
    (``tkeys``/``thead``/``nxt``), whose cells follow the keys down to ``min_cell`` (rebuilt as in
    :func:`seam_merge`)."""
    n = xyz.shape[0]
    mask = tkeys.shape[0] - 1
    cell = np.inf
    for i in range(n):
        k = key[i]
        if own[i] and np.isfinite(k) and k > 0.0:
            radius = alpha * k * (1.0 + slack)
            if k < 0.5 * cell:
                cell = max(k, min_cell)
                grid_rebuild(tkeys, thead, nxt, xyz, lo, cell, mask, i)
            px = xyz[i, 0]
            py = xyz[i, 1]
            pz = xyz[i, 2]
            for cx in range(cell_of(px - radius, lo[0], cell), cell_of(px + radius, lo[0], cell) + 1):
                for cy in range(cell_of(py - radius, lo[1], cell), cell_of(py + radius, lo[1], cell) + 1):
                    for cz in range(cell_of(pz - radius, lo[2], cell), cell_of(pz + radius, lo[2], cell) + 1):
                        s = grid_slot(tkeys, key3(cx, cy, cz), mask)
                        if tkeys[s] == -1:
                            continue
                        j = thead[s]
                        while j >= 0:
                            if tile[j] != tile[i]:
                                dx = xyz[j, 0] - px
                                dy = xyz[j, 1] - py
                                dz = xyz[j, 2] - pz
                                if np.sqrt(dx * dx + dy * dy + dz * dz) <= radius:
                                    linked[i] = True
                                    linked[j] = True
                            j = nxt[j]
        if cell < np.inf:
            grid_insert(tkeys, thead, nxt, xyz, lo, cell, mask, i)


@nb.njit(**JIT)
def _tile_sift(theap, n):  # pragma: no cover - compiled
    """The top of the tile heap changed: sift it down (max by key, ties by tile)."""
    i = 0
    k = theap[0, 0]
    t = theap[0, 1]
    while True:
        c = 2 * i + 1
        if c >= n:
            break
        if c + 1 < n and (theap[c + 1, 0] > theap[c, 0] or (theap[c + 1, 0] == theap[c, 0] and theap[c + 1, 1] < theap[c, 1])):
            c += 1
        if theap[c, 0] < k or (theap[c, 0] == k and theap[c, 1] > t):
            break
        theap[i, 0] = theap[c, 0]
        theap[i, 1] = theap[c, 1]
        i = c
    theap[i, 0] = k
    theap[i, 1] = t


@nb.njit(**JIT)
def tile_pop(theap, n):  # pragma: no cover - compiled
    n -= 1
    if n > 0:
        theap[0, 0] = theap[n, 0]
        theap[0, 1] = theap[n, 1]
        _tile_sift(theap, n)
    return n


@nb.njit(**JIT)
def tile_heap_refresh(theap, n, t, key):  # pragma: no cover - compiled
    """Tile t (at the top) got a refilled buffer whose first key is ``key``."""
    theap[0, 0] = key
    _tile_sift(theap, n)
    return n


# ------------------------------------------------------------------------------------ covering

@nb.njit(**JIT)
def _box_dist(px, py, pz, x0, y0, z0, size):  # pragma: no cover - compiled
    """Distance from p to the axis-aligned cube [x0, x0 + size] x ... (0 inside)."""
    dx = max(x0 - px, 0.0, px - (x0 + size))
    dy = max(y0 - py, 0.0, py - (y0 + size))
    dz = max(z0 - pz, 0.0, pz - (z0 + size))
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@nb.njit(**JIT)
def cover_pass(xyz, rank, core, cell, ev_rank, ev_val, pt_rank, pt_parent, pt_space):  # pragma: no cover
    """Exact covering radii of a tile's core while the points of its core and halo are inserted in
    rank order (``rank`` ascending; ``xyz`` in that order).

    Writes an event (rank + 1, covering radius) whenever the radius changes and, for each inserted
    core point in rank order, its rank, the rank of its nearest earlier point and the distance to
    it. Two phases: :func:`cover_head` while the radius is above ``TAIL * cell`` (each insertion
    updates the pending points it comes closer to), then :func:`cover_tail` (each pending point's
    nearer and nearer earlier points found from a grid, the radius a suffix maximum).
    Returns (number of events, number of core points)."""
    ne, npt, i0, last, d0, p0 = cover_head(xyz, rank, core, cell, TAIL * cell, ev_rank, ev_val, pt_rank,
                                           pt_parent, pt_space)
    if i0 < xyz.shape[0]:
        ne, npt = cover_tail(xyz, rank, core, cell, i0, d0, p0, last, ne, npt, ev_rank, ev_val, pt_rank,
                             pt_parent, pt_space)
    return ne, npt


@nb.njit(**JIT)
def stable_argsort(key):  # pragma: no cover - compiled
    """The permutation that sorts non-negative ``key`` stably (as ``np.argsort(kind="stable")``):
    a least-significant-digit radix sort, 11 bits a pass (numba's merge sort is 3 x slower)."""
    n = key.shape[0]
    o = np.arange(n)
    tmp = np.empty(n, np.int64)
    top = 0
    for i in range(n):
        top = max(top, key[i])
    shift = 0
    count = np.empty(2049, np.int64)
    while shift < 63 and (shift == 0 or (top >> shift) > 0):
        count[:] = 0
        for i in range(n):
            count[((key[o[i]] >> shift) & 2047) + 1] += 1
        for d in range(2048):
            count[d + 1] += count[d]
        for i in range(n):
            d = (key[o[i]] >> shift) & 2047
            tmp[count[d]] = o[i]
            count[d] += 1
        o, tmp = tmp, o
        shift += 11
    return o


@nb.njit(**JIT)
def cover_head(xyz, rank, core, cell, stop, ev_rank, ev_val, pt_rank, pt_parent, pt_space):  # pragma: no cover
    """The first phase of :func:`cover_pass`: points inserted one by one until the covering radius
    is at most ``stop`` (before the insertion of point ``i0``).

    Keeps, for every pending core point, its distance to (and the rank of) the nearest inserted
    point. After each insertion the core's covering radius is the largest pending distance (the root
    of a max segment tree over the blocks). An insertion updates only the pending points it comes closer to: they sit in cubic
    cells of size ``cell`` (the non-empty ones, numbered compactly, their points stored together)
    grouped in blocks of 2^3 cells; each cell and block keeps an upper bound of its points'
    distances, and a cell or block no nearer to the new point than that bound is skipped.
    Returns (events, core points written, i0, the last event's radius, d0, p0): ``d0[i - i0]`` and
    ``p0[i - i0]`` the distance and the rank of the nearest of points 0..i0-1 to each pending core
    point i (inf and -1 at the others)."""
    n = xyz.shape[0]
    lo, hi = _box(xyz, 0)
    g = np.empty(3, np.int64)
    for a in range(3):
        g[a] = max(1, np.int64((hi[a] - lo[a]) / cell) + 1)
    nbx, nby, nbz = (g[0] + 1) // 2, (g[1] + 1) // 2, (g[2] + 1) // 2
    # core points sorted by cell; cells numbered compactly in that order
    ncore = 0
    for i in range(n):
        if core[i]:
            ncore += 1
    pid = np.empty(ncore, np.int64)
    key = np.empty(ncore, np.int64)
    m = 0
    for i in range(n):
        if core[i]:
            cx = min(np.int64((xyz[i, 0] - lo[0]) / cell), g[0] - 1)
            cy = min(np.int64((xyz[i, 1] - lo[1]) / cell), g[1] - 1)
            cz = min(np.int64((xyz[i, 2] - lo[2]) / cell), g[2] - 1)
            # block-major key: the cells of a block are neighbours in the order
            b = ((cx // 2) * nby + cy // 2) * nbz + cz // 2
            key[m] = (b * 8 + (cx % 2) * 4 + (cy % 2) * 2 + (cz % 2))
            pid[m] = i
            m += 1
    o = stable_argsort(key)
    key = key[o]
    pid = pid[o]
    nc = 0
    for j in range(ncore):
        if j == 0 or key[j] != key[j - 1]:
            nc += 1
    cstart = np.empty(nc + 1, np.int64)
    ccorner = np.empty((nc, 3))
    cblock = np.empty(nc, np.int64)
    c = -1
    for j in range(ncore):
        if j == 0 or key[j] != key[j - 1]:
            c += 1
            cstart[c] = j
            b = key[j] // 8
            r = key[j] % 8
            bz = b % nbz
            by = (b // nbz) % nby
            bx = b // (nbz * nby)
            ccorner[c, 0] = lo[0] + (bx * 2 + r // 4) * cell
            ccorner[c, 1] = lo[1] + (by * 2 + (r // 2) % 2) * cell
            ccorner[c, 2] = lo[2] + (bz * 2 + r % 2) * cell
            cblock[c] = b
    cstart[nc] = ncore
    npend = np.empty(nc, np.int64)
    for c in range(nc):
        npend[c] = cstart[c + 1] - cstart[c]
    # point data in slot order (a cell's pending points are contiguous); spos: point -> slot
    sx = np.empty(ncore)
    sy = np.empty(ncore)
    sz = np.empty(ncore)
    sd = np.full(ncore, np.inf)
    slab = np.full(ncore, -1, np.int64)
    sid = pid.copy()
    scell = np.empty(ncore, np.int64)
    spos = np.full(n, -1, np.int64)
    for c in range(nc):
        for j in range(cstart[c], cstart[c + 1]):
            scell[j] = c
    for j in range(ncore):
        i = pid[j]
        sx[j] = xyz[i, 0]
        sy[j] = xyz[i, 1]
        sz[j] = xyz[i, 2]
        spos[i] = j
    cmax = np.full(nc, np.inf)
    nblock = nbx * nby * nbz
    bmax = np.full(nblock, -1.0)
    bfirst = np.full(nblock, -1, np.int64)
    bcnt = np.zeros(nblock, np.int64)
    for c in range(nc):
        b = cblock[c]
        if bfirst[b] < 0:
            bfirst[b] = c
        bcnt[b] += 1
        bmax[b] = np.inf
    # a max segment tree over the blocks' maxima: its root is the covering radius of the core
    size = 1
    while size < nblock:
        size *= 2
    tree = np.full(2 * size, -1.0)
    for b in range(nblock):
        tree[size + b] = bmax[b]
    for t in range(size - 1, 0, -1):
        tree[t] = max(tree[2 * t], tree[2 * t + 1])
    pending = ncore
    ne = 0
    npt = 0
    last = -1.0
    bsize = 2.0 * cell
    for i in range(n + 1):
        cr = tree[1] if pending > 0 else 0.0
        if cr != last:
            ev_rank[ne] = rank[i - 1] + 1 if i > 0 else 0
            ev_val[ne] = cr
            ne += 1
            last = cr
        if i == n or cr <= stop:
            break
        j = spos[i]
        if j >= 0:
            pt_rank[npt] = rank[i]
            pt_parent[npt] = slab[j]
            pt_space[npt] = sd[j]
            npt += 1
            # remove the point from its cell: swap with the cell's last pending slot
            c = scell[j]
            removed = sd[j]
            last_j = cstart[c] + npend[c] - 1
            if last_j != j:
                sx[j], sx[last_j] = sx[last_j], sx[j]
                sy[j], sy[last_j] = sy[last_j], sy[j]
                sz[j], sz[last_j] = sz[last_j], sz[j]
                sd[j], sd[last_j] = sd[last_j], sd[j]
                slab[j], slab[last_j] = slab[last_j], slab[j]
                other = sid[last_j]
                sid[j] = other
                sid[last_j] = i
                spos[other] = j
            spos[i] = -1
            npend[c] -= 1
            pending -= 1
            if removed >= cmax[c]:  # the cell's (and maybe its block's) maximum goes down
                cm = -1.0
                for jj in range(cstart[c], cstart[c] + npend[c]):
                    if sd[jj] > cm:
                        cm = sd[jj]
                cmax[c] = cm
                b = cblock[c]
                bm = -1.0
                for cc in range(bfirst[b], bfirst[b] + bcnt[b]):
                    if npend[cc] > 0 and cmax[cc] > bm:
                        bm = cmax[cc]
                bmax[b] = bm
                _tree_set(tree, size, b, bm)
        if pending == 0:
            continue
        px = xyz[i, 0]
        py = xyz[i, 1]
        pz = xyz[i, 2]
        rad = cr
        if not np.isfinite(rad):
            rad = 2.0 * (hi[0] - lo[0] + hi[1] - lo[1] + hi[2] - lo[2]) + 1.0
        b0x = max(np.int64((px - rad - lo[0]) / bsize), 0)
        b1x = min(np.int64((px + rad - lo[0]) / bsize), nbx - 1)
        b0y = max(np.int64((py - rad - lo[1]) / bsize), 0)
        b1y = min(np.int64((py + rad - lo[1]) / bsize), nby - 1)
        b0z = max(np.int64((pz - rad - lo[2]) / bsize), 0)
        b1z = min(np.int64((pz + rad - lo[2]) / bsize), nbz - 1)
        for bx in range(b0x, b1x + 1):
            for by in range(b0y, b1y + 1):
                for bz in range(b0z, b1z + 1):
                    b = (bx * nby + by) * nbz + bz
                    bm = bmax[b]
                    if bm < 0.0:
                        continue
                    if bm <= _box_dist(px, py, pz, lo[0] + bx * bsize, lo[1] + by * bsize, lo[2] + bz * bsize,
                                       bsize):
                        continue
                    newb = -1.0
                    for c in range(bfirst[b], bfirst[b] + bcnt[b]):
                        if npend[c] == 0:
                            cmax[c] = -1.0
                            continue
                        cm = cmax[c]
                        if cm > _box_dist(px, py, pz, ccorner[c, 0], ccorner[c, 1], ccorner[c, 2], cell):
                            cm = -1.0
                            for jj in range(cstart[c], cstart[c] + npend[c]):
                                dx = sx[jj] - px
                                dy = sy[jj] - py
                                dz = sz[jj] - pz
                                dd = np.sqrt(dx * dx + dy * dy + dz * dz)
                                if dd < sd[jj]:
                                    sd[jj] = dd
                                    slab[jj] = rank[i]
                                if sd[jj] > cm:
                                    cm = sd[jj]
                            cmax[c] = cm
                        if cm > newb:
                            newb = cm
                    if newb != bm:
                        bmax[b] = newb
                        _tree_set(tree, size, b, newb)
    i0 = min(i, n)
    d0 = np.full(n - i0, np.inf)
    p0 = np.full(n - i0, -1, np.int64)
    for c in range(nc):
        for j in range(cstart[c], cstart[c] + npend[c]):
            d0[sid[j] - i0] = sd[j]
            p0[sid[j] - i0] = slab[j]
    return ne, npt, i0, last, d0, p0


#: :func:`cover_pass` changes phase when the covering radius falls to TAIL cells
TAIL = 0.5
#: the cells of the tail's grid, in cells of the first phase
TAIL_GRID = 1.0
#: most cells of the tail's grid (its cells grow beyond ``cell`` to keep under it)
TAIL_CELLS = 1 << 22


@nb.njit(**JIT)
def _box(xyz, i0):  # pragma: no cover - compiled
    """The bounding box (lo, hi) of points i0..n-1."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(i0, xyz.shape[0]):
        for a in range(3):
            lo[a] = min(lo[a], xyz[i, a])
            hi[a] = max(hi[a], xyz[i, a])
    return lo, hi


@nb.njit(**JIT)
def _tail_grid(xyz, i0, cell):  # pragma: no cover - compiled
    """Points i0..n-1 by cubic cells of a dense grid (x-major): (lo, cell size, dims, start of each
    cell's points, their indices ascending within a cell, their coordinates in that order, and the
    slot of each point i at ``[i - i0]``)."""
    n = xyz.shape[0]
    lo, hi = _box(xyz, i0)
    g = cell
    dims = np.empty(3, np.int64)
    while True:
        for a in range(3):
            dims[a] = np.int64((hi[a] - lo[a]) / g) + 1
        if dims[0] * dims[1] * dims[2] <= TAIL_CELLS:
            break
        g *= 1.25
    m = n - i0
    key = np.empty(m, np.int64)
    start = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for i in range(i0, n):
        cx = min(np.int64((xyz[i, 0] - lo[0]) / g), dims[0] - 1)
        cy = min(np.int64((xyz[i, 1] - lo[1]) / g), dims[1] - 1)
        cz = min(np.int64((xyz[i, 2] - lo[2]) / g), dims[2] - 1)
        k = (cx * dims[1] + cy) * dims[2] + cz
        key[i - i0] = k
        start[k + 1] += 1
    for k in range(start.shape[0] - 1):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    idx = np.empty(m, np.int64)
    pxyz = np.empty((m, 3))
    for i in range(i0, n):  # (in index order: each cell's points ascending)
        k = key[i - i0]
        idx[fill[k]] = i
        pxyz[fill[k]] = xyz[i]
        key[i - i0] = fill[k]  # (now the point's slot)
        fill[k] += 1
    return lo, g, dims, start, idx, pxyz, key


@nb.njit(**JIT)
def _tail_range(x, d, lo, g, dim):  # pragma: no cover - compiled
    """The cells along one axis of the grid that hold every point nearer than ``d`` to ``x`` (a
    margin of 1e-6 cell and of the coordinates' rounding on either side)."""
    eps = 1e-6 * g + 1e-12 * (abs(x) + abs(lo))
    a = max(np.int64(np.floor((x - d - eps - lo) / g)), 0)
    b = min(np.int64(np.floor((x + d + eps - lo) / g)), dim - 1)
    return a, b


@nb.njit(**JIT)
def _tail_point(iq, s, par, prank, lo, g, dims, start, idx, pxyz, q, buf_i, buf_d, buf_r, st_e, st_v, ns
                ):  # pragma: no cover - compiled
    """Pending core point ``iq`` in slot ``q`` (distance ``s`` to, and ``par`` the rank of, its
    nearest point before the tail): its nearer and nearer points of the tail inserted before it,
    each a step (index of the nearer point, distance before it) appended to ``st_e``, ``st_v`` at
    ``ns``, the last one (``iq``, distance). Returns the distance to and the rank of its nearest
    earlier point and the new ``ns``, or (s, par, -k) with nothing done when a buffer needs k slots."""
    x, y, z = pxyz[q, 0], pxyz[q, 1], pxyz[q, 2]
    x0, x1 = _tail_range(x, s, lo[0], g, dims[0])
    y0, y1 = _tail_range(y, s, lo[1], g, dims[1])
    z0, z1 = _tail_range(z, s, lo[2], g, dims[2])
    need = 0
    for cx in range(x0, x1 + 1):
        for cy in range(y0, y1 + 1):
            base = (cx * dims[1] + cy) * dims[2]
            need += start[base + z1 + 1] - start[base + z0]
    if need > buf_i.shape[0] or ns + need + 1 > st_e.shape[0]:
        return s, par, -need - 1
    k = 0
    for cx in range(x0, x1 + 1):
        for cy in range(y0, y1 + 1):
            base = (cx * dims[1] + cy) * dims[2]
            for jj in range(start[base + z0], start[base + z1 + 1]):
                ip = idx[jj]
                if ip >= iq:
                    continue
                dx = x - pxyz[jj, 0]
                dy = y - pxyz[jj, 1]
                dz = z - pxyz[jj, 2]
                dd = np.sqrt(dx * dx + dy * dy + dz * dz)
                if dd < s:
                    buf_i[k] = ip
                    buf_d[k] = dd
                    buf_r[k] = prank[jj]
                    k += 1
    _sort_steps(buf_i, buf_d, buf_r, k)
    for t in range(k):
        if buf_d[t] < s:
            st_e[ns] = buf_i[t]
            st_v[ns] = s
            ns += 1
            s = buf_d[t]
            par = buf_r[t]
    st_e[ns] = iq
    st_v[ns] = s
    return s, par, ns + 1


@nb.njit(**JIT)
def _sort_steps(key, val, aux, k):  # pragma: no cover - compiled
    """Sort key[:k] ascending (distinct keys), val[:k] and aux[:k] with it."""
    if k > 32:
        o = np.argsort(key[:k])
        key[:k], val[:k], aux[:k] = key[:k][o], val[:k][o], aux[:k][o]
        return
    for t in range(1, k):
        a, v, w = key[t], val[t], aux[t]
        u = t - 1
        while u >= 0 and key[u] > a:
            key[u + 1], val[u + 1], aux[u + 1] = key[u], val[u], aux[u]
            u -= 1
        key[u + 1], val[u + 1], aux[u + 1] = a, v, w


@nb.njit(**JIT)
def cover_tail(xyz, rank, core, cell, i0, d0, p0, last, ne, npt, ev_rank, ev_val, pt_rank, pt_parent,
               pt_space):  # pragma: no cover - compiled
    """The second phase of :func:`cover_pass`, from point ``i0`` on (``d0``, ``p0``: see
    :func:`cover_head`; ``last``: the radius of the last event written). Every pending core point
    is independent of the others: its distance to the points before it falls in steps (each
    nearer earlier point one), all below ``cell``, so the points of the tail within that distance
    are all it needs (from a grid, point by point in the grid's order). The covering radius before
    point i is the largest distance held by a pending point then: the largest value of any step
    that ends (its nearer point, or the point itself, inserted) at i or later, a suffix maximum."""
    n = xyz.shape[0]
    m = n - i0
    lo, g, dims, start, idx, pxyz, slot = _tail_grid(xyz, i0, TAIL_GRID * cell)
    prank = np.empty(m, np.int64)
    for q in range(m):
        prank[q] = rank[idx[q]]
    res_s = np.empty(m)
    res_p = np.empty(m, np.int64)
    buf_i, buf_d, buf_r = np.empty(256, np.int64), np.empty(256), np.empty(256, np.int64)
    st_e, st_v = np.empty(m // 2 + 1024, np.int64), np.empty(m // 2 + 1024)  # (grown when full)
    ns = 0
    for q in range(m):
        iq = idx[q]
        if not core[iq]:
            continue
        while True:
            s, par, r = _tail_point(iq, d0[iq - i0], p0[iq - i0], prank, lo, g, dims, start, idx, pxyz, q,
                                    buf_i, buf_d, buf_r, st_e, st_v, ns)
            if r >= 0:
                break
            buf_i, buf_d, buf_r = _grown(buf_i, -r), _grown(buf_d, -r), _grown(buf_r, -r)
            st_e, st_v = _grown(st_e, ns - r), _grown(st_v, ns - r)
        ns = r
        res_s[q] = s
        res_p[q] = par
    for i in range(i0, n):
        if core[i]:
            q = slot[i - i0]
            pt_rank[npt], pt_parent[npt], pt_space[npt] = rank[i], res_p[q], res_s[q]
            npt += 1
    return _tail_events(rank, i0, st_e, st_v, ns, last, ne, ev_rank, ev_val), npt


@nb.njit(**JIT)
def _grown(a, k):  # pragma: no cover - compiled
    """``a`` (1-d) with at least ``k`` slots: itself, or a copy twice that long."""
    if a.shape[0] >= k:
        return a
    b = np.empty(2 * k, a.dtype)
    b[: a.shape[0]] = a
    return b


@nb.njit(**JIT)
def _tail_events(rank, i0, st_e, st_v, ns, last, ne, ev_rank, ev_val):  # pragma: no cover - compiled
    """Events of the tail from its steps (see :func:`cover_tail`); returns the number of events."""
    n = rank.shape[0]
    m = n - i0
    top = np.full(m + 1, -1.0)
    for t in range(ns):
        e = st_e[t] - i0
        if st_v[t] > top[e]:
            top[e] = st_v[t]
    for e in range(m - 1, -1, -1):  # suffix maxima
        if top[e + 1] > top[e]:
            top[e] = top[e + 1]
    for i in range(i0 + 1, n + 1):
        cr = max(top[i - i0], 0.0)
        if cr != last:
            ev_rank[ne] = rank[i - 1] + 1
            ev_val[ne] = cr
            ne += 1
            last = cr
    return ne


@nb.njit(**JIT)
def _tree_set(tree, size, b, value):  # pragma: no cover - compiled
    t = size + b
    tree[t] = value
    t >>= 1
    while t >= 1:
        v = max(tree[2 * t], tree[2 * t + 1])
        if tree[t] == v:
            break
        tree[t] = v
        t >>= 1


# ------------------------------------------------------------------------------------ events

@nb.njit(**JIT)
def merge_events(ev_rank, ev_tile, ev_val, cur, k0, k1, radius):  # pragma: no cover - compiled
    """Write radius[k - k0] = max over tiles of their covering radius at k for k in [k0, k1).
    ``cur[t]``: tile t's value at k0 (inf before its first event; updated in place); ``ev_rank``,
    ``ev_tile``, ``ev_val``: the events of every tile in the band (rank in [k0, k1), tile, value),
    sorted by rank (a tile's own events in their order).

    The tiles' values are the leaves of a max segment tree: each event updates one leaf, and each run
    of positions between two events takes the root (O(events log T + k1 - k0), where a scan of every
    tile at every position took O((k1 - k0) T))."""
    T = cur.shape[0]
    size = 1
    while size < T:
        size *= 2
    tree = np.full(2 * size, -np.inf)
    for t in range(T):
        tree[size + t] = cur[t]
    for i in range(size - 1, 0, -1):
        tree[i] = max(tree[2 * i], tree[2 * i + 1])
    e, n_ev, k = 0, ev_rank.shape[0], k0
    while k < k1:
        while e < n_ev and ev_rank[e] <= k:
            t = ev_tile[e]
            cur[t] = ev_val[e]
            _tree_set(tree, size, t, ev_val[e])
            e += 1
        nxt = k1
        if e < n_ev and ev_rank[e] < k1:
            nxt = ev_rank[e]
        g = tree[1]
        for j in range(k, nxt):
            radius[j - k0] = g
        k = nxt


# ------------------------------------------------------------------------------------ split

@nb.njit(**JIT)
def halo_members(pts, own, t_lo, t_hi, halo, nstart, nlist):  # pragma: no cover - compiled
    """The points of a block that lie in other tiles' halos: for each tile t, the points i (in
    increasing order) with ``own[i] != t`` within ``halo`` of their own tile's faces (``pts[i, a] -
    t_lo[own, a] <= halo`` or ``t_hi[own, a] - pts[i, a] <= halo`` on some axis a) and inside t's box
    grown by ``halo`` (``t_lo[t] - halo <= pts[i] <= t_hi[t] + halo``).

    Only the tiles near the point's own tile o are tested: ``nlist[nstart[o]:nstart[o + 1]]`` (every
    other tile whose box comes within ``halo`` plus how far a point may lie outside its own tile's
    box). Returns (start, members): tile t's points are ``members[start[t]:start[t + 1]]``."""
    T, m = t_lo.shape[0], pts.shape[0]
    start = np.zeros(T + 1, np.int64)
    members = np.empty(0, np.int64)
    for p in range(2):  # count, then fill (each tile's points in increasing order)
        fill = start[:T].copy()
        for i in range(m):
            o = own[i]
            near = False
            for d in range(3):
                if pts[i, d] - t_lo[o, d] <= halo or t_hi[o, d] - pts[i, d] <= halo:
                    near = True
            if not near:
                continue
            for j in range(nstart[o], nstart[o + 1]):
                t = nlist[j]
                inside = True
                for d in range(3):
                    if not (pts[i, d] >= t_lo[t, d] - halo and pts[i, d] <= t_hi[t, d] + halo):
                        inside = False
                        break
                if inside:
                    if p == 0:
                        start[t + 1] += 1
                    else:
                        members[fill[t]] = i
                        fill[t] += 1
        if p == 0:
            for t in range(T):
                start[t + 1] += start[t]
            members = np.empty(start[T], np.int64)
    return start, members
