"""Sparse voxel grid: Morton keys, an open-addressing hash map, band construction, neighbour table.

Voxel centres sit at integer grid coordinates (grid units: one unit = the voxel size h). A point with
grid coordinates u lies in the cell whose lower corner is floor(u); the cell's 8 corners are voxel
centres. Keys are 63-bit Morton codes of 21-bit coordinates, so sorting keys sorts voxels in Morton
order.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import JIT

MAX_COORD = (1 << 21) - 1  # per axis

_M0 = np.uint64(0x1FFFFF)
_M1 = np.uint64(0x1F00000000FFFF)
_M2 = np.uint64(0x1F0000FF0000FF)
_M3 = np.uint64(0x100F00F00F00F00F)
_M4 = np.uint64(0x10C30C30C30C30C3)
_M5 = np.uint64(0x1249249249249249)
_GOLD = np.uint64(0x9E3779B97F4A7C15)


@nb.njit(**JIT)
def _split3(x):  # pragma: no cover - compiled
    x = np.uint64(x) & _M0
    x = (x | (x << np.uint64(32))) & _M1
    x = (x | (x << np.uint64(16))) & _M2
    x = (x | (x << np.uint64(8))) & _M3
    x = (x | (x << np.uint64(4))) & _M4
    x = (x | (x << np.uint64(2))) & _M5
    return x


@nb.njit(**JIT)
def _compact3(x):  # pragma: no cover - compiled
    x = x & _M5
    x = (x ^ (x >> np.uint64(2))) & _M4
    x = (x ^ (x >> np.uint64(4))) & _M3
    x = (x ^ (x >> np.uint64(8))) & _M2
    x = (x ^ (x >> np.uint64(16))) & _M1
    x = (x ^ (x >> np.uint64(32))) & _M0
    return np.int64(x)


@nb.njit(**JIT)
def morton(x, y, z):  # pragma: no cover - compiled
    return np.int64(_split3(x) | (_split3(y) << np.uint64(1)) | (_split3(z) << np.uint64(2)))


@nb.njit(**JIT)
def unmorton(key):  # pragma: no cover - compiled
    k = np.uint64(key)
    return _compact3(k), _compact3(k >> np.uint64(1)), _compact3(k >> np.uint64(2))


@nb.njit(**JIT)
def morton_keys(cells):  # pragma: no cover - compiled
    """Morton keys of (n, 3) non-negative int64 cell coordinates."""
    n = cells.shape[0]
    out = np.empty(n, np.int64)
    for i in range(n):
        out[i] = morton(cells[i, 0], cells[i, 1], cells[i, 2])
    return out


@nb.njit(**JIT)
def _slot(key, mask):  # pragma: no cover - compiled
    return np.int64((np.uint64(key) * _GOLD) >> np.uint64(20)) & mask


@nb.njit(**JIT)
def hash_insert(hkeys, key):  # pragma: no cover - compiled
    """Insert ``key``; return True if it was new. The table must have a free slot."""
    mask = hkeys.shape[0] - 1
    s = _slot(key, mask)
    while True:
        k = hkeys[s]
        if k == key:
            return False
        if k == -1:
            hkeys[s] = key
            return True
        s = (s + 1) & mask


@nb.njit(**JIT)
def hash_find(hkeys, hvals, key):  # pragma: no cover - compiled
    """Value stored for ``key``, or -1."""
    mask = hkeys.shape[0] - 1
    s = _slot(key, mask)
    while True:
        k = hkeys[s]
        if k == key:
            return hvals[s]
        if k == -1:
            return -1
        s = (s + 1) & mask


@nb.njit(**JIT)
def lookup(hkeys, hvals, x, y, z):  # pragma: no cover - compiled
    """Voxel index at integer coordinates (x, y, z), or -1 (also for negative coordinates)."""
    if x < 0 or y < 0 or z < 0:
        return -1
    return hash_find(hkeys, hvals, morton(x, y, z))


@nb.njit(**JIT)
def _rehash(hkeys, new_cap):  # pragma: no cover - compiled
    out = np.full(new_cap, -1, np.int64)
    for k in hkeys:
        if k != -1:
            hash_insert(out, k)
    return out


@nb.njit(**JIT)
def band_keys(u, occ, ostart, rad, cap_limit):  # pragma: no cover - compiled
    """Keys of all voxels whose centre lies within ``rad`` (grid units) of some point.

    ``u``: (M, 3) grid coordinates sorted by cell; ``occ``: (C, 3) occupied cell coordinates;
    ``ostart``: (C + 1,) point ranges of the occupied cells. Returns (keys, count); count is -1 when
    more than ``cap_limit`` voxels would be needed.
    """
    ext = int(np.floor(rad))
    r2 = rad * rad
    cap = 1024
    while cap < 2 * (2 * rad + 1) * occ.shape[0]:  # about 2r/h + 1 voxels per occupied cell
        cap *= 2
    hkeys = np.full(cap, -1, np.int64)
    count = 0
    for c in range(occ.shape[0]):
        cx, cy = occ[c, 0], occ[c, 1]
        p0, p1 = ostart[c], ostart[c + 1]
        for x in range(cx - ext, cx + ext + 2):
            for y in range(cy - ext, cy + ext + 2):
                # the z range where some point of the cell can be within rad
                zlo = np.inf
                zhi = -np.inf
                for i in range(p0, p1):
                    dx = u[i, 0] - x
                    dy = u[i, 1] - y
                    rest = r2 - dx * dx - dy * dy
                    if rest >= 0.0:
                        w = np.sqrt(rest)
                        zlo = min(zlo, u[i, 2] - w)
                        zhi = max(zhi, u[i, 2] + w)
                if zlo > zhi:
                    continue
                for z in range(int(np.ceil(zlo)), int(np.floor(zhi)) + 1):
                    inside = False
                    for i in range(p0, p1):
                        dx = u[i, 0] - x
                        dy = u[i, 1] - y
                        dz = u[i, 2] - z
                        if dx * dx + dy * dy + dz * dz <= r2:
                            inside = True
                            break
                    if not inside:
                        continue
                    if hash_insert(hkeys, morton(x, y, z)):
                        count += 1
                        if count > cap_limit:
                            return hkeys, -1
                        if 2 * count > hkeys.shape[0]:
                            hkeys = _rehash(hkeys, 2 * hkeys.shape[0])
    return hkeys, count


@nb.njit(**JIT)
def build_index(keys):  # pragma: no cover - compiled
    """Hash map key -> index for sorted ``keys``, their coordinates and the 6-neighbour table."""
    v = keys.shape[0]
    cap = 1024
    while cap < 2 * v:
        cap *= 2
    hkeys = np.full(cap, -1, np.int64)
    hvals = np.full(cap, -1, np.int32)
    mask = cap - 1
    for i in range(v):
        s = _slot(keys[i], mask)
        while hkeys[s] != -1:
            s = (s + 1) & mask
        hkeys[s] = keys[i]
        hvals[s] = i
    coord = np.empty((v, 3), np.int32)
    nbr = np.empty((v, 6), np.int32)
    for i in range(v):
        x, y, z = unmorton(keys[i])
        coord[i, 0] = x
        coord[i, 1] = y
        coord[i, 2] = z
        nbr[i, 0] = lookup(hkeys, hvals, x - 1, y, z)
        nbr[i, 1] = lookup(hkeys, hvals, x + 1, y, z)
        nbr[i, 2] = lookup(hkeys, hvals, x, y - 1, z)
        nbr[i, 3] = lookup(hkeys, hvals, x, y + 1, z)
        nbr[i, 4] = lookup(hkeys, hvals, x, y, z - 1)
        nbr[i, 5] = lookup(hkeys, hvals, x, y, z + 1)
    return hkeys, hvals, coord, nbr


@nb.njit(**JIT)
def coarse_runs(keys, cs, levels):  # pragma: no cover - compiled
    """Point ranges of coarse cells (2^j voxels a side, j = 1..levels) for ball queries.

    Points are sorted by the Morton key of their voxel cell, and the Morton key of the coarse cell
    of side 2^j is the fine key >> 3j, so every coarse cell is one contiguous range of points.
    Returns a hash map ((coarse key << 3) | j) -> run, and the runs' start and end.
    """
    nv = keys.shape[0]
    nrun = 0
    for j in range(1, levels + 1):
        sh = np.uint64(3 * j)
        prev = np.int64(-1)
        for v in range(nv):
            if cs[v + 1] > cs[v]:
                ck = np.int64(np.uint64(keys[v]) >> sh)
                if ck != prev:
                    nrun += 1
                    prev = ck
    rstart = np.empty(nrun, np.int64)
    rend = np.empty(nrun, np.int64)
    cap = 1024
    while cap < 2 * nrun:
        cap *= 2
    hk = np.full(cap, -1, np.int64)
    hv = np.full(cap, -1, np.int32)
    mask = cap - 1
    r = -1
    for j in range(1, levels + 1):
        sh = np.uint64(3 * j)
        prev = np.int64(-1)
        for v in range(nv):
            if cs[v + 1] > cs[v]:
                ck = np.int64(np.uint64(keys[v]) >> sh)
                if ck != prev:
                    r += 1
                    rstart[r] = cs[v]
                    prev = ck
                    key = (ck << 3) | j
                    s = _slot(key, mask)
                    while hk[s] != -1:
                        s = (s + 1) & mask
                    hk[s] = key
                    hv[s] = r
                rend[r] = cs[v + 1]
    return hk, hv, rstart, rend
