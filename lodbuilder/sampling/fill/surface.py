"""Local surfaces around a hole: tangent frames and a height field fitted to the hole's ring.

A hole is filled over one plane (the least-squares plane of the input points around it), as a
height field ``h(u, v)``: a thin-plate spline with a quadratic polynomial part
(:class:`scipy.interpolate.RBFInterpolator`, ``degree=2``), fitted to the ring of input points
around the hole. The quadratic part reproduces a quadric exactly (a sphere cap, a cylinder, a
saddle), the spline bends it to pass near every ring point; across the hole it is the smoothest
surface (least bending energy) that does. Coordinates are scaled by rho before the fit, so the
smoothing is in units of rho whatever the scan's units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: at most this many ring points enter a fit (a deterministic subsample beyond)
MAX_FIT_POINTS = 250
#: smoothing of the thin-plate spline, in rho units (0 would interpolate the noise exactly)
SMOOTHING = 1e-3


def tangents(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangent vectors per unit normal ((N, 3) each), a right-handed frame (t1, t2, n)."""
    n = np.atleast_2d(normals)
    # the axis least aligned with the normal, crossed with it
    axis = np.zeros_like(n)
    axis[np.arange(n.shape[0]), np.argmin(np.abs(n), axis=1)] = 1.0
    t1 = np.cross(n, axis)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return t1, t2


@dataclass
class Frame:
    """A plane: ``origin`` and the orthonormal ``t1``, ``t2`` (in plane) and ``normal``."""

    origin: np.ndarray
    t1: np.ndarray
    t2: np.ndarray
    normal: np.ndarray

    @classmethod
    def of(cls, origin: np.ndarray, normal: np.ndarray) -> Frame:
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        t1, t2 = tangents(n[None, :])
        return cls(np.asarray(origin, dtype=np.float64), t1[0], t2[0], n)

    def uv(self, points: np.ndarray) -> np.ndarray:
        d = points - self.origin
        return np.column_stack([d @ self.t1, d @ self.t2])

    def height(self, points: np.ndarray) -> np.ndarray:
        return (points - self.origin) @ self.normal

    def lift(self, uv: np.ndarray, h: np.ndarray) -> np.ndarray:
        return (
            self.origin
            + uv[:, :1] * self.t1
            + uv[:, 1:2] * self.t2
            + np.asarray(h)[:, None] * self.normal
        )


def plane_normal(points: np.ndarray, near: np.ndarray) -> np.ndarray:
    """Unit normal of the least-squares plane of ``points``, oriented like ``near``."""
    c = points - points.mean(axis=0)
    _, vec = np.linalg.eigh(c.T @ c)
    n = vec[:, 0]
    return n if float(n @ near) >= 0 else -n


def _rbf(uv: np.ndarray, h: np.ndarray, degree: int = 2):
    from scipy.interpolate import RBFInterpolator

    return RBFInterpolator(uv, h, kernel="thin_plate_spline", degree=degree, smoothing=SMOOTHING)


class HeightField:
    """``h(u, v)`` over a hole: thin-plate spline + quadratic polynomial fitted to ring points.

    ``uv`` (M, 2) and ``h`` (M,) are in scan units; ``scale`` (rho) normalises them for the fit.
    """

    def __init__(
        self, uv: np.ndarray, h: np.ndarray, scale: float, inner: np.ndarray | None = None
    ) -> None:
        if inner is None:
            inner = np.ones(uv.shape[0], dtype=bool)
        if uv.shape[0] > MAX_FIT_POINTS:
            keep = np.linspace(0, uv.shape[0] - 1, MAX_FIT_POINTS).round().astype(np.int64)
            uv, h, inner = uv[keep], h[keep], inner[keep]
        self.scale = float(scale)
        self._uv, self._h, self._inner = uv / self.scale, h / self.scale, inner
        self._f = _rbf(self._uv, self._h)
        self._cv: float | None = None

    @property
    def cv(self) -> float:
        """RMS error (scan units) of predicting the inner ring points (``inner``: those next to
        the hole) of each sixth of the ring (angular sectors around its centroid) from a fit to
        the other five sixths: how well the surface bridges a gap as wide as the hole, where it
        matters. Computed on first use (six more fits)."""
        if self._cv is None:
            self._cv = self._sector_error(self._uv, self._h, self._inner) * self.scale
        return self._cv

    @staticmethod
    def _sector_error(uv: np.ndarray, h: np.ndarray, inner: np.ndarray, sectors: int = 6) -> float:
        c = uv - uv.mean(axis=0)
        sec = np.floor((np.arctan2(c[:, 1], c[:, 0]) + np.pi) / (2 * np.pi) * sectors)
        sec = np.minimum(sec.astype(np.int64), sectors - 1)
        err = []
        for s in range(sectors):
            out = sec == s
            test = out & inner
            if not test.any() or (~out).sum() < 12:
                continue
            train = np.flatnonzero(~out)
            if train.size > MAX_FIT_POINTS // 2:
                train = train[
                    np.linspace(0, train.size - 1, MAX_FIT_POINTS // 2).round().astype(np.int64)
                ]
            f = _rbf(uv[train], h[train])
            err.append(f(uv[test]) - h[test])
        if not err:
            return float("inf")
        e = np.concatenate(err)
        return float(np.sqrt(np.mean(e * e)))

    def __call__(self, uv: np.ndarray) -> np.ndarray:
        if uv.shape[0] == 0:
            return np.zeros(0)
        return self._f(uv / self.scale) * self.scale

    def normals(self, uv: np.ndarray, frame: Frame) -> np.ndarray:
        """(M, 3) unit normals of the height field at ``uv`` (central differences)."""
        e = 0.05 * self.scale
        du, dv = np.array([e, 0.0]), np.array([0.0, e])
        m = uv.shape[0]
        h = self(np.concatenate([uv + du, uv - du, uv + dv, uv - dv]))
        hu = (h[:m] - h[m : 2 * m]) / (2 * e)
        hv = (h[2 * m : 3 * m] - h[3 * m :]) / (2 * e)
        n = frame.normal - hu[:, None] * frame.t1 - hv[:, None] * frame.t2
        return n / np.linalg.norm(n, axis=1, keepdims=True)
