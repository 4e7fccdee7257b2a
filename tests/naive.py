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


def prefix_covering_radii(points: np.ndarray, order: np.ndarray) -> np.ndarray:
    """cr[k] = largest Euclidean distance from any point to the first k points of ``order``
    (cr[0] = inf), for every k, by inserting the points one at a time (O(N^2))."""
    pts = np.asarray(points, dtype=np.float64)
    best = np.full(pts.shape[0], np.inf)
    cr = np.empty(len(order) + 1)
    cr[0] = np.inf
    for k, q in enumerate(order):
        best = np.minimum(best, np.linalg.norm(pts - pts[q], axis=1))
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
