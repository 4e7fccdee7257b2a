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
    """n points spread evenly on a sphere (:func:`fibonacci_sphere`, small jitter)."""
    p = fibonacci_sphere(n)
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


# ---- surfaces with analytic geodesic distances (the accuracy suite and tools/bench_accuracy.py) ----


def plane_patch(half: float, spacing: float, rng: np.random.Generator, jitter: float = 0.3) -> np.ndarray:
    """A jittered grid of the square [-half, half]^2 (z = 0) at the given spacing."""
    t = np.arange(-half, half + 0.5 * spacing, spacing)
    g = np.stack(np.meshgrid(t, t), -1).reshape(-1, 2)
    g = g + rng.uniform(-jitter, jitter, g.shape) * spacing
    return np.c_[g, np.zeros(len(g))]


def sphere_points(radius: float, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """About 4 pi R^2 / spacing^2 points spread evenly on a sphere of the given radius."""
    n = max(int(round(4 * np.pi * radius**2 / spacing**2)), 4)
    return sphere(n, rng, radius)


def cylinder_points(
    radius: float, length: float, spacing: float, rng: np.random.Generator, jitter: float = 0.3
) -> np.ndarray:
    """A jittered (angle, height) grid on the cylinder x^2 + y^2 = R^2, 0 <= z <= length."""
    na = max(int(round(2 * np.pi * radius / spacing)), 8)
    nz = max(int(round(length / spacing)), 2)
    a, z = np.meshgrid(np.arange(na) + 0.5, np.arange(nz) + 0.5)
    a = (a.ravel() + rng.uniform(-jitter, jitter, a.size)) * 2 * np.pi / na
    z = (z.ravel() + rng.uniform(-jitter, jitter, z.size)) * length / nz
    return np.c_[radius * np.cos(a), radius * np.sin(a), z]


def geodesic_plane(points: np.ndarray, src: int) -> np.ndarray:
    return np.linalg.norm(points - points[src], axis=1)


def geodesic_sphere(points: np.ndarray, src: int, radius: float) -> np.ndarray:
    c = points @ points[src] / (np.linalg.norm(points, axis=1) * np.linalg.norm(points[src]))
    return radius * np.arccos(np.clip(c, -1.0, 1.0))


def geodesic_cylinder(points: np.ndarray, src: int, radius: float) -> np.ndarray:
    """Geodesic on the cylinder of the z axis: unrolled, it is a straight line."""
    a = np.arctan2(points[:, 1], points[:, 0])
    da = np.abs(a - a[src])
    da = np.minimum(da, 2 * np.pi - da)
    return np.hypot(radius * da, points[:, 2] - points[src, 2])


def unfold_folded(points: np.ndarray, gap: float, length: float) -> np.ndarray:
    """(N, 2) coordinates of ``lodbuilder.datasets.folded_sheet`` laid flat.

    The sheet is developable and unfolds to the rectangle [0, 2 length + pi gap / 2] x [0, width],
    which is convex, so the geodesic distance on the sheet is the Euclidean distance here."""
    r = gap / 2
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    s = np.where(z < r, x, length + np.pi * r + (length - x))
    mid = x > length
    s[mid] = length + r * np.arctan2(x[mid] - length, r - z[mid])
    return np.column_stack([s, y])


def geodesic_folded(points: np.ndarray, src: int, gap: float, length: float) -> np.ndarray:
    u = unfold_folded(points, gap, length)
    return np.linalg.norm(u - u[src], axis=1)


def fibonacci_sphere(n: int, radius: float = 1.0) -> np.ndarray:
    """(n, 3) points spread evenly over a sphere (the Fibonacci spiral): deterministic."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return radius * np.c_[np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)]


def accordion(n: int, sheets: int, gap: float, length: float = 1.0, width: float = 1.0, seed: int = 0):
    """A stack of ``sheets`` parallel sheets z = k gap over [0, length] x [0, width], joined by
    half-cylinders of radius gap / 2 alternately along x = length and x = 0 (an accordion), n
    random points. Returns (points, uv): uv are the points laid flat on the rectangle
    [0, sheets length + (sheets - 1) pi gap / 2] x [0, width], which is convex, so the geodesic
    distance on the stack is the Euclidean distance there."""
    r = gap / 2
    arc = np.pi * r
    rng = np.random.default_rng(seed)
    s = rng.random(n) * (sheets * length + (sheets - 1) * arc)
    y = rng.random(n) * width
    k = np.minimum((s // (length + arc)).astype(int), sheets - 1)
    t = s - k * (length + arc)
    forward = k % 2 == 0  # sheet k runs toward +x when k is even
    pts = np.column_stack([np.where(forward, t, length - t), y, k * gap])
    fold = t >= length
    a = (t[fold] - length) / r  # the angle around the fold, 0..pi
    pts[fold, 0] = np.where(forward[fold], length + r * np.sin(a), -r * np.sin(a))
    pts[fold, 2] = k[fold] * gap + r - r * np.cos(a)
    return pts, np.column_stack([s, y])
