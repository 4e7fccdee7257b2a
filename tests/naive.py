"""Deliberately slow reference implementations the fast kernels are compared against."""

from __future__ import annotations

import numpy as np


def naive_euclidean_fps(
    points: np.ndarray, seeds: list[int], cost: np.ndarray | None = None,
    timed: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact Euclidean farthest point ordering in O(N^2) NumPy (with ``cost``: a pair's distance
    scaled by the mean of the two points' costs).

    ``timed`` = (indices, keys): points never chosen as the farthest; each joins (radius: its key)
    as soon as the largest distance of the other points is at most its key (by decreasing key,
    ties in the given order; parent -1), those left at the end come last.

    Returns (order, radius, parent) with radius = inf and parent = -1 for seeds; ties go to the
    lowest input index.
    """
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    c = np.ones(n) if cost is None else np.asarray(cost, dtype=np.float64)
    d = np.full(n, np.inf)
    lab = np.full(n, -1, dtype=np.int64)
    done = np.zeros(n, dtype=bool)
    is_timed = np.zeros(n, dtype=bool)
    pending: list[tuple[int, float]] = []
    if timed is not None:
        srt = np.argsort(-np.asarray(timed[1], dtype=np.float64), kind="stable")
        pending = [(int(timed[0][j]), float(timed[1][j])) for j in srt]
        is_timed[np.asarray(timed[0], dtype=np.int64)] = True
    order, radius, parent = [], [], []
    for k in range(n):
        if k < len(seeds):
            q, rq, pq = seeds[k], np.inf, -1
        else:
            while pending and done[pending[0][0]]:
                pending.pop(0)
            masked = np.where(done | is_timed, -1.0, d)
            q = int(np.argmax(masked))
            if pending and (masked[q] < 0 or pending[0][1] >= masked[q]):
                q, rq = pending.pop(0)
                pq = -1
            elif masked[q] < 0:
                break
            else:
                rq, pq = float(d[q]), int(lab[q])
        order.append(q)
        radius.append(rq)
        parent.append(pq)
        done[q] = True
        dq = np.linalg.norm(pts - pts[q], axis=1) * 0.5 * (c + c[q])
        closer = (dq < d) & ~done
        d[closer] = dq[closer]
        lab[closer] = k
    return np.array(order), np.array(radius), np.array(parent)


def covering_radius(points: np.ndarray, kept: np.ndarray) -> float:
    """Largest Euclidean distance from any point to its nearest kept point (brute force)."""
    pts = np.asarray(points, dtype=np.float64)
    best = np.full(pts.shape[0], np.inf)
    for q in np.asarray(kept):
        best = np.minimum(best, np.linalg.norm(pts - pts[q], axis=1))
    return float(best.max())


def naive_band_voxels(points: np.ndarray, h: float, r: float, origin: np.ndarray) -> set[tuple[int, int, int]]:
    """Integer coordinates of every voxel centre origin + h * (i, j, k) within r of some point."""
    out: set[tuple[int, int, int]] = set()
    ext = int(np.ceil(r / h)) + 1
    for p in np.asarray(points, dtype=np.float64):
        c = np.floor((p - origin) / h).astype(int)
        for dx in range(-ext, ext + 2):
            for dy in range(-ext, ext + 2):
                for dz in range(-ext, ext + 2):
                    v = c + (dx, dy, dz)
                    if np.linalg.norm(origin + h * v - p) <= r:
                        out.add(tuple(int(x) for x in v))
    return out


def naive_farthest_insert(
    candidates: np.ndarray, existing: np.ndarray, stop: float
) -> tuple[list[int], list[float]]:
    """Farthest point insertion of candidates among existing points, one candidate at a time,
    recomputing every distance from scratch: (picked indices, insertion distances)."""
    cand = np.asarray(candidates, dtype=np.float64)
    picked: list[int] = []
    radii: list[float] = []
    while True:
        have = np.concatenate([np.asarray(existing, dtype=np.float64).reshape(-1, 3), cand[picked]])
        best, best_d = -1, -1.0
        for i in range(cand.shape[0]):
            d = float(np.sqrt(((have - cand[i]) ** 2).sum(axis=1)).min()) if have.size else np.inf
            if d > best_d:
                best, best_d = i, d
        if best < 0 or not best_d > stop:
            return picked, radii
        picked.append(best)
        radii.append(best_d)


def naive_euclidean_fps_cost(points: np.ndarray, seeds: list[int], cost: np.ndarray):
    """Exact farthest point ordering where a pair's distance is scaled by the mean of the two
    points' costs (lodbuilder's weighted Euclidean metric), in O(N^2) NumPy; ties to the lowest index."""
    return naive_euclidean_fps(points, seeds, cost=cost)


# ---- a naive marcher: the kernel's single-source march, written plainly -----------------------

SEED_RADIUS = 6.0


def _naive_update(t1s, t2s, f):
    """The upwind solution of |grad T| = f: second order on the axes where a second upwind value is
    given (inf: first order), falling back to first order when that is not upwind."""
    axes = sorted(zip(t1s, t2s, strict=True), key=lambda a: a[0])
    if any(t2 < np.inf for _, t2 in axes):
        sa = sb = sc = 0.0
        sol = np.inf
        ok = True
        for t1, t2 in axes:
            if t1 >= sol:
                break
            al, be = (2.25, (4.0 * t1 - t2) / 3.0) if t2 < np.inf else (1.0, t1)
            na, nb, nc = sa + al, sb + al * be, sc + al * be * be
            disc = nb * nb - na * (nc - f * f)
            if disc < 0.0:
                ok = False
                break
            t = (nb + np.sqrt(disc)) / na
            if t < t1:
                ok = False
                break
            sa, sb, sc, sol = na, nb, nc, t
        if ok and sol < np.inf:
            return sol
    a, b, c = (t for t, _ in axes)
    t = a + f
    if t <= b:
        return t
    t = 0.5 * (a + b + np.sqrt(2.0 * f * f - (a - b) ** 2))
    if t <= c:
        return t
    s, q = a + b + c, a * a + b * b + c * c
    return (s + np.sqrt(max(s * s - 3.0 * (q - f * f), 0.0))) / 3.0


def naive_band_march(band, source: int) -> np.ndarray:
    """Point values (cell order, grid units) of one march from point ``source`` (cell order) in a
    :class:`lodbuilder.sampling.band.Band` without thin parts, with the kernel's rules written out
    plainly: exact values in the line-of-sight ball, frozen; second-order upwind updates where both
    upwind voxels are accepted; a point's value min over its marchable corners of T + |p - v|, or a
    Taylor step along the front at its nearest marchable corner (never below the straight
    distance). A dictionary of coordinates instead of the neighbour table, heapq with lazy entries
    instead of the indexed heap. As in the kernel, T is float32 and equal T pop in voxel order (the
    heap's entries are (T, voxel)): two tied voxels in line, accepted in the other order, switch a
    neighbour's second-order update on or off."""
    import heapq

    u = band.u
    coord = [tuple(int(x) for x in c) for c in band.coord]
    index = {c: i for i, c in enumerate(coord)}
    vcost = band.vcost.astype(np.float64)
    march = np.isfinite(vcost)
    nv = len(coord)
    cells = {}
    for v in range(nv):
        if band.cs[v + 1] > band.cs[v]:
            cells[coord[v]] = range(band.cs[v], band.cs[v + 1])

    def vox(c):
        return index.get(c, -1)

    s = u[source]
    anchor = tuple(int(x) for x in np.floor(s))
    corner_of = [tuple(anchor[a] + ((c >> a) & 1) for a in range(3)) for c in range(8)]
    v0 = vox(tuple(anchor[a] + (1 if s[a] - anchor[a] >= 0.5 else 0) for a in range(3)))
    if v0 < 0 or not march[v0]:
        v0 = next(vox(c) for c in corner_of if vox(c) >= 0 and march[vox(c)])
    c0 = np.array(coord[v0])
    T = np.full(nv, np.inf, dtype=np.float32)
    accepted = np.zeros(nv, dtype=bool)
    dq = np.full(u.shape[0], np.inf)
    # the ball: marchable voxels within SEED_RADIUS of the sample, connected to v0 inside it
    ball, todo = {v0}, [v0]
    while todo:
        v = todo.pop()
        for a in range(3):
            for step in (-1, 1):
                c = list(coord[v])
                c[a] += step
                w = vox(tuple(c))
                if w >= 0 and march[w] and w not in ball and np.linalg.norm(s - np.array(c)) <= SEED_RADIUS:
                    ball.add(w)
                    todo.append(w)
    seen = {}
    heap = []
    for v in sorted(ball, key=lambda v: np.linalg.norm(np.array(coord[v]) - c0)):
        c = np.array(coord[v])
        if v == v0:
            ok = True
        else:
            d = np.linalg.norm(c - c0)
            back = tuple(int(x) for x in np.floor(c - (c - c0) / d + 0.5))
            ok = seen.get(vox(back), False)
        seen[v] = ok
        if not ok:
            continue
        T[v] = np.float32(np.linalg.norm(s - c) * 0.5 * (1.0 + vcost[v]))
        accepted[v] = True
        heapq.heappush(heap, (float(T[v]), v))
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    for p in cells.get((c[0] - dx, c[1] - dy, c[2] - dz), ()):
                        dq[p] = min(dq[p], np.linalg.norm(u[p] - s))
    done = np.zeros(nv, dtype=bool)
    while heap:
        t, v = heapq.heappop(heap)
        if done[v] or t != float(T[v]):
            continue
        done[v] = True
        accepted[v] = True
        c = coord[v]
        tv = float(T[v])
        g = np.zeros(3)
        for a in range(3):
            lo = list(c)
            hi = list(c)
            lo[a] -= 1
            hi[a] += 1
            ta = float(T[vox(tuple(lo))]) if vox(tuple(lo)) >= 0 else np.inf
            tb = float(T[vox(tuple(hi))]) if vox(tuple(hi)) >= 0 else np.inf
            if ta < tb and ta < tv:
                g[a] = tv - ta
            elif tb < tv:
                g[a] = tb - tv
        gn = np.linalg.norm(g)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    for p in cells.get((c[0] - dx, c[1] - dy, c[2] - dz), ()):
                        e = u[p] - np.array(c)
                        if gn > 0 and band.near[p] == dx + 2 * dy + 4 * dz:
                            val = max(tv + float(g @ e) / gn, float(np.linalg.norm(u[p] - s)))
                        else:
                            val = tv + float(np.linalg.norm(e))
                        dq[p] = min(dq[p], val)
        for a in range(3):
            for step in (-1, 1):
                cm = list(c)
                cm[a] += step
                m = vox(tuple(cm))
                if m < 0 or accepted[m] or not march[m]:
                    continue
                t1s, t2s = [], []
                for b in range(3):
                    side = []
                    for sb in (-1, 1):
                        cn = list(cm)
                        cn[b] += sb
                        n1 = vox(tuple(cn))
                        side.append((float(T[n1]) if n1 >= 0 else np.inf, n1, sb))
                    t1, best, nb_dir = side[0] if side[0][0] <= side[1][0] else side[1]
                    t2 = np.inf
                    if t1 < np.inf and accepted[best]:
                        c2 = list(coord[best])
                        c2[b] += nb_dir
                        n2 = vox(tuple(c2))
                        if n2 >= 0 and accepted[n2] and float(T[n2]) <= t1:
                            t2 = float(T[n2])
                    t1s.append(t1)
                    t2s.append(t2)
                tn = np.float32(_naive_update(t1s, t2s, vcost[m]))
                if tn < T[m]:
                    T[m] = tn
                    heapq.heappush(heap, (float(tn), m))
    dq[source] = 0.0
    return dq


def prefix_covering_radii(points: np.ndarray, order: np.ndarray, targets: np.ndarray | None = None) -> np.ndarray:
    """cr[k] = largest Euclidean distance from any point (of ``targets`` when given) to the first k
    points of ``order`` (cr[0] = inf), for every k, by inserting the points one at a time (O(N^2))."""
    pts = np.asarray(points, dtype=np.float64)
    tgt = pts if targets is None else pts[targets]
    best = np.full(tgt.shape[0], np.inf)
    cr = np.empty(len(order) + 1)
    cr[0] = np.inf
    for k, q in enumerate(order):
        best = np.minimum(best, np.linalg.norm(tgt - pts[q], axis=1))
        cr[k + 1] = best.max()
    return cr


def prefix_spacings(points: np.ndarray, order: np.ndarray) -> np.ndarray:
    """sp[k] = smallest distance between two of the first k points of ``order`` (inf for k < 2)."""
    pts = np.asarray(points, dtype=np.float64)[np.asarray(order)]
    sp = np.full(len(order) + 1, np.inf)
    run = np.inf
    for k in range(1, len(order)):
        run = min(run, float(np.linalg.norm(pts[:k] - pts[k], axis=1).min()))
        sp[k + 1] = run
    return sp


def nearest_earlier(points: np.ndarray, order: np.ndarray) -> np.ndarray:
    """e[k] = distance from the k-th point of ``order`` to the nearest of the points before it
    (inf for k = 0)."""
    pts = np.asarray(points, dtype=np.float64)[np.asarray(order)]
    e = np.full(len(order), np.inf)
    for k in range(1, len(order)):
        e[k] = float(np.linalg.norm(pts[:k] - pts[k], axis=1).min())
    return e


def naive_sheet_cut(band, vcost: np.ndarray, normal: np.ndarray, sep: np.ndarray) -> np.ndarray:
    """The rule of ``lodbuilder._kernels.sheets.sheet_cut`` written plainly: voxels by coordinates in
    a dict, every pair tested from scratch (``normal``, ``sep``: per point in the band's point order,
    grid units)."""
    from lodbuilder._kernels.sheets import CUT_CONE, CUT_PARALLEL, CUT_SHARE

    u = band.u
    coord = [tuple(int(c) for c in row) for row in band.coord]
    index = {c: i for i, c in enumerate(coord)}
    cells: dict[tuple[int, int, int], list[int]] = {}
    for p in range(u.shape[0]):
        cells.setdefault(tuple(int(c) for c in np.floor(u[p])), []).append(p)

    def across(e: int, o: int) -> bool:
        n = normal[e]
        if not n.any():
            return False
        d = u[o] - u[e]
        a = abs(float(d @ n))
        dist = float(np.linalg.norm(d))
        if a < CUT_SHARE * sep[e] or a < CUT_CONE * dist:
            return False
        return dist >= sep[e] or not normal[o].any() or abs(float(n @ normal[o])) >= CUT_PARALLEL

    def apart(f: int, g: int) -> bool:
        return f != g and (across(f, g) or across(g, f))

    def depth(v: int) -> float:
        return float(np.sum((np.array(coord[v]) - u[band.foot[v]]) ** 2))

    out = vcost.copy()
    for v, c in enumerate(coord):
        if not np.isfinite(vcost[v]):
            continue
        f = int(band.foot[v])
        for step in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)):
            w = index.get((c[0] + step[0], c[1] + step[1], c[2] + step[2]), -1)
            if w < 0 or not np.isfinite(vcost[w]) or not apart(f, int(band.foot[w])):
                continue
            if depth(w) < depth(v) or (depth(w) == depth(v) and w < v):
                out[v] = np.inf
        for dx in (0, -1):
            for dy in (0, -1):
                for dz in (0, -1):
                    for p in cells.get((c[0] + dx, c[1] + dy, c[2] + dz), []):
                        if apart(f, p):
                            out[v] = np.inf
    return out


def naive_seam_merge(streams: list[np.ndarray], head: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """The tiled build's merge with its seam repair, one candidate at a time with brute-force
    distances.

    ``streams``: per tile, rows (g, key, x, y, z, margin) by non-increasing key; ``head``: (h, 3)
    points accepted first (tile -1). Candidates come by the largest key (a tile row before a demoted
    one at equal keys; tiles by index, demoted rows by order of demotion). A candidate with margin
    < key (a seam point) that lies within ``alpha`` x key of an accepted seam point of another tile
    or of the head is demoted to that distance / ``alpha`` (and checked again then); the others are
    merged at their key. Returns the input index and key of every row in merged order."""
    rows = [np.asarray(s, dtype=np.float64) for s in streams]
    acc_xyz = [p for p in np.asarray(head, dtype=np.float64).reshape(-1, 3)]
    acc_tile = [-1] * len(acc_xyz)
    pos = [0] * len(rows)
    deferred: list[tuple[float, int, np.ndarray, int]] = []
    n_def = 0
    g_out, k_out = [], []
    while True:
        ks, t = -1.0, -1
        for u, r in enumerate(rows):
            if pos[u] < len(r) and r[pos[u], 1] > ks:
                ks, t = r[pos[u], 1], u
        kd = max((d[0] for d in deferred), default=-1.0)
        if ks < 0 and kd < 0:
            break
        if ks >= kd:
            x, key, tile = rows[t][pos[t]], rows[t][pos[t], 1], t
            pos[t] += 1
        else:
            j = max(range(len(deferred)), key=lambda i: (deferred[i][0], -deferred[i][1]))
            key, _, x, tile = deferred.pop(j)
        seam = x[5] < key
        if seam and alpha > 0 and np.isfinite(key):
            d = min((float(np.sqrt(((q - x[2:5]) ** 2).sum())) for q, u in zip(acc_xyz, acc_tile, strict=True)
                     if u != tile), default=np.inf)
            if d < alpha * key:
                deferred.append((d / alpha, n_def, x, tile))
                n_def += 1
                continue
        g_out.append(int(x[0]))
        k_out.append(float(key))
        if seam:
            acc_xyz.append(x[2:5])
            acc_tile.append(tile)
    return np.asarray(g_out, dtype=np.int64), np.asarray(k_out)


def naive_normal_agreement(u: np.ndarray, ostart: np.ndarray, sep: np.ndarray, nrm: np.ndarray, ball: float,
                           stride: int) -> np.ndarray:
    """The rule of ``lodbuilder._kernels.sheets.normal_agreement`` written plainly: per cell, the
    mean |cos| between its normal and those of every other thin cell whose centroid lies within
    ``ball`` x its separation (brute force over all cells), for every ``stride``-th thin cell."""
    from lodbuilder._kernels.sheets import AGREE_MIN

    cen = np.array([u[ostart[c]:ostart[c + 1]].mean(axis=0) for c in range(ostart.shape[0] - 1)])
    thin = np.flatnonzero(np.isfinite(sep))
    out = np.full(sep.shape[0], np.nan)
    for c in thin[::stride]:
        near = thin[(np.linalg.norm(cen[thin] - cen[c], axis=1) <= ball * sep[c]) & (thin != c)]
        if near.size >= AGREE_MIN:
            out[c] = np.abs(nrm[near] @ nrm[c]).mean()
    return out


def naive_stable_argsort(keys: np.ndarray) -> np.ndarray:
    """The permutation that sorts ``keys``, equal keys in index order (Python's sort, one by one)."""
    return np.array(sorted(range(len(keys)), key=lambda i: (int(keys[i]), i)), dtype=np.int64)


def naive_cover_pass(xyz: np.ndarray, rank: np.ndarray, core: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The covering pass of a tiled build's tile (``lodbuilder._kernels.tiled.cover_pass``) by brute
    force: points inserted in index order (``rank`` ascending); before point i, the covering radius
    of the core points not yet inserted by points 0..i-1 (inf before the first, 0 once none is left).

    Returns (ev_rank, ev_val): rank[i - 1] + 1 (0 for i = 0) and the radius, for every i in 0..n where
    the radius differs from the one before; and, for each core point in index order, its rank, the
    rank of its earliest nearest earlier point (-1: none) and the distance to it (inf: none)."""
    xyz = np.asarray(xyz, np.float64)
    n = xyz.shape[0]
    d = np.full(n, np.inf)  # distance of each point to points 0..i-1
    par = np.full(n, -1, np.int64)
    ev_rank, ev_val, last = [], [], -1.0
    pt = []
    for i in range(n + 1):
        pending = core.copy()
        pending[:i] = False
        cr = float(d[pending].max()) if pending.any() else 0.0
        if cr != last:
            ev_rank.append(int(rank[i - 1]) + 1 if i > 0 else 0)
            ev_val.append(cr)
            last = cr
        if i == n:
            break
        if core[i]:
            pt.append((int(rank[i]), int(par[i]), float(d[i])))
        diff = xyz - xyz[i]
        dist = np.sqrt(diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2])
        better = dist < d
        d[better], par[better] = dist[better], rank[i]
    p = np.array(pt, dtype=[("rank", "<i8"), ("parent", "<i8"), ("space", "<f8")]).reshape(-1)
    return np.array(ev_rank, np.int64), np.array(ev_val), p["rank"], p["parent"], p["space"]


def naive_hash_collisions(pts: np.ndarray) -> bool:
    """Whether two rows of ``pts`` share the 64-bit hash of ``_kernels.grid.hash_collisions``
    (splitmix64's finaliser over x's bits, then y's and z's xored in; -0.0 as 0.0), by sorting."""

    def mix(h: np.ndarray) -> np.ndarray:
        h ^= h >> np.uint64(30)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(27)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(31)
        return h

    hsh = mix((pts[:, 0] + 0.0).view(np.uint64))
    for axis in (1, 2):
        hsh ^= (pts[:, axis] + 0.0).view(np.uint64)
        mix(hsh)
    hsh.sort()
    return bool((hsh[1:] == hsh[:-1]).any())


def naive_bring_in(tseed: np.ndarray, tkey: np.ndarray, pos: int, seeds: np.ndarray, band_idx: np.ndarray,
                   keys: np.ndarray, now: float) -> tuple[np.ndarray, np.ndarray]:
    """The pending timed seeds (``tseed[pos:]``, keys ``tkey[pos:]``, non-increasing) after the
    band points ``band_idx`` get ``min(keys, now)`` as new keys (those already joined or seeds
    skipped), re-sorted by key, stably: by one array over every
    band point, as the first resumable engine did it."""
    m = int(max(tseed.max(initial=0), seeds.max(initial=0), band_idx.max(initial=0))) + 1
    where = np.full(m, -1, np.int64)
    where[tseed[pos:]] = np.arange(tseed.size - pos)
    at = where[band_idx]
    live = at >= 0
    new = tkey[pos:].copy()
    new[at[live]] = np.minimum(keys[live], now)
    srt = np.argsort(-new, kind="stable")
    return np.concatenate([tseed[:pos], tseed[pos:][srt]]), np.concatenate([tkey[:pos], new[srt]])


def naive_band_radii(cur: np.ndarray, events: list[tuple[np.ndarray, np.ndarray]], k0: int, k1: int) -> np.ndarray:
    """The largest of the tiles' covering radii at each position ``k0 .. k1``: tile t's value is
    ``cur[t]`` until its first event, then that of its last event (rank, value) at or before k."""
    vals = np.repeat(np.asarray(cur, float)[:, None], k1 - k0, axis=1)
    for t, (ranks, values) in enumerate(events):
        for r, v in zip(ranks, values, strict=True):
            vals[t, int(r) - k0:] = v
    return vals.max(axis=0) if vals.shape[0] else np.full(k1 - k0, -np.inf)
