"""Small generated surfaces for the engine tests."""

from __future__ import annotations

import numpy as np


def jittered_plane(n: int, rng: np.random.Generator, jitter: float = 0.3) -> np.ndarray:
    """About n points on the unit square (z = 0), a jittered grid like a range scan."""
    side = max(int(np.sqrt(n)), 2)
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2).astype(float)
    g += rng.uniform(-jitter, jitter, g.shape)
    g /= side
    return np.c_[g, np.zeros(len(g))]


def sphere(n: int, rng: np.random.Generator, radius: float = 1.0) -> np.ndarray:
    """n points spread evenly on a sphere (Fibonacci lattice, small jitter)."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    p = np.c_[np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)]
    p += rng.normal(0, 0.05 / np.sqrt(n), p.shape)
    return radius * p / np.linalg.norm(p, axis=1, keepdims=True)


def folded_sheet(spacing: float, gap: float, length: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Two parallel sheets z = 0 and z = gap over [0, length]^2, joined along x = 0 by a
    half-cylinder. Returns (points, sheet) with sheet = 0 (lower), 1 (upper), 2 (fold)."""
    xs = np.arange(spacing / 2, length, spacing)
    ys = np.arange(spacing / 2, length, spacing)
    X, Y = np.meshgrid(xs, ys)
    lower = np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]
    upper = np.c_[X.ravel(), Y.ravel(), np.full(X.size, gap)]
    rad = gap / 2
    na = max(int(np.pi * rad / spacing), 2)
    ang = (np.arange(na) + 0.5) / na * np.pi
    A, Yf = np.meshgrid(ang, ys)
    fold = np.c_[-rad * np.sin(A.ravel()), Yf.ravel(), rad - rad * np.cos(A.ravel())]
    pts = np.vstack([lower, upper, fold])
    sheet = np.r_[np.zeros(len(lower)), np.ones(len(upper)), np.full(len(fold), 2)].astype(int)
    return pts, sheet
