"""Holes that are no height field: an implicit surface over the hole's surroundings (issue 21).

Round a hole on a thin part's edge (an ear's rim) or on a strongly curved place, the surface
beyond the hole folds over any one plane: no height field fits its ring (the fits miss by 2 rho
and more). There the hole is filled from an *implicit* surface ``f(x) = 0``: a radial basis
function in 3D (the biharmonic ``|x|``, plus a linear part) through the input points around the
hole (value 0) and through points half a rho off them along their normals (values -1/2 and
+1/2 rho: the normals oriented along the surface, round the fold of a thin part:
:func:`~lodbuilder.fill.local.oriented_normals`), the classic construction of Carr et al.
(2001). ``f`` is about the signed distance near the input, and its zero set bridges the hole
whatever its shape.

The region is found on that surface itself: a cubic grid (spacing rho/4) in a ball round the
seeds; each grid cell the zero set crosses holds a surface point (the cell's crossings on its
edges, averaged, moved onto ``f = 0``); those farther than rho/2 from every input point form
regions (cells linked through faces, edges or corners). The grid is evaluated coarse to fine
(every 4 nodes, then every 2 nodes of the boxes the zero set may cross by a slope bound, then
every node of those: :func:`node_values`), which finds the same cells as evaluating every node at
under half the cost; only the cells' points that may lie farther than rho/2 from the input are
moved onto ``f = 0``. A region with a seed that stays inside
the ball is **enclosed**: the input bounds it all round on the surface (the hole's rim is a
closed loop round it). One that reaches the ball's shell runs into empty space (a border: the
surface is extrapolated beyond it) and is left open.

Each surface point stands for the area ``g^2 / (|n_x| + |n_y| + |n_z|)`` (a plane of normal n
crosses that many cells per unit area). The region is *rough* (reported, not filled) when the
fit does not predict its own surroundings: fitted without one sixth of the ring (angular
sectors round the hole, in the plane of the ring), the surface misses that sixth's points next
to the hole by more than :data:`~lodbuilder.fill.gaps.MAX_RESIDUAL` rho RMS.
"""

from __future__ import annotations

import math

import numpy as np

#: the fit's points lie this far off the input along its normals (in rho), on both sides
OFFSET = 0.5
#: at most this many input points enter a fit (each with its two offset points)
MAX_FIT_POINTS = 300
#: the radial function (``|x|``: biharmonic in 3D, the smoothest interpolant)
KERNEL = "linear"
SMOOTHING = 1e-3


def _subsample(n: int, most: int) -> np.ndarray:
    if n <= most:
        return np.arange(n)
    return np.linspace(0, n - 1, most).round().astype(np.int64)


class ImplicitSurface:
    """``f(x) = 0`` through ``points`` (M, 3) with unit ``normals`` (M, 3) oriented alike:
    ``f`` is about the signed distance (scan units) near them, positive along the normals."""

    def __init__(self, points: np.ndarray, normals: np.ndarray, scale: float) -> None:
        from scipy.interpolate import RBFInterpolator

        keep = _subsample(points.shape[0], MAX_FIT_POINTS)
        p, n = points[keep], normals[keep]
        self.scale = float(scale)
        self.origin = p.mean(axis=0)
        q = (p - self.origin) / self.scale
        x = np.concatenate([q, q + OFFSET * n, q - OFFSET * n])
        y = np.concatenate([np.zeros(len(q)), np.full(len(q), OFFSET), np.full(len(q), -OFFSET)])
        self._f = RBFInterpolator(x, y, kernel=KERNEL, degree=1, smoothing=SMOOTHING)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        if x.shape[0] == 0:
            return np.zeros(0)
        return self._f((x - self.origin) / self.scale) * self.scale

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """(N, 3) gradient of ``f`` at ``x`` (central differences, a twentieth of rho)."""
        e = 0.05 * self.scale
        m = x.shape[0]
        steps = np.concatenate([x + e * u for u in np.eye(3)] + [x - e * u for u in np.eye(3)])
        v = self(steps)
        return np.stack(
            [(v[i * m : (i + 1) * m] - v[(i + 3) * m : (i + 4) * m]) for i in range(3)], 1
        ) / (2 * e)

    def normals(self, x: np.ndarray) -> np.ndarray:
        """(N, 3) unit normals of the surface at ``x`` (along the gradient)."""
        g = self.gradient(x)
        return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-300)

    def distance(self, x: np.ndarray) -> np.ndarray:
        """(N,) first-order distance of ``x`` to the zero set, |f| / |grad f|."""
        g = np.linalg.norm(self.gradient(x), axis=1)
        return np.abs(self(x)) / np.maximum(g, 1e-12)

    def project(self, x: np.ndarray, steps: int = 2) -> np.ndarray:
        """``x`` moved onto the zero set (Newton steps along the gradient, by forward
        differences of a twentieth of rho: four evaluations of ``f`` per point and step)."""
        x = np.array(x, dtype=np.float64)
        e, m = 0.05 * self.scale, x.shape[0]
        for _ in range(steps):
            v = self(np.concatenate([x] + [x + e * u for u in np.eye(3)]))
            f = v[:m]
            g = np.stack([v[(i + 1) * m : (i + 2) * m] - f for i in range(3)], 1) / e
            g2 = np.maximum(np.einsum("ij,ij->i", g, g), 1e-12)
            x -= (f / g2)[:, None] * g
        return x


def sector_error(
    points: np.ndarray,
    normals: np.ndarray,
    test: np.ndarray,
    axes: np.ndarray,
    scale: float,
    centre: np.ndarray,
) -> float:
    """RMS distance of the ``test`` points (K, 3: those next to the hole) of each sixth round
    ``centre`` (angular sectors in the plane of the unit ``axes`` (2, 3)) to the surface fitted
    to the ``points`` (with their ``normals``) of the other five sixths: how well the fit
    bridges a gap as wide as the hole, where it matters."""

    def sectors(x: np.ndarray) -> np.ndarray:
        c = (x - centre) @ axes.T
        sec = np.floor((np.arctan2(c[:, 1], c[:, 0]) + np.pi) / (2 * np.pi) * 6)
        return np.minimum(sec.astype(np.int64), 5)

    sec, sec_test = sectors(points), sectors(test)
    err = []
    for s in range(6):
        train = np.flatnonzero(sec != s)
        if not (sec_test == s).any() or train.size < 12:
            continue
        surf = ImplicitSurface(points[train], normals[train], scale)
        err.append(surf.distance(test[sec_test == s]))
    if not err:
        return math.inf
    e = np.concatenate(err)
    return float(np.sqrt(np.mean(e * e)))


#: the grid is evaluated coarse to fine: first every COARSE[0] nodes, then every COARSE[1] nodes
#: of the boxes the zero set may cross, ..., then at every node of those (:func:`node_values`)
COARSE = (4, 2)
#: the slope bound that decides which boxes the zero set can cross: this many times the
#: steepest slope seen along the first coarse grid's edges (at least 1: ``f`` is about a distance)
LIPSCHITZ_SAFETY = 2.0


def node_values(
    surface: ImplicitSurface,
    centre: np.ndarray,
    radius: float,
    g: float,
    coarse: tuple[int, ...] = COARSE,
) -> np.ndarray:
    """``f`` at the nodes of a cubic grid (spacing ``g``, ``2 half + 1`` nodes a side, centred
    on ``centre``, ``half = ceil(radius / g)``), NaN outside the ball of ``radius`` and at the
    nodes no crossed cell needs. Coarse to fine: ``f`` is first evaluated every ``coarse[0]``
    nodes; a box (``d`` its diagonal) whose corners all have one sign and ``|f| > L d / 2``
    holds no zero of ``f`` (every point of it is within ``d / 2`` of a corner; ``L``:
    :data:`LIPSCHITZ_SAFETY` times the steepest slope along the first grid's edges). Only the
    other boxes are evaluated at the next step, and so on down to every node. Every fine cell
    that the zero set crosses lies in such a box, all its corners evaluated: the crossed cells
    are those of the full evaluation (``coarse`` empty), at a fraction of its cost."""
    half = int(math.ceil(radius / g))
    side = 2 * half + 1
    ax = (np.arange(side) - half) * g
    live = (ax[:, None, None] ** 2 + ax[None, :, None] ** 2 + ax[None, None, :] ** 2) <= radius**2
    val = np.full((side,) * 3, np.nan)
    need = np.ones((side,) * 3, dtype=bool)
    lip = 0.0
    for step in coarse:
        ci = np.unique(np.r_[np.arange(0, side, step), side - 1])
        lattice = need[np.ix_(ci, ci, ci)] & np.isnan(val[np.ix_(ci, ci, ci)])
        at = ci[np.argwhere(lattice)]
        val[tuple(at.T)] = surface(ax[at] + centre)
        f = val[np.ix_(ci, ci, ci)]
        lip = lip or LIPSCHITZ_SAFETY * max(_slope(f, np.diff(ax[ci])), 1.0)
        need = _boxes_near_zero(f, ci, np.diff(ax[ci]), lip, side)
    need &= live
    at = np.argwhere(need & np.isnan(val))
    val[tuple(at.T)] = surface(ax[at] + centre)
    return np.where(need, val, np.nan)


def _slope(f: np.ndarray, width: np.ndarray) -> float:
    """The steepest slope of ``f`` along the edges of its (lattice) grid of box ``width``s."""
    w = (width[:, None, None], width[None, :, None], width[None, None, :])
    return max(float(np.nanmax(np.abs(np.diff(f, axis=a)) / w[a])) for a in range(3))


def _boxes_near_zero(f: np.ndarray, ci: np.ndarray, width: np.ndarray, lip: float, side: int):
    """Mask of the fine nodes (``side`` a side) of the boxes of the lattice ``ci`` (values
    ``f``, NaN where not evaluated: inside a box known to hold no zero) that the zero set may
    cross (:func:`node_values`)."""
    n = ci.size - 1
    corners = np.stack(
        [f[i : n + i, j : n + j, k : n + k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], -1
    )
    wx, wy, wz = width[:, None, None], width[None, :, None], width[None, None, :]
    diag = np.sqrt(wx**2 + wy**2 + wz**2)
    known = np.isfinite(corners).all(axis=-1)
    c = np.where(known[..., None], corners, 1.0)
    one_sign = (c.min(axis=-1) > 0) | (c.max(axis=-1) < 0)
    maybe = known & ~(one_sign & (np.abs(c).min(axis=-1) > 0.5 * lip * diag))
    # each fine node: the boxes holding it (two along an axis where it is on a boundary)
    nodes = np.arange(side)
    box = np.minimum(np.searchsorted(ci, nodes, side="right") - 1, n - 1)
    lower = np.maximum(np.searchsorted(ci, nodes, side="left") - 1, 0)
    need = np.zeros((side,) * 3, dtype=bool)
    for a in (box, lower):
        for b in (box, lower):
            for d in (box, lower):
                need |= maybe[np.ix_(a, b, d)]
    return need


def zero_set_cells(
    surface: ImplicitSurface,
    centre: np.ndarray,
    radius: float,
    g: float,
    coarse: tuple[int, ...] = COARSE,
    project: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int, int]]:
    """The cells of a cubic grid (spacing ``g``, centred on ``centre``) inside the ball of
    ``radius`` that the zero set crosses: (cell index (C, 3), surface point in each (C, 3), on
    the ball's shell (C,), the grid's shape in cells). ``f`` is evaluated coarse to fine
    (:func:`node_values`; ``coarse`` empty: at every node). The point of a cell is the mean of
    its edges' crossings, moved onto the zero set (``project``; else left in the cell, within
    its diagonal of the zero set)."""
    half = int(math.ceil(radius / g))
    side = 2 * half + 1
    v = node_values(surface, centre, radius, g, coarse)
    corners = np.stack(
        [
            v[i : side - 1 + i, j : side - 1 + j, k : side - 1 + k]
            for i in (0, 1)
            for j in (0, 1)
            for k in (0, 1)
        ],
        axis=-1,
    )
    whole = np.isfinite(corners).all(axis=-1)
    known = np.where(whole[..., None], corners, 0.0)
    cross = whole & (known.min(axis=-1) < 0) & (known.max(axis=-1) > 0)
    ijk = np.argwhere(cross)
    if ijk.size == 0:
        empty = np.zeros((0, 3))
        return ijk, empty, np.zeros(0, dtype=bool), (side - 1,) * 3
    # the crossings on the cell's 12 edges, averaged
    base = (ijk - half) * g
    cv = corners[cross]  # (C, 8): corner (i, j, k) at index 4 i + 2 j + k
    off = np.array([(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)
    total = np.zeros((ijk.shape[0], 3))
    count = np.zeros(ijk.shape[0])
    for a in range(8):
        for b in range(a + 1, 8):
            if np.abs(off[a] - off[b]).sum() != 1:
                continue
            va, vb = cv[:, a], cv[:, b]
            hit = (va < 0) != (vb < 0)
            t = np.where(hit, va / np.where(hit, va - vb, 1.0), 0.0)
            total += hit[:, None] * (off[a] + t[:, None] * (off[b] - off[a]))
            count += hit
    pts = base + g * total / np.maximum(count, 1)[:, None] + centre
    if project:
        pts = surface.project(pts)
    # a cell with a corner on the ball's last layer: the region reaches the ball's shell
    shell = np.linalg.norm(base + 0.5 * g, axis=1) > radius - 2.0 * g
    return ijk, pts, shell, (side - 1,) * 3


def cell_area(normals: np.ndarray, g: float) -> np.ndarray:
    """Surface area each crossed cell stands for: a plane of unit normal n crosses
    ``(|n_x| + |n_y| + |n_z|) / g^2`` cells per unit area."""
    return g * g / np.abs(normals).sum(axis=1)
