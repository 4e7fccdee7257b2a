"""Deliberately slow reference implementations the fast kernels are compared against."""

from __future__ import annotations

import heapq

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


def dijkstra(n_nodes: int, edges: list[tuple[int, int, float]], sources: list[int]) -> np.ndarray:
    """Plain Dijkstra distances from ``sources`` over an undirected weighted edge list."""
    adj: list[list[tuple[int, float]]] = [[] for _ in range(n_nodes)]
    for a, b, w in edges:
        adj[a].append((b, w))
        adj[b].append((a, w))
    dist = np.full(n_nodes, np.inf)
    heap = []
    for s in sources:
        dist[s] = 0.0
        heap.append((0.0, s))
    heapq.heapify(heap)
    while heap:
        d, u = heapq.heappop(heap)
        if d > dist[u]:
            continue
        for v, w in adj[u]:
            nd = d + w
            if nd < dist[v]:
                dist[v] = nd
                heapq.heappush(heap, (nd, v))
    return dist
