"""Public farthest point ordering: validation and orchestration around the compiled kernels."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from .._validate import check_positive, check_size, validate_indices, validate_points
from ..errors import InputError
from ..progress import ProgressCallback
from .ordering import Ordering

log = logging.getLogger(__name__)


def default_seed(points: np.ndarray) -> int:
    """The deterministic default seed: the point nearest the centroid (lowest index on ties)."""
    c = points.mean(axis=0)
    return int(np.argmin(((points - c) ** 2).sum(axis=1)))


def validate_cost(cost: Any, n: int, name: str = "cost") -> np.ndarray:
    """Return a per-point cost (speed) array: (N,) float64, finite and > 0."""
    arr = np.asarray(cost)
    if arr.ndim != 1 or arr.shape[0] != n:
        raise InputError(f"{name} must have one value per point, shape ({n},), got {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all() or (arr <= 0).any():
        raise InputError(f"{name} must be finite and > 0 everywhere; clamp or fill it first")
    return arr


def _prepare(points, rho, size, seeds):
    pts = validate_points(points)
    n = pts.shape[0]
    rho = check_positive(rho, "rho")
    size = None if size is None else check_size(size, n)
    if seeds is None:
        seed_arr = np.array([default_seed(pts)], dtype=np.int64)
    else:
        seed_arr = validate_indices(seeds, n, "seeds")
        if seed_arr.size == 0:
            seed_arr = np.array([default_seed(pts)], dtype=np.int64)
    return pts, n, rho, size, seed_arr


def _truncate(order, radius, parent, rho, size):
    k = order.shape[0]
    if rho is not None:
        k = min(k, int(np.searchsorted(-radius, -rho, side="left")))
    if size is not None:
        k = min(k, size)
    return order[:k].copy(), radius[:k].copy(), parent[:k].copy()


def euclidean_fps(
    points: Any,
    *,
    rho: float | None = None,
    size: int | None = None,
    seeds: Any = None,
    cost: Any = None,
) -> Ordering:
    """Exact Euclidean farthest point ordering, O(N * K). A baseline for small inputs.

    Same conventions as :func:`fastfps`; ``cost`` scales each pair's distance by the mean of the
    two points' costs.
    """
    pts, n, rho, size, seed_arr = _prepare(points, rho, size, seeds)
    c = np.ones(n) if cost is None else validate_cost(cost, n)
    from .._kernels.euclid import euclidean_fps_kernel

    k_max = n if size is None else max(size, seed_arr.size)
    order, radius, parent = euclidean_fps_kernel(pts, seed_arr, k_max, c)
    order, radius, parent = _truncate(order, radius, parent, rho, size)
    return Ordering(order, radius, parent, 0.0, 0.0, seed_arr, n, {"engine": "euclidean"})


def fastfps(
    points: Any,
    *,
    rho: float | None = None,
    size: int | None = None,
    seeds: Any = None,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    cost: Any = None,
    max_memory: int | None = None,
    progress: ProgressCallback = None,
) -> Ordering:
    """Farthest point ordering of ``points`` under the band (surface) metric.

    Args:
        points: (N, 3) array of finite coordinates.
        rho: stop once the next insertion radius is <= rho (the prefix then covers within rho).
        size: stop after this many points.
        seeds: must-keep input indices that come first, in the given order. Default: the point
            nearest the centroid.
        voxel_size: grid spacing h (default: derived from the point spacing).
        band_radius: band radius r (default: derived from h).
        cost: optional per-point cost F > 0 (feature sensitivity): distances grow F times faster.
        max_memory: bytes the band may use (default: 60 % of physical memory).
        progress: ``progress(stage, done, total)`` callback.

    Returns:
        An :class:`Ordering`.
    """
    # Interim body: exact Euclidean ordering, replaced by the band engine.
    voxel_size = check_positive(voxel_size, "voxel_size")
    band_radius = check_positive(band_radius, "band_radius")
    return euclidean_fps(points, rho=rho, size=size, seeds=seeds, cost=cost)
