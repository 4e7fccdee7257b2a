"""Local surfaces around a hole: tangent frames and a height field fitted to the hole's ring.

A hole is filled over one plane (the least-squares plane of the input points around it), as a
height field ``h(u, v)``: a polyharmonic spline with a quadratic polynomial part
(:class:`scipy.interpolate.RBFInterpolator`, ``degree=2``), fitted to the ring of input points
around the hole. The quadratic part reproduces a quadric exactly (a sphere cap, a cylinder, a
saddle), the spline bends it to pass near every ring point. Coordinates are scaled by rho before
the fit, so the smoothing is in units of rho whatever the scan's units.

Two splines are tried (:data:`KERNELS`): the thin-plate spline (``r^2 log r``: the surface of
least bending energy, which bridges a hole as flat as the ring lets it) and the cubic spline
(``r^3``: it carries the ring's change of curvature farther into the hole, so a bump or a wave
whose flanks the ring shows is continued rather than flattened). Which one suits a hole depends
on the surface, so each hole's ring chooses by cross-validation
(:meth:`HeightField.select`): the spline that best predicts the inner ring points of each sixth
of the ring from the other five sixths, a gap as wide as the hole, is used. On issue 14's holes
(6-10 rho wide, flat surroundings) it lowered the worst holes' largest error (bunny 0.66 -> 0.29
rho, Igea 0.52 -> 0.36 and 0.50 -> 0.39 rho) and kept the thin-plate spline on frag_115's walls.
The choice is a prediction, not an oracle: on a few holes the other spline was closer (by up to
0.17 rho, on a bunny hole both miss by 0.6-0.75 rho). No spline guesses a bump or a dip that
the ring does not show. On issue 21's holes (3-10 rho wide at random enclosed points, 21 per scan)
the best of 28 fits per hole, chosen knowing the true surface (thin-plate or cubic spline at three
smoothings, quadratic and cubic polynomials, moving least squares, rings 2-4 rho wide), still
misses by up to 0.56 rho on the bunny and 0.74 rho on Igea: the errors left are the surface's
own detail inside the holes, not the choice of fit. Nor is it the height field: a 3D implicit
radial-basis surface through the ring and its normals (biharmonic or triharmonic, rings 2 and 3
rho wide), each candidate projected onto it, missed the worst holes by as much or more (Igea 0.66
-> 0.68-0.73 rho, bunny 0.54 -> 0.59-0.64). Where no height field fits at all (the bunny's ears,
whose ring folds over every plane: height fields miss by 2.2-2.5 rho), that implicit surface is
used (:mod:`lodbuilder.fill.implicit`): 0.12-0.25 rho off on those holes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: at most this many ring points enter a fit (a deterministic subsample beyond)
MAX_FIT_POINTS = 250
#: smoothing of the spline, in rho units (0 would interpolate the noise exactly)
SMOOTHING = 1e-3
#: the splines a hole chooses from (the first is the default before :meth:`HeightField.select`)
KERNELS = ("thin_plate_spline", "cubic")
#: largest share of ring normals tilted more than MAX_TILT from the hole's normal
MAX_TILTED = 0.25
MAX_TILT = math.radians(60.0)
#: a rim too tilted over its least-squares plane is laid over the least tilted plane this close
TILT_SEARCH = math.radians(60.0)


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


def least_tilted(
    normals: np.ndarray, near: np.ndarray, max_tilt: float, cone: float = math.radians(60.0)
) -> tuple[np.ndarray, float]:
    """The unit direction within ``cone`` of the unit vector ``near`` along which the smallest
    share of the unit ``normals`` (M, 3) is tilted more than ``max_tilt`` (radians), and that
    share: ``near`` itself unless another direction does better (directions on a spiral of about
    400 over the hemisphere; the one closest to ``near`` on a tie). The frame in which a hole's
    rim is most nearly a height field."""
    n = np.asarray(near, dtype=np.float64)
    n = n / np.linalg.norm(n)
    k = np.arange(400) + 0.5
    z = 1.0 - k / 400.0  # the upper hemisphere, about evenly
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    z = np.r_[1.0, z[z >= math.cos(cone)]]
    phi = np.r_[0.0, phi[: z.size - 1]]
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    t1, t2 = tangents(n[None, :])
    dirs = (r * np.cos(phi))[:, None] * t1 + (r * np.sin(phi))[:, None] * t2 + z[:, None] * n
    share = (np.abs(normals @ dirs.T) < math.cos(max_tilt)).mean(axis=0)
    best = int(np.argmin(share))  # (z decreases along the spiral: the first minimum is closest)
    return dirs[best], float(share[best])


def tilted_share(normals: np.ndarray, normal: np.ndarray) -> float:
    """Share of unit ``normals`` tilted more than :data:`MAX_TILT` from ``normal``."""
    return float((np.abs(normals @ normal) < math.cos(MAX_TILT)).mean())


def height_field_normal(
    inner_normals: np.ndarray, normal: np.ndarray, current: np.ndarray
) -> tuple[np.ndarray, bool]:
    """The hole's normal and whether to lay the grid again over it. When at most
    :data:`MAX_TILTED` of the inner ring's normals are tilted over :data:`MAX_TILT` from the
    grid's ``current`` normal: the ring's least-squares ``normal``, laid again when it is more
    than 5 degrees away and no more of the rim is tilted over it. Otherwise the direction
    within :data:`TILT_SEARCH` of ``normal`` from which the fewest are tilted (the closest to
    ``normal`` of those), over whose plane the rim is most nearly a height field (the lopsided
    rim of a hole beside a nose, a chin or a corner), laid again."""
    now = tilted_share(inner_normals, current)
    if now <= MAX_TILTED:  # (never to a plane over which more of the rim is tilted)
        moved = float(normal @ current) < math.cos(math.radians(5.0))
        return normal, moved and tilted_share(inner_normals, normal) <= now
    best, share = least_tilted(inner_normals, normal, MAX_TILT, TILT_SEARCH)
    return (best if share < tilted_share(inner_normals, normal) else normal), True


def plane_normal(points: np.ndarray, near: np.ndarray) -> np.ndarray:
    """Unit normal of the least-squares plane of ``points``, oriented like ``near``."""
    c = points - points.mean(axis=0)
    _, vec = np.linalg.eigh(c.T @ c)
    n = vec[:, 0]
    return n if float(n @ near) >= 0 else -n


def _rbf(uv: np.ndarray, h: np.ndarray, degree: int = 2, kernel: str = KERNELS[0]):
    from scipy.interpolate import RBFInterpolator

    return RBFInterpolator(uv, h, kernel=kernel, degree=degree, smoothing=SMOOTHING)


class HeightField:
    """``h(u, v)`` over a hole: a spline + quadratic polynomial fitted to ring points.

    ``uv`` (M, 2) and ``h`` (M,) are in scan units; ``scale`` (rho) normalises them for the fit.
    ``kernel`` is one of :data:`KERNELS` (the thin-plate spline unless :meth:`select` chose).
    """

    def __init__(
        self,
        uv: np.ndarray,
        h: np.ndarray,
        scale: float,
        inner: np.ndarray | None = None,
        kernel: str = KERNELS[0],
    ) -> None:
        if inner is None:
            inner = np.ones(uv.shape[0], dtype=bool)
        #: the whole ring, over the plane (``ring_uv``) and its heights (scan units)
        self.ring_uv, self.ring_h = uv, h
        near = h[inner] if inner.any() else h
        #: the heights the inner ring spans (scan units)
        self.inner_heights = (float(near.min()), float(near.max())) if near.size else (0.0, 0.0)
        if uv.shape[0] > MAX_FIT_POINTS:
            keep = np.linspace(0, uv.shape[0] - 1, MAX_FIT_POINTS).round().astype(np.int64)
            uv, h, inner = uv[keep], h[keep], inner[keep]
        self.scale = float(scale)
        self._uv, self._h, self._inner = uv / self.scale, h / self.scale, inner
        self.kernel = kernel
        self._f = _rbf(self._uv, self._h, kernel=kernel)
        self._cv: dict[str, float] = {}

    @property
    def cv(self) -> float:
        """RMS error (scan units) of predicting the inner ring points (``inner``: those next to
        the hole) of each sixth of the ring (angular sectors around its centroid) from a fit to
        the other five sixths, with this field's spline: how well the surface bridges a gap as
        wide as the hole, where it matters. Computed on first use (six more fits)."""
        return self.cv_of(self.kernel)

    def cv_of(self, kernel: str) -> float:
        """:attr:`cv` with the spline ``kernel`` (one of :data:`KERNELS`)."""
        if kernel not in self._cv:
            err = self._sector_error(self._uv, self._h, self._inner, kernel=kernel)
            self._cv[kernel] = err * self.scale
        return self._cv[kernel]

    def select(self) -> bool:
        """Use the spline of :data:`KERNELS` with the smallest :attr:`cv` (the first on a tie).
        True when that changed the surface."""
        best = min(KERNELS, key=self.cv_of)
        if best == self.kernel:
            return False
        self.kernel = best
        self._f = _rbf(self._uv, self._h, kernel=best)
        return True

    @staticmethod
    def _sector_error(
        uv: np.ndarray,
        h: np.ndarray,
        inner: np.ndarray,
        sectors: int = 6,
        kernel: str = KERNELS[0],
    ) -> float:
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
            f = _rbf(uv[train], h[train], kernel=kernel)
            err.append(f(uv[test]) - h[test])
        if not err:
            return float("inf")
        e = np.concatenate(err)
        return float(np.sqrt(np.mean(e * e)))

    def overshoot(self, heights: np.ndarray) -> float:
        """How far ``heights`` (scan units) leave the range of the inner ring's heights
        (:attr:`inner_heights`): 0 where they stay within it."""
        if heights.size == 0:
            return 0.0
        lo, hi = self.inner_heights
        return float(max(0.0, heights.max() - hi, lo - heights.min()))

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
