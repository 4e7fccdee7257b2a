"""Scan-like synthetic surfaces for the demo, tests and benchmarks (seeded, NumPy only).

Every generator returns ``(points, normals)``: (N, 3) float64 points on the surface and unit
normals, optionally with Gaussian noise along the normal. :func:`demo_scan` wraps one in a
:class:`~lodbuilder.io.base.Scan` with colours and normals like a real scanner file.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .errors import InputError
from .io.base import Scan


def _finish(points, normals, noise, rng):
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    if noise:
        points = points + normals * rng.normal(0.0, noise, size=(points.shape[0], 1))
    return np.ascontiguousarray(points), np.ascontiguousarray(normals)


def wavy_sheet(
    n: int,
    *,
    seed: int = 0,
    noise: float = 0.0,
    size: float = 1.0,
    amplitude: float = 0.08,
    waves: float = 2.0,
):
    """A square sheet ``z = a sin(2 pi w x) cos(2 pi w y)`` of side ``size``."""
    rng = np.random.default_rng(seed)
    xy = rng.random((n, 2)) * size
    k = 2 * np.pi * waves / size
    z = amplitude * np.sin(k * xy[:, 0]) * np.cos(k * xy[:, 1])
    dzdx = amplitude * k * np.cos(k * xy[:, 0]) * np.cos(k * xy[:, 1])
    dzdy = -amplitude * k * np.sin(k * xy[:, 0]) * np.sin(k * xy[:, 1])
    pts = np.column_stack([xy, z])
    nrm = np.column_stack([-dzdx, -dzdy, np.ones(n)])
    return _finish(pts, nrm, noise, rng)


def sphere(n: int, *, seed: int = 0, noise: float = 0.0, radius: float = 0.5):
    """Uniform points on a sphere of the given radius centred at the origin."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return _finish(v * radius, v.copy(), noise, rng)


def torus(n: int, *, seed: int = 0, noise: float = 0.0, major: float = 0.5, minor: float = 0.18):
    """Area-uniform points on a torus around the z axis (rejection sampling on the tube angle)."""
    rng = np.random.default_rng(seed)
    out_u, out_v = [], []
    have = 0
    while have < n:
        m = 2 * (n - have) + 16
        u = rng.random(m) * 2 * np.pi
        v = rng.random(m) * 2 * np.pi
        accept = rng.random(m) < (major + minor * np.cos(v)) / (major + minor)
        out_u.append(u[accept])
        out_v.append(v[accept])
        have += int(accept.sum())
    u = np.concatenate(out_u)[:n]
    v = np.concatenate(out_v)[:n]
    ring = major + minor * np.cos(v)
    pts = np.column_stack([ring * np.cos(u), ring * np.sin(u), minor * np.sin(v)])
    nrm = np.column_stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)])
    return _finish(pts, nrm, noise, rng)


def folded_sheet(
    n: int,
    *,
    seed: int = 0,
    noise: float = 0.0,
    length: float = 1.0,
    width: float = 0.6,
    gap: float = 0.05,
):
    """A sheet folded over itself: two parallel layers ``gap`` apart joined by a half cylinder.

    Close in space, far along the surface: a band that is too wide bridges the layers."""
    rng = np.random.default_rng(seed)
    r = gap / 2
    arc = np.pi * r
    total = 2 * length + arc
    s = rng.random(n) * total
    y = rng.random(n) * width
    pts = np.empty((n, 3))
    nrm = np.empty((n, 3))
    low = s < length
    mid = (s >= length) & (s < length + arc)
    up = s >= length + arc
    pts[low] = np.column_stack([s[low], y[low], np.zeros(low.sum())])
    nrm[low] = [0.0, 0.0, -1.0]
    t = (s[mid] - length) / r  # angle 0..pi around the fold axis
    pts[mid] = np.column_stack([length + r * np.sin(t), y[mid], r - r * np.cos(t)])
    nrm[mid] = np.column_stack([np.sin(t), np.zeros(t.size), -np.cos(t)])
    back = s[up] - length - arc
    pts[up] = np.column_stack([length - back, y[up], np.full(up.sum(), gap)])
    nrm[up] = [0.0, 0.0, 1.0]
    return _finish(pts, nrm, noise, rng)


SURFACES: dict[str, Callable[..., tuple[np.ndarray, np.ndarray]]] = {
    "wavy": wavy_sheet,
    "sphere": sphere,
    "torus": torus,
    "folded": folded_sheet,
}


def make_surface(kind: str, n: int, *, seed: int = 0, noise: float = 0.0, **kw):
    """``(points, normals)`` of the named surface (wavy, sphere, torus, folded)."""
    if kind not in SURFACES:
        raise InputError(f"unknown surface {kind!r}; choose one of {', '.join(SURFACES)}")
    if int(n) < 1:
        raise InputError(f"n must be a positive number of points, got {n!r}")
    return SURFACES[kind](int(n), seed=seed, noise=noise, **kw)


def demo_scan(
    n: int = 20000, *, kind: str = "wavy", seed: int = 7, noise: float = 0.0005, name: str = "demo"
) -> Scan:
    """A scan-like Scan: float32-precision coordinates (as a PLY file stores them), colours by
    height and float32 normals."""
    pts, nrm = make_surface(kind, n, seed=seed, noise=noise)
    pts = pts.astype(np.float32).astype(np.float64)
    z = pts[:, 2]
    t = (z - z.min()) / max(float(np.ptp(z)), 1e-12)
    attrs = {
        "nx": nrm[:, 0].astype(np.float32),
        "ny": nrm[:, 1].astype(np.float32),
        "nz": nrm[:, 2].astype(np.float32),
        "red": np.rint(255 * t).astype(np.uint8),
        "green": np.rint(255 * (1 - np.abs(2 * t - 1))).astype(np.uint8),
        "blue": np.rint(255 * (1 - t)).astype(np.uint8),
    }
    meta = {"generator": kind, "seed": seed, "noise": noise, "n": n}
    return Scan(points=pts, attributes=attrs, name=name, source=None, reader="demo", metadata=meta)
