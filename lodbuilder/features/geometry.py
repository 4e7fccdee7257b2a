"""Geometric importance maps: surface variation, normal variation, noise / outlier score.

Each map returns ``(values, params)``: one float64 per point and a JSON-serialisable dict of the
parameters that produced it (stored beside the map in the archive).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .._validate import strict_keywords, validate_points
from ..errors import InputError
from .neighbours import (
    Neighbourhoods,
    check_k,
    kd_tree,
    local_pca,
    mean_pair_function,
    median_of_entries,
    median_over_neighbours,
    neighbourhoods,
    plane_residuals,
)

COMBINE = ("mean", "max")
#: noise score of a point with fewer than 3 neighbours (radius neighbourhoods): an outlier
ISOLATED_SCORE = 1e6


def _nbhd_params(k: int | None, radius: float | None) -> dict[str, Any]:
    return {"radius": float(radius)} if radius is not None else {"k": int(16 if k is None else k)}


@strict_keywords
def surface_variation(
    points: Any,
    *,
    k: int | Sequence[int] = 16,
    radius: float | None = None,
    combine: str = "mean",
    tree: Any = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Surface variation lambda0 / (lambda0 + lambda1 + lambda2) of each point's neighbourhood
    covariance (Pauly et al. 2002), lambda0 the smallest eigenvalue.

    0 on a plane, up to 1/3 for an isotropic blob; on a sphere of radius R sampled with
    neighbourhoods of radius s it is about s^2 / (8 R^2) (small and the same everywhere).

    Args:
        points: (N, 3) coordinates.
        k: neighbours per point (the point included), or several k for a multi-scale map.
        radius: use every point within this radius instead of kNN (``k`` is then ignored).
        combine: how a multi-scale map merges its scales: ``"mean"`` or ``"max"``.
    """
    pts = validate_points(points)
    tree = kd_tree(pts) if tree is None else tree
    if combine not in COMBINE:
        raise InputError(f"combine must be one of {', '.join(COMBINE)}, got {combine!r}")
    if radius is not None:
        return _variation(pts, neighbourhoods(pts, radius=radius, tree=tree)), {
            "radius": float(radius)
        }
    ks = [check_k(k)] if isinstance(k, (int, np.integer)) else [check_k(x) for x in k]
    if not ks:
        raise InputError("k must list at least one neighbourhood size")
    maps = np.stack([_variation(pts, neighbourhoods(pts, k=kk, tree=tree)) for kk in ks])
    values = maps.mean(axis=0) if combine == "mean" else maps.max(axis=0)
    params: dict[str, Any] = {"k": ks[0]} if len(ks) == 1 else {"k": ks, "combine": combine}
    return values, params


def _variation(pts: np.ndarray, nb: Neighbourhoods) -> np.ndarray:
    evals, _, _ = local_pca(pts, nb)
    total = evals.sum(axis=1)
    out = np.zeros(pts.shape[0])
    ok = total > 0
    out[ok] = evals[ok, 0] / total[ok]
    return out


@strict_keywords
def pca_normals(
    points: Any, *, k: int = 16, radius: float | None = None, tree: Any = None
) -> np.ndarray:
    """(N, 3) unit, unoriented normals: the smallest principal axis of each neighbourhood."""
    pts = validate_points(points)
    _, normals, _ = local_pca(pts, neighbourhoods(pts, k=k, radius=radius, tree=tree))
    return normals


def validate_normals(normals: Any, n: int) -> np.ndarray:
    arr = np.asarray(normals, dtype=np.float64)
    if arr.shape != (n, 3):
        raise InputError(f"normals must have shape ({n}, 3), got {arr.shape}")
    length = np.linalg.norm(arr, axis=1)
    bad = ~np.isfinite(length) | (length == 0)
    if bad.any():
        raise InputError(
            f"normals has {int(bad.sum())} zero-length or non-finite vector(s) (first at index "
            f"{int(np.flatnonzero(bad)[0])}); leave normals=None to estimate them by PCA"
        )
    return arr / length[:, None]


@strict_keywords
def normal_variation(
    points: Any,
    normals: Any = None,
    *,
    k: int = 16,
    radius: float | None = None,
    oriented: bool = False,
    tree: Any = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Angle spread of the normals around each point: the mean angle (radians) between the
    point's normal and its neighbours' normals.

    ``normals`` (N, 3) come from the scan when it has them; ``None`` estimates them by PCA over the
    same neighbourhoods. Unless ``oriented``, a normal and its opposite count as the same (angles in
    [0, pi/2]), which suits PCA normals and scans whose normals flip.
    """
    pts = validate_points(points)
    tree = kd_tree(pts) if tree is None else tree
    nb = neighbourhoods(pts, k=k, radius=radius, tree=tree)
    if normals is None:
        _, nrm, _ = local_pca(pts, nb)
        source = "pca"
    else:
        nrm = validate_normals(normals, pts.shape[0])
        source = "scan"
    nb = nb.without_self()

    def angle(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        dots = np.einsum("ij,ij->i", nrm[i], nrm[j])
        return np.arccos(np.clip(dots if oriented else np.abs(dots), -1.0, 1.0))

    params = _nbhd_params(k, radius) | {"normals": source, "oriented": bool(oriented)}
    return mean_pair_function(nb, angle), params


@strict_keywords
def noise_score(
    points: Any,
    *,
    k: int = 16,
    radius: float | None = None,
    floor: float = 0.01,
    tree: Any = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Outlier score: a point's distance to the local plane of its neighbours (the point itself left
    out), divided by the median of the same distance over those neighbours.

    The local plane is a robust PCA fit: a first fit, then a refit without the neighbours farther
    than 3 times the median residual, so one outlier does not tilt its neighbours' planes. The score
    is about 1 on a surface with even noise and large for a point off the surface.

    The denominator has a floor of ``floor`` times the point's mean neighbour distance: distances
    below 1 % of the point spacing count as noise-free, so exact (synthetic) surfaces, whose
    distances are ~1e-17 away from creases, do not turn tiny crease effects into huge ratios.
    With ``radius`` neighbourhoods a point with fewer than 3 other points within the radius has
    no plane to compare with and scores :data:`ISOLATED_SCORE` (1e6).
    """
    pts = validate_points(points)
    tree = kd_tree(pts) if tree is None else tree
    nb = neighbourhoods(pts, k=k, radius=radius, tree=tree).without_self()
    _, normals, cen = local_pca(pts, nb)
    res = plane_residuals(pts, nb, normals, cen)
    med = median_of_entries(res, nb)
    rows, _ = nb.rows()
    inlier = (res <= 3.0 * med[rows]).astype(np.float64)
    _, normals, cen = local_pca(pts, nb, weights=inlier)
    dist = np.abs(np.einsum("ij,ij->i", pts - cen, normals))
    spacing = mean_pair_function(nb, lambda i, j: np.linalg.norm(pts[j] - pts[i], axis=1))
    denom = np.maximum(median_over_neighbours(dist, nb), floor * spacing)
    out = np.zeros(pts.shape[0])
    ok = denom > 0
    out[ok] = dist[ok] / denom[ok]
    out[nb.counts() < 3] = ISOLATED_SCORE  # no plane to compare with: alone in its radius
    params = {"refit": "3x median residual", "floor": float(floor)}
    return out, _nbhd_params(k, radius) | params
