"""Distances between a scan and one of its levels: covering radius, Hausdorff, Chamfer, spacing.

Every function takes plain (N, 3) arrays (the input scan and the level's points) and returns numbers
or arrays. Distances are Euclidean and exact (k-d tree nearest neighbours, all cores).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .._validate import strict_keywords, strict_methods, validate_points


@strict_keywords
def nearest_distances(
    source: np.ndarray, target: np.ndarray, *, tree: cKDTree | None = None
) -> np.ndarray:
    """(len(source),) distance from every source point to its nearest target point.

    ``tree`` may pass a prebuilt ``cKDTree(target)`` to save rebuilding it.
    """
    if tree is None:
        tree = cKDTree(target)
    d, _ = tree.query(source, k=1, workers=-1)
    return np.asarray(d, dtype=np.float64)


@strict_keywords
def covering_radius(points, level, *, tree: cKDTree | None = None) -> float:
    """Largest Euclidean distance from an input point to its nearest level point.

    Every input point lies within this radius of the level: the level's actual density.
    """
    pts = validate_points(points, "points")
    lev = validate_points(level, "level")
    return float(nearest_distances(pts, lev, tree=tree).max())


@strict_keywords
def meets_rho(cover: float, rho: float | None, *, rtol: float = 1e-9) -> bool | None:
    """True when a measured covering radius honours the density ``rho`` a level claims.

    ``rtol`` absorbs float rounding only. ``None`` when the level claims no rho.
    """
    if rho is None or not np.isfinite(rho):
        return None
    return bool(cover <= rho * (1.0 + rtol) + 1e-300)


@strict_methods
@dataclass(frozen=True)
class TwoSided:
    """A two-sided distance between the input scan and a level.

    Attributes:
        input_to_level: statistic over input points of the distance to the nearest level point.
        level_to_input: statistic over level points of the distance to the nearest input point
            (0 when the level is a subset of the input).
        value: the combined figure (max of both for Hausdorff, mean of both for Chamfer).
    """

    input_to_level: float
    level_to_input: float
    value: float


@strict_keywords
def hausdorff(points, level) -> TwoSided:
    """Two-sided Hausdorff distance: the larger of both directed Hausdorff distances."""
    pts = validate_points(points, "points")
    lev = validate_points(level, "level")
    a = float(nearest_distances(pts, lev).max())
    b = float(nearest_distances(lev, pts).max())
    return TwoSided(a, b, max(a, b))


@strict_keywords
def chamfer(points, level) -> TwoSided:
    """Chamfer distance (not squared): the mean of both directions' mean nearest-neighbour distance."""
    pts = validate_points(points, "points")
    lev = validate_points(level, "level")
    a = float(nearest_distances(pts, lev).mean())
    b = float(nearest_distances(lev, pts).mean())
    return TwoSided(a, b, 0.5 * (a + b))


@strict_methods
@dataclass(frozen=True)
class Spacing:
    """Nearest-neighbour spacing inside a level.

    Attributes:
        min: smallest distance between two level points (0 with duplicates; inf for one point).
        mean: mean distance from a level point to its nearest other level point.
        max: largest such distance (the most isolated point).
    """

    min: float
    mean: float
    max: float


@strict_keywords
def spacing(level, *, tree: cKDTree | None = None) -> Spacing:
    """Nearest-neighbour spacing statistics of a level."""
    lev = validate_points(level, "level")
    if lev.shape[0] < 2:
        return Spacing(float("inf"), float("inf"), float("inf"))
    if tree is None:
        tree = cKDTree(lev)
    d, _ = tree.query(lev, k=2, workers=-1)
    nn = d[:, 1]
    return Spacing(float(nn.min()), float(nn.mean()), float(nn.max()))


@strict_keywords
def uniformity(min_spacing: float, cover: float) -> float:
    """Minimum spacing divided by covering radius.

    An exact Euclidean farthest point level scores >= 1 (its points are at least the covering
    radius apart); a random subsample scores near 0. 1.0 when both are 0 (the full scan without
    duplicates covers itself), inf when the covering radius alone is 0 and spacing is not.
    """
    if cover == 0.0:
        return 1.0 if min_spacing == 0.0 else float("inf")
    return float(min_spacing / cover)
