"""Deliberately slow reference implementations the fast kernels are compared against."""

from __future__ import annotations

import numpy as np


def naive_euclidean_fps(points: np.ndarray, seeds: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact Euclidean farthest point ordering in O(N^2) NumPy.

    Returns (order, radius, parent) with radius = inf and parent = -1 for seeds; ties go to the
    lowest input index.
    """
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    d = np.full(n, np.inf)
    lab = np.full(n, -1, dtype=np.int64)
    done = np.zeros(n, dtype=bool)
    order, radius, parent = [], [], []
    for k in range(n):
        if k < len(seeds):
            q, rq, pq = seeds[k], np.inf, -1
        else:
            masked = np.where(done, -1.0, d)
            q = int(np.argmax(masked))
            rq, pq = float(d[q]), int(lab[q])
        order.append(q)
        radius.append(rq)
        parent.append(pq)
        done[q] = True
        dq = np.linalg.norm(pts - pts[q], axis=1)
        closer = dq < d
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

