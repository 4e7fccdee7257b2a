"""Point-to-surface error: how far the input points lie from the surface a level describes.

The level's local surface around an input point is fitted to the level's ``k`` nearest points of
that input point: a least-squares plane (PCA), or a moving-least-squares (MLS) quadric: a
Gaussian-weighted plane followed by a weighted quadratic height field over it (Levin's MLS, one
step). The error of the input point is its distance to that surface along the local normal.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from .._validate import strict_keywords, strict_methods, validate_points
from ..errors import InputError

METHODS = ("plane", "mls")


@strict_methods
@dataclass(frozen=True)
class ErrorStats:
    """Summary of a per-point error array."""

    mean: float
    rms: float
    p95: float
    max: float

    @classmethod
    def of(cls, err: np.ndarray) -> ErrorStats:
        if err.size == 0:
            nan = float("nan")
            return cls(nan, nan, nan, nan)
        return cls(
            float(err.mean()),
            float(np.sqrt(np.mean(err * err))),
            float(np.percentile(err, 95)),
            float(err.max()),
        )

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def _plane_fit(nb: np.ndarray, w: np.ndarray | None):
    """Weighted centroid and eigenvectors (ascending eigenvalues) of (n, k, 3) neighbourhoods."""
    if w is None:
        c = nb.mean(axis=1)
        x = nb - c[:, None, :]
        cov = np.einsum("nki,nkj->nij", x, x)
    else:
        ws = w / w.sum(axis=1, keepdims=True)
        c = np.einsum("nk,nki->ni", ws, nb)
        x = nb - c[:, None, :]
        cov = np.einsum("nk,nki,nkj->nij", ws, x, x)
    _, vec = np.linalg.eigh(cov)
    return c, vec


def _plane_error(p: np.ndarray, nb: np.ndarray) -> np.ndarray:
    c, vec = _plane_fit(nb, None)
    normal = vec[:, :, 0]
    return np.abs(np.einsum("ni,ni->n", p - c, normal))


def _mls_error(p: np.ndarray, nb: np.ndarray, d: np.ndarray) -> np.ndarray:
    h = np.maximum(d[:, -1], 1e-300)  # kernel width: distance to the k-th neighbour
    w = np.exp(-((d / h[:, None]) ** 2))
    c, vec = _plane_fit(nb, w)
    n_, t1, t2 = vec[:, :, 0], vec[:, :, 2], vec[:, :, 1]
    x = (nb - c[:, None, :]) / h[:, None, None]
    u = np.einsum("nki,ni->nk", x, t1)
    v = np.einsum("nki,ni->nk", x, t2)
    f = np.einsum("nki,ni->nk", x, n_)
    one = np.ones_like(u)
    a = np.stack([one, u, v, u * u, u * v, v * v], axis=2)  # (n, k, 6)
    ata = np.einsum("nk,nki,nkj->nij", w, a, a) + 1e-9 * np.eye(6)
    atf = np.einsum("nk,nki,nk->ni", w, a, f)
    coef = np.linalg.solve(ata, atf[:, :, None])[:, :, 0]
    q = (p - c) / h[:, None]
    uq = np.einsum("ni,ni->n", q, t1)
    vq = np.einsum("ni,ni->n", q, t2)
    fq = np.einsum("ni,ni->n", q, n_)
    aq = np.stack([np.ones_like(uq), uq, vq, uq * uq, uq * vq, vq * vq], axis=1)
    fit = np.einsum("ni,ni->n", aq, coef)
    return np.abs(fq - fit) * h


@strict_keywords
def surface_error(
    points,
    level,
    *,
    k: int | None = None,
    method: str = "plane",
    chunk: int = 65536,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """(N,) distance of every input point to the level's local surface.

    Args:
        points: (N, 3) input scan.
        level: (M, 3) level points.
        k: neighbours per fit (default 8 for ``"plane"``, 16 for ``"mls"``); clipped to M.
        method: ``"plane"`` (PCA plane of the k nearest level points) or ``"mls"``.
        chunk: input points per vectorised batch (bounds memory at about chunk * k * 200 bytes).
        tree: optional prebuilt ``cKDTree(level)``.

    With fewer than 3 level points no plane exists and the error is the distance to the nearest
    level point; MLS falls back to the plane with fewer than 6.
    """
    pts = validate_points(points, "points")
    lev = validate_points(level, "level")
    if method not in METHODS:
        raise InputError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if k is None:
        k = 8 if method == "plane" else 16
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 3:
        raise InputError(f"k must be a whole number of neighbours >= 3, got {k!r}")
    m = lev.shape[0]
    k = int(min(k, m))
    if tree is None:
        tree = cKDTree(lev)
    if k < 3:
        d, _ = tree.query(pts, k=1, workers=-1)
        return np.asarray(d, dtype=np.float64)
    if method == "mls" and k < 6:
        method = "plane"
    out = np.empty(pts.shape[0], dtype=np.float64)
    for s in range(0, pts.shape[0], chunk):
        p = pts[s : s + chunk]
        d, idx = tree.query(p, k=k, workers=-1)
        nb = lev[idx]
        if method == "plane":
            out[s : s + chunk] = _plane_error(p, nb)
        else:
            out[s : s + chunk] = _mls_error(p, nb, d)
    return out
