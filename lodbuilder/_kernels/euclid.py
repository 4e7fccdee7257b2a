"""Exact Euclidean farthest point ordering (brute force, O(N * K)). Baseline and small inputs."""

from __future__ import annotations

import numba as nb
import numpy as np

from . import JIT


@nb.njit(**JIT)
def euclidean_fps_kernel(pts, seeds, k_max, cost):  # pragma: no cover - compiled
    n = pts.shape[0]
    d = np.full(n, np.inf)
    lab = np.full(n, -1, np.int64)
    order = np.empty(k_max, np.int64)
    radius = np.empty(k_max, np.float64)
    parent = np.empty(k_max, np.int64)
    done = np.zeros(n, np.bool_)
    k = 0
    while k < k_max:
        if k < seeds.shape[0]:
            q = seeds[k]
            rq = np.inf
            pq = -1
        else:
            q = -1
            best = -1.0
            for i in range(n):
                if not done[i] and d[i] > best:
                    best = d[i]
                    q = i
            rq = best
            pq = lab[q]
        order[k] = q
        radius[k] = rq
        parent[k] = pq
        done[q] = True
        for i in range(n):
            if done[i]:
                continue
            dx = pts[i, 0] - pts[q, 0]
            dy = pts[i, 1] - pts[q, 1]
            dz = pts[i, 2] - pts[q, 2]
            di = np.sqrt(dx * dx + dy * dy + dz * dz) * 0.5 * (cost[i] + cost[q])
            if di < d[i]:
                d[i] = di
                lab[i] = k
        k += 1
    return order, radius, parent
