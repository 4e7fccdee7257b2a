"""Sparse voxel grid: Morton keys, open-addressing hash maps, band construction, neighbour table.

Voxel centres sit at integer grid coordinates (grid units: one unit = the voxel size h). A point with
grid coordinates u lies in the cell whose lower corner (its *anchor*) is floor(u); the cell's 8
corners are voxel centres. Keys are 63-bit Morton codes of 21-bit coordinates, so sorting keys sorts
voxels in Morton order, and a cell of side 2^j holds one contiguous run of keys.

Dtypes are fixed (one compiled specialisation per kernel): keys int64, voxel and point indices
int32, coordinates float64, per-voxel values float32.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import INLINE, JIT
from .heaps import f64_bits

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
def _slot(key, mask):  # pragma: no cover - compiled
    return np.int64((np.uint64(key) * _GOLD) >> np.uint64(20)) & mask


@nb.njit(**INLINE)
def hash_find(hidx, keys, key):  # pragma: no cover - compiled
    """Index i with keys[i] == key in the index hash ``hidx`` (int32 slots, -1 empty), or -1."""
    mask = hidx.shape[0] - 1
    s = _slot(key, mask)
    while True:
        i = hidx[s]
        if i < 0:
            return -1
        if keys[i] == key:
            return i
        s = (s + 1) & mask


@nb.njit(**INLINE)
def lower_bound(arr, key):  # pragma: no cover - compiled
    """The first index i with arr[i] >= key in the sorted ``arr`` (written out: one compiled
    version for every caller, where np.searchsorted compiles one per argument type)."""
    lo = np.int64(0)
    hi = np.int64(arr.shape[0])
    while lo < hi:
        mid = (lo + hi) >> 1
        if arr[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@nb.njit(**JIT)
def index_hash(keys):  # pragma: no cover - compiled
    """An open-addressing hash of the distinct ``keys`` (int32 slots holding indices into keys)."""
    n = keys.shape[0]
    cap = 1024
    while 2 * cap < 3 * n:  # load factor <= 2/3
        cap *= 2
    hidx = np.full(cap, -1, np.int32)
    mask = cap - 1
    for i in range(n):
        s = _slot(keys[i], mask)
        while hidx[s] != -1:
            s = (s + 1) & mask
        hidx[s] = i
    return hidx


@nb.njit(**JIT)
def cell_order(points, origin, h):  # pragma: no cover - compiled
    """Morton keys of the cells (anchors) of ``points`` (N, 3) on the grid (origin, h)."""
    n = points.shape[0]
    out = np.empty(n, np.int64)
    for i in range(n):
        x = int(np.floor((points[i, 0] - origin[0]) / h))
        y = int(np.floor((points[i, 1] - origin[1]) / h))
        z = int(np.floor((points[i, 2] - origin[2]) / h))
        out[i] = morton(x, y, z)
    return out


RADIX_BITS = 14  # at most this many key bits per pass of the radix sort (a 128 KB count table)


@nb.njit(**JIT)
def radix_argsort(keys):  # pragma: no cover - compiled
    """Stable sort of non-negative int64 ``keys``: (the sorted keys, the int32 permutation with
    keys[perm] sorted and equal keys in index order), exactly np.argsort(keys, kind="stable").
    Least significant digit first, as few passes of up to RADIX_BITS bits as the largest key
    needs (a pass whose digit is the same for every key is skipped)."""
    n = keys.shape[0]
    kmax = np.int64(0)
    for i in range(n):
        if keys[i] > kmax:
            kmax = keys[i]
    bits = 0
    while bits < 63 and (kmax >> bits) > 0:
        bits += 1
    passes = max(1, (bits + RADIX_BITS - 1) // RADIX_BITS)
    width = (bits + passes - 1) // passes
    mask = np.int64((1 << width) - 1)
    sk = keys.copy()
    si = np.arange(n).astype(np.int32)
    dk = np.empty(n, np.int64)
    di = np.empty(n, np.int32)
    cnt = np.empty(1 << width, np.int64)
    for pas in range(passes):
        shift = pas * width
        for b in range(cnt.shape[0]):
            cnt[b] = 0
        for i in range(n):
            cnt[(sk[i] >> shift) & mask] += 1
        if n > 0 and cnt[(sk[0] >> shift) & mask] == n:
            continue  # one digit for all: this pass keeps the order
        acc = np.int64(0)
        for b in range(cnt.shape[0]):
            c = cnt[b]
            cnt[b] = acc
            acc += c
        for i in range(n):
            d = (sk[i] >> shift) & mask
            j = cnt[d]
            cnt[d] = j + 1
            dk[j] = sk[i]
            di[j] = si[i]
        sk, dk = dk, sk
        si, di = di, si
    return sk, si


@nb.njit(**JIT)
def grid_coords(points, perm, origin, h):  # pragma: no cover - compiled
    """u[i] = (points[perm[i]] - origin) / h, without a permuted copy of the points."""
    n = perm.shape[0]
    u = np.empty((n, 3), np.float64)
    for i in range(n):
        p = perm[i]
        for a in range(3):
            u[i, a] = (points[p, a] - origin[a]) / h
    return u


FAR_SEP = 0.4
OUTER_SEP = 0.2
DEAD_ZONE = 0.5
BLOCK_BITS = 4  # the band is built block by block, 16^3 voxels each, in Morton order
BLOCK = 1 << BLOCK_BITS


@nb.njit(**JIT)
def band_voxels(u, irad2, rad, ostart, bkey, bstart, cand, cap_limit):  # pragma: no cover - compiled
    """The band: every voxel within its points' radius, plus the 8 corners of every occupied cell.

    ``u``: (M, 3) grid coordinates sorted by cell (Morton order); ``irad2``/``rad``: (M,) inverse
    squared and plain band radius of every point in grid units; ``ostart``: (C + 1,) point ranges of
    the occupied cells. Every voxel v gets its ``foot``, the nearest point, and
    q2 = |u_foot - v|^2 / rad_foot^2 (its squared *depth ratio*); v is in the band ("marchable")
    when q2 <= 1. Corners of occupied cells outside the band are kept with q2 > 1 only so that every
    cell's corners can be found.

    Voxels are produced block by block (blocks of BLOCK^3 voxels, in Morton order): each block
    gathers the contributions of the cells within reach into a dense local table and emits its voxels
    in Morton order, so the keys come out sorted and no global hash is needed. ``bkey``/``bstart``:
    the occupied blocks (sorted Morton keys of the block coordinates) and their cell ranges;
    ``cand``: the sorted keys of every block within reach of one (see :func:`block_plan`). Returns
    (keys, q2, foot, count); count is -1 when more than ``cap_limit`` voxels would be needed.
    """
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
    rmax = 0.0
    for i in range(rad.shape[0]):
        rmax = max(rmax, rad[i])
    ext = int(np.floor(rmax))
    reach_blocks = (ext + 1 + BLOCK - 1) // BLOCK
    lut = np.empty(BLOCK, np.int64)  # local Morton spread of a coordinate
    for t in range(BLOCK):
        lut[t] = np.int64(_split3(t))
    dq = np.empty(nb3, np.float64)  # squared distance to the nearest point, then q2
    df = np.empty(nb3, np.int32)
    dc = np.zeros(nb3, np.uint8)
    cap = max(1024, 2 * u.shape[0])
    keys = np.empty(cap, np.int64)
    qo = np.empty(cap, np.float32)
    fo = np.empty(cap, np.int32)
    count = 0
    for t in range(cand.shape[0]):
        blk = cand[t]
        bx, by, bz = unmorton(blk)
        x0 = bx * BLOCK
        y0 = by * BLOCK
        z0 = bz * BLOCK
        for li in range(nb3):  # (not dq[:] = ...: a slice is a view, reference counted per block)
            dq[li] = np.inf
            dc[li] = 0
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
                                # the z range where some point of the cell is within its radius
                                zlo = np.inf
                                zhi = -np.inf
                                for i in range(p0, p1):
                                    ex = u[i, 0] - x
                                    ey = u[i, 1] - y
                                    rest = rad[i] * rad[i] - ex * ex - ey * ey
                                    if rest >= 0.0:
                                        w = np.sqrt(rest)
                                        zlo = min(zlo, u[i, 2] - w)
                                        zhi = max(zhi, u[i, 2] + w)
                                za = int(np.ceil(zlo)) if zlo <= zhi else cz + 2
                                zb = int(np.floor(zhi)) if zlo <= zhi else cz - 1
                                corner = (x == cx or x == cx + 1) and (y == cy or y == cy + 1)
                                if corner:
                                    za = min(za, cz)
                                    zb = max(zb, cz + 1)
                                za = max(za, z0)
                                zb = min(zb, z0 + BLOCK - 1)
                                lxy = lut[x - x0] | (lut[y - y0] << 1)
                                for z in range(za, zb + 1):
                                    d2 = np.inf
                                    foot = p0
                                    li = lxy | (lut[z - z0] << 2)
                                    for i in range(p0, p1):
                                        ex = u[i, 0] - x
                                        ey = u[i, 1] - y
                                        ez = u[i, 2] - z
                                        e2 = ex * ex + ey * ey + ez * ez
                                        if e2 < d2:
                                            d2 = e2
                                            foot = i
                                    if d2 < dq[li] or (d2 == dq[li] and foot < df[li]):
                                        dq[li] = d2
                                        df[li] = foot
                                    if corner and (z == cz or z == cz + 1):
                                        dc[li] = 1
                                    touched = True
        if not touched:
            continue
        base = blk << (3 * BLOCK_BITS)
        for li in range(nb3):
            if dq[li] == np.inf:
                continue
            f = df[li]
            q2 = dq[li] * irad2[f]
            dq[li] = q2
            if q2 <= 1.0 or dc[li] == 1:
                if count == cap:
                    cap *= 2
                    keys = np.concatenate((keys, np.empty(cap - count, np.int64)))
                    qo = np.concatenate((qo, np.empty(cap - count, np.float32)))
                    fo = np.concatenate((fo, np.empty(cap - count, np.int32)))
                keys[count] = base | li
                qo[count] = dq[li]
                fo[count] = df[li]
                count += 1
                if count > cap_limit:
                    return keys, qo, fo, -1
    return keys[:count].copy(), qo[:count].copy(), fo[:count].copy(), count


_AXIS_BITS = (_M5, _M5 << np.uint64(1), _M5 << np.uint64(2))  # the Morton bits of x, y, z


@nb.njit(**INLINE)
def find_after(keys, i, key):  # pragma: no cover - compiled
    """The index of ``key`` in the sorted ``keys``, known to lie after position ``i`` (-1: absent):
    steps of 1, 2, 4, ... from i, then a binary search in the last step (a neighbour's key is
    usually a few positions away in Morton order: cache lines already read, no hash table)."""
    n = keys.shape[0]
    lo = i + 1  # (keys[lo - 1] < key throughout)
    step = 1
    hi = lo
    while hi < n and keys[hi] < key:
        lo = hi + 1
        hi = lo + step
        step *= 2
    lo += lower_bound(keys[lo:min(hi, n)], key)
    return lo if lo < n and keys[lo] == key else -1


@nb.njit(**JIT)
def neighbour_table(keys):  # pragma: no cover - compiled
    """The 6-neighbour table (-x, +x, -y, +y, -z, +z; -1 = absent) of the sorted voxel ``keys``.

    Only the + neighbours are looked up (the key one step up an axis: that axis's interleaved
    bits incremented in place, a larger key: searched after the voxel's own position, with no
    hash table beside the table: 4 bytes per slot, 1.5-3 slots per voxel, at the band's peak);
    each found pair fills both directions."""
    v = keys.shape[0]
    nbr = np.full((v, 6), -1, np.int32)
    for i in range(v):
        k = np.uint64(keys[i])
        for ax in range(3):
            m = _AXIS_BITS[ax]
            up = ((k | ~m) + np.uint64(1)) & m
            if up == np.uint64(0):
                continue  # the last coordinate: nothing above it
            j = find_after(keys, np.int64(i), np.int64(up | (k & ~m)))
            if j >= 0:
                nbr[i, 2 * ax + 1] = j
                nbr[j, 2 * ax] = i
    return nbr


@nb.njit(**JIT)
def coarse_runs(keys, cs, levels):  # pragma: no cover - compiled
    """Point ranges of coarse cells (2^j voxels a side, j = 1..levels) for ball queries.

    Points are sorted by the Morton key of their voxel cell, and the Morton key of the coarse cell
    of side 2^j is the fine key >> 3j, so every coarse cell is one contiguous range of points.
    Returns the runs' keys ((coarse key << 3) | j) with an index hash over them, and the runs'
    start and end.
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
    rkey = np.empty(nrun, np.int64)
    rstart = np.empty(nrun, np.int32)
    rend = np.empty(nrun, np.int32)
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
                    rkey[r] = (ck << 3) | j
                rend[r] = cs[v + 1]
    return rkey, index_hash(rkey), rstart, rend


# the 27 cells around a query's cell, nearest first (own cell, 6 faces, 12 edges, 8 corners), so
# that the k nearest found early prune the farther cells
_OFFS = np.array(
    sorted(
        [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)],
        key=lambda d: abs(d[0]) + abs(d[1]) + abs(d[2]),
    ),
    dtype=np.int64,
)


@nb.njit(**INLINE)
def cell_gap2(px, py, pz, fx, fy, fz, dx, dy, dz):  # pragma: no cover - compiled
    """Squared distance from the point (px, py, pz) in cell (fx, fy, fz) (grid units) to the box of
    the neighbour cell (fx + dx, fy + dy, fz + dz), with dx, dy, dz in -1..1."""
    g = 0.0
    if dx < 0:
        g += (px - fx) ** 2
    elif dx > 0:
        g += (fx + 1 - px) ** 2
    if dy < 0:
        g += (py - fy) ** 2
    elif dy > 0:
        g += (fy + 1 - py) ** 2
    if dz < 0:
        g += (pz - fz) ** 2
    elif dz > 0:
        g += (fz + 1 - pz) ** 2
    return g


@nb.njit(**JIT)
def kth_neighbour(u, ostart, cell_keys, queries, k):  # pragma: no cover - compiled
    """For each query point (grid coordinates, cell size 1): the distance to its k-th nearest point
    among ``u`` (sorted by cell; ``ostart`` the cells' ranges, ``cell_keys`` their Morton keys),
    searched in the 27 cells around it, and whether that is certain (the k-th distance is at most 1,
    so no nearer point can lie outside those cells). A query that is one of the points counts itself
    at distance 0, as a k-d tree query would. Cells are visited nearest first and a cell whose box
    lies farther than the k-th distance found so far is skipped (it cannot change that distance)."""
    hidx = index_hash(cell_keys)
    nq = queries.shape[0]
    out = np.empty(nq)
    sure = np.empty(nq, np.bool_)
    best = np.empty(k)
    offs = _OFFS
    for q in range(nq):
        qx, qy, qz = queries[q, 0], queries[q, 1], queries[q, 2]
        fx = int(np.floor(qx))
        fy = int(np.floor(qy))
        fz = int(np.floor(qz))
        nk = 0
        for o in range(27):
            dx, dy, dz = offs[o, 0], offs[o, 1], offs[o, 2]
            if nk == k and cell_gap2(qx, qy, qz, fx, fy, fz, dx, dy, dz) >= best[k - 1]:
                continue
            x, y, z = fx + dx, fy + dy, fz + dz
            if x < 0 or y < 0 or z < 0:
                continue
            j = hash_find(hidx, cell_keys, morton(x, y, z))
            if j < 0:
                continue
            for i in range(ostart[j], ostart[j + 1]):
                d2 = (u[i, 0] - qx) ** 2 + (u[i, 1] - qy) ** 2 + (u[i, 2] - qz) ** 2
                if nk < k:
                    t = nk
                    nk += 1
                elif d2 < best[k - 1]:
                    t = k - 1
                else:
                    continue
                while t > 0 and best[t - 1] > d2:
                    best[t] = best[t - 1]
                    t -= 1
                best[t] = d2
        if nk < k:
            out[q] = np.inf
            sure[q] = False
        else:
            out[q] = np.sqrt(best[k - 1])
            sure[q] = out[q] <= 1.0
    return out, sure


@nb.njit(**JIT)
def one_sided_cost(keys, foot, u, nin, psep, irad2, side_tol, beta):  # pragma: no cover - compiled
    """The cost of moving through each voxel of a band whose thin parts are one-sided (inf: not
    marchable). A voxel whose foot (nearest point) has a normal ``nin`` toward another sheet at
    distance ``psep`` (grid units; zero normal: not thin) is marchable only within the foot's
    radius (``irad2``: inverse squared) and on the foot's side away from that sheet: near the
    surface it may lie up to min(side_tol, 0.4 (psep - 1)) on the gap side (so that the band's
    nearest layer stays close to the surface); farther than FAR_SEP x psep from the foot it must
    lie more than OUTER_SEP x psep on the outer side (so that a slightly misjudged normal cannot let
    a voxel near the middle of a gap in). Decided by the nearest point alone, so that a neighbour's
    misjudged normal near a fold cannot fill the gap. There, the depth is counted from DEAD_ZONE of
    the nearest layer's possible offset (1 - tol), so the depth cost adds little bias."""
    nv = keys.shape[0]
    out = np.empty(nv, np.float32)
    for v in range(nv):
        f = foot[v]
        x, y, z = unmorton(keys[v])
        ex = x - u[f, 0]
        ey = y - u[f, 1]
        ez = z - u[f, 2]
        d2 = ex * ex + ey * ey + ez * ez
        q2 = d2 * irad2[f]
        if q2 > 1.0:
            out[v] = np.inf
            continue
        nx, ny, nz = nin[f, 0], nin[f, 1], nin[f, 2]
        if nx != 0.0 or ny != 0.0 or nz != 0.0:
            side = ex * nx + ey * ny + ez * nz
            far = d2 > (FAR_SEP * psep[f]) ** 2
            tol = min(side_tol, 0.4 * (psep[f] - 1.0))
            if side > (-OUTER_SEP * psep[f] if far else tol):
                out[v] = np.inf
                continue
            dd = max(np.sqrt(d2) - DEAD_ZONE * (1.0 - tol), 0.0)
            q2 = dd * dd * irad2[f]
        out[v] = np.float32(1.0 + beta * q2)
    return out


@nb.njit(**INLINE)
def _splitmix(h):  # pragma: no cover - compiled
    """splitmix64's finaliser (uint64 arithmetic, wrapping)."""
    h ^= h >> np.uint64(30)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(27)
    h *= np.uint64(0x94D049BB133111EB)
    h ^= h >> np.uint64(31)
    return h


@nb.njit(**JIT)
def hash_collisions(pts):  # pragma: no cover - compiled
    """Whether two rows of ``pts`` (N, 3) share a 64-bit hash of their coordinates: splitmix64's
    finaliser over the bits of x, then xor y's bits and mix, then z's (each coordinate + 0.0:
    -0.0 and 0.0 hash alike). Equal rows always do. An open-addressing set of the hashes (twice
    as many slots as rows) instead of a sort: one pass."""
    n = pts.shape[0]
    size = 2
    while size < 2 * n:
        size *= 2
    mask = np.uint64(size - 1)
    table = np.empty(size, np.uint64)
    used = np.zeros(size, np.bool_)
    for i in range(n):
        h = _splitmix(f64_bits(pts[i, 0] + 0.0))
        h = _splitmix(h ^ f64_bits(pts[i, 1] + 0.0))
        h = _splitmix(h ^ f64_bits(pts[i, 2] + 0.0))
        j = h & mask
        while used[j]:
            if table[j] == h:
                return True
            j = (j + np.uint64(1)) & mask
        used[j] = True
        table[j] = h
    return False
