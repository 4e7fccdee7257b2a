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
    h = (k * np.int64(0x9E3779B97F4A7C15)) >> np.int64(17)
    return h & mask


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
    """Merge tile streams by descending key, repairing seams (see lodbuilder.sampling.tiled.merge).

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
                for s in range(tkeys.shape[0]):
                    tkeys[s] = -1
                for j in range(n_acc):
                    grid_insert(tkeys, thead, nxt, ax, lo, cell, mask, j)
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
def cover_pass(xyz, rank, core, d, lab, start, lo, min_cell, ev_rank, ev_val, pt_rank, pt_parent, pt_space):
    """Exact covering radii of a tile's core while the points of its core and halo are inserted in
    rank order (``rank`` ascending; ``xyz`` in that order).

    ``d``/``lab``: per point, the distance to (and rank of) the nearest inserted point, already set
    for the points inserted before ``start`` (the head). After inserting point i the covering radius
    of the core is max over core points of d. Writes events (rank + 1, covering radius) whenever it
    changes (``ev_*``), and for every inserted core point its rank, the rank of its nearest earlier
    point and the distance to it (``pt_*``). Returns (number of events, number of core points).
    """  # pragma: no cover - compiled
    n = xyz.shape[0]
    # lazy max-heap over pending core points (keys may be stale: larger than d)
    hkey = np.empty(n)
    hitem = np.empty(n, np.int64)
    hn = 0
    for i in range(start, n):
        if core[i]:
            hkey[hn] = d[i]
            hitem[hn] = i
            hn += 1
    for i in range((hn - 2) // 2, -1, -1):
        _down(hkey, hitem, i, hn)
    done = np.zeros(n, np.bool_)
    for i in range(start):
        done[i] = True
    # hash grid of pending core points (cells rebuilt as the radius shrinks)
    size = 1024
    while size < 2 * n:
        size *= 2
    tkeys = np.full(size, -1, np.int64)
    thead = np.full(size, -1, np.int64)
    nxt = np.full(n, -1, np.int64)
    mask = size - 1
    cell = np.inf
    ne = 0
    npt = 0
    last = -1.0
    for i in range(start, n + 1):
        # the covering radius of the core now (prefix: every point of rank < rank[i])
        while hn > 0:
            top = hitem[0]
            if done[top]:
                hn -= 1
                if hn > 0:
                    hkey[0] = hkey[hn]
                    hitem[0] = hitem[hn]
                    _down(hkey, hitem, 0, hn)
                continue
            if hkey[0] > d[top]:
                hkey[0] = d[top]
                _down(hkey, hitem, 0, hn)
                continue
            break
        cr = hkey[0] if hn > 0 else 0.0
        if cr != last:
            ev_rank[ne] = rank[i - 1] + 1 if i > 0 else 0
            ev_val[ne] = cr
            ne += 1
            last = cr
        if i == n:
            break
        if core[i]:
            pt_rank[npt] = rank[i]
            pt_parent[npt] = lab[i]
            pt_space[npt] = d[i]
            npt += 1
        done[i] = True
        if hn == 0:
            continue
        if not np.isfinite(cr):
            # some core points are still uncovered: this point reaches every pending one
            px = xyz[i, 0]
            py = xyz[i, 1]
            pz = xyz[i, 2]
            for j in range(i + 1, n):
                if core[j]:
                    dx = xyz[j, 0] - px
                    dy = xyz[j, 1] - py
                    dz = xyz[j, 2] - pz
                    dd = np.sqrt(dx * dx + dy * dy + dz * dz)
                    if dd < d[j]:
                        d[j] = dd
                        lab[j] = rank[i]
            continue
        # (re)build the grid when the radius has halved
        if cr < 0.5 * cell:
            cell = max(cr, min_cell)
            for s in range(size):
                tkeys[s] = -1
            for j in range(i + 1, n):
                if core[j] and not done[j]:
                    grid_insert(tkeys, thead, nxt, xyz, lo, cell, mask, j)
        px = xyz[i, 0]
        py = xyz[i, 1]
        pz = xyz[i, 2]
        rad = cr
        cx0 = cell_of(px - rad, lo[0], cell)
        cx1 = cell_of(px + rad, lo[0], cell)
        cy0 = cell_of(py - rad, lo[1], cell)
        cy1 = cell_of(py + rad, lo[1], cell)
        cz0 = cell_of(pz - rad, lo[2], cell)
        cz1 = cell_of(pz + rad, lo[2], cell)
        for cx in range(cx0, cx1 + 1):
            for cy in range(cy0, cy1 + 1):
                for cz in range(cz0, cz1 + 1):
                    s = grid_slot(tkeys, key3(cx, cy, cz), mask)
                    if tkeys[s] == -1:
                        continue
                    prev = -1
                    j = thead[s]
                    while j >= 0:
                        nj = nxt[j]
                        if done[j]:  # unlink inserted points as they are met
                            if prev < 0:
                                thead[s] = nj
                            else:
                                nxt[prev] = nj
                            j = nj
                            continue
                        dx = xyz[j, 0] - px
                        dy = xyz[j, 1] - py
                        dz = xyz[j, 2] - pz
                        dd = np.sqrt(dx * dx + dy * dy + dz * dz)
                        if dd < d[j]:
                            d[j] = dd
                            lab[j] = rank[i]
                        prev = j
                        j = nj
    return ne, npt


# ------------------------------------------------------------------------------------ events

@nb.njit(**JIT)
def merge_events(ev_rank, ev_val, ev_pos, ev_len, ev_done, cur, k0, k1, bound, radius):
    """Write radius[k - k0] = min(bound, max over tiles of their covering radius at k) for k in
    [k0, k1). ``ev_*`` (T, B): per tile its events (rank, value) in rank order, read position,
    length, exhausted flag; ``cur[t]`` the tile's current value (inf before its first event).

    Returns (k, t): k == k1 when done, else tile t needs more events (k is where to resume)."""  # pragma: no cover
    T = cur.shape[0]
    gmax = -np.inf
    for t in range(T):
        if cur[t] > gmax:
            gmax = cur[t]
    for k in range(k0, k1):
        for t in range(T):
            while True:
                if ev_pos[t] >= ev_len[t]:
                    if not ev_done[t]:
                        return k, t
                    break
                if ev_rank[t, ev_pos[t]] > k:
                    break
                v = ev_val[t, ev_pos[t]]
                old = cur[t]
                cur[t] = v
                ev_pos[t] += 1
                if v > gmax:
                    gmax = v
                elif old == gmax and v < old:
                    gmax = -np.inf
                    for u in range(T):
                        if cur[u] > gmax:
                            gmax = cur[u]
        radius[k - k0] = min(bound, gmax)
    return k1, -1
