"""Per-level quality reports: every metric of a level against its scan, as a dataclass or dict."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .._validate import (
    check_fraction,
    check_positive,
    check_size,
    strict_keywords,
    strict_methods,
    validate_points,
)
from ..errors import InputError
from ..levels import count_above, covering_bound, log_sizes, nonempty, size_for_fraction
from ..progress import ProgressCallback, report
from .metrics import meets_rho, nearest_distances, spacing, uniformity
from .surface import ErrorStats, surface_error

log = logging.getLogger(__name__)


@strict_methods
@dataclass
class LevelReport:
    """Every quality figure of one level.

    Attributes:
        size: number of level points; ``fraction`` = size / number of input points.
        rho: the density the level claims (every input point within rho of a level point), or None.
        covering_radius: measured largest distance from an input point to the level (Euclidean).
        meets_rho: covering_radius <= rho (None when no rho is claimed).
        hausdorff: two-sided Hausdorff distance; ``hausdorff_level_to_input`` is 0 for subsets.
        chamfer: mean of both directions' mean nearest-neighbour distance (not squared).
        min_spacing / mean_spacing: nearest-neighbour distances inside the level.
        uniformity: min_spacing / covering_radius (>= 1 for an exact Euclidean FPS level).
        surface_*: distance of the input points to the level's local surface (plane or MLS).
        diagonal: the input's bounding-box diagonal, to compare scans of different scale.
        seconds: time spent evaluating this level.
    """

    size: int
    fraction: float
    rho: float | None
    covering_radius: float
    meets_rho: bool | None
    hausdorff: float
    hausdorff_input_to_level: float
    hausdorff_level_to_input: float
    chamfer: float
    chamfer_input_to_level: float
    chamfer_level_to_input: float
    min_spacing: float
    mean_spacing: float
    uniformity: float
    surface_method: str
    surface_k: int
    surface_error: dict[str, float]
    diagonal: float
    seconds: float
    label: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (lodbuilder's one convention: inf and NaN as strings)."""
        from .._json import jsonable

        return jsonable(asdict(self))


def _claimed_rho(rho: Any) -> float | None:
    if rho is None:
        return None
    rho = float(rho)
    if math.isnan(rho) or rho < 0:
        raise InputError(f"rho must be a number >= 0, got {rho!r}")
    return rho


@strict_keywords
def evaluate_level(
    points,
    level,
    *,
    rho: float | None = None,
    surface: str = "plane",
    k: int | None = None,
    label: str = "",
    input_tree: cKDTree | None = None,
) -> LevelReport:
    """Measure one level (any (M, 3) point set) against its input scan.

    Args:
        points: (N, 3) input scan.
        level: (M, 3) level points (a subset of the input or not).
        rho: the density the level claims, checked against the measured covering radius.
        surface: ``"plane"`` or ``"mls"`` for the point-to-surface error.
        k: neighbours per local surface fit (default by method).
        label: free text carried into the report (method name, query, ...).
        input_tree: optional prebuilt ``cKDTree(points)`` when evaluating many levels of one scan.
    """
    t0 = time.perf_counter()
    pts = validate_points(points, "points")
    lev = validate_points(level, "level")
    rho = _claimed_rho(rho)
    level_tree = cKDTree(lev)
    if input_tree is None:
        input_tree = cKDTree(pts)
    d_in = nearest_distances(pts, lev, tree=level_tree)
    d_lev = nearest_distances(lev, pts, tree=input_tree)
    cover = float(d_in.max())
    sp = spacing(lev, tree=level_tree)
    err = surface_error(pts, lev, k=k, method=surface, tree=level_tree)
    k_used = int(min(k if k is not None else (8 if surface == "plane" else 16), lev.shape[0]))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    rep = LevelReport(
        size=int(lev.shape[0]),
        fraction=float(lev.shape[0] / pts.shape[0]),
        rho=rho,
        covering_radius=cover,
        meets_rho=meets_rho(cover, rho),
        hausdorff=max(cover, float(d_lev.max())),
        hausdorff_input_to_level=cover,
        hausdorff_level_to_input=float(d_lev.max()),
        chamfer=0.5 * (float(d_in.mean()) + float(d_lev.mean())),
        chamfer_input_to_level=float(d_in.mean()),
        chamfer_level_to_input=float(d_lev.mean()),
        min_spacing=sp.min,
        mean_spacing=sp.mean,
        uniformity=uniformity(sp.min, cover),
        surface_method=surface,
        surface_k=k_used,
        surface_error=ErrorStats.of(err).as_dict(),
        diagonal=float(np.linalg.norm(hi - lo)),
        seconds=0.0,
        label=label,
    )
    rep.seconds = time.perf_counter() - t0
    return rep


@strict_keywords
def prefix_sizes(
    radius: np.ndarray,
    n_points: int,
    *,
    sizes=None,
    rhos=None,
    fractions=None,
) -> list[tuple[int, float | None]]:
    """(size, claimed rho) of each requested level of a farthest point ordering.

    ``radius`` is the ordering's non-increasing insertion radius array (length K <= n_points). A
    level of size k claims rho = radius[k] (the next insertion radius), 0 when it is the whole scan,
    and nothing when the ordering stops at k < n_points. A level asked by rho is the shortest prefix
    whose next radius is <= rho, and claims that rho.
    """
    radius = np.asarray(radius, dtype=np.float64)
    kmax = radius.shape[0]
    out: list[tuple[int, float | None]] = []

    def claim(s: int) -> float | None:
        if s >= kmax and kmax < n_points:
            return None  # the ordering stops here: nothing is known past it
        return covering_bound(s, kmax, radius.__getitem__)

    for s in sizes or ():
        s = check_size(s, kmax, "size")
        out.append((s, claim(s)))
    for f in fractions or ():
        s = size_for_fraction(check_fraction(f), n_points)
        if s > kmax:
            raise InputError(
                f"fraction {f:g} is {s} points, more than the {kmax} the ordering reaches; "
                "ask for a smaller fraction"
            )
        out.append((s, claim(s)))
    for r in rhos or ():
        r = float(check_positive(r, "rho", allow_none=False))  # type: ignore[arg-type]
        s = count_above(radius, r)
        if s >= kmax and kmax < n_points:
            raise InputError(
                f"rho {r:g} is finer than the ordering reaches (its last radius is {radius[-1]:g}); "
                "ask for a larger rho"
            )
        out.append((nonempty(s), r))
    return out


@strict_keywords
def evaluate_prefixes(
    points,
    order,
    radius,
    *,
    sizes=None,
    rhos=None,
    fractions=None,
    surface: str = "plane",
    k: int | None = None,
    progress: ProgressCallback = None,
) -> list[LevelReport]:
    """Reports of prefixes of a farthest point ordering ``order`` of ``points``.

    Levels come from ``sizes``, ``rhos`` or ``fractions`` (see :func:`prefix_sizes`); with none of
    them, ten sizes spaced evenly on a log scale from 0.1 % to 100 %.
    """
    pts = validate_points(points, "points")
    order = np.asarray(order, dtype=np.int64)
    radius = np.asarray(radius, dtype=np.float64)
    if order.shape != radius.shape:
        raise InputError(
            f"order and radius must have the same shape, got {order.shape} and {radius.shape}"
        )
    if not sizes and not rhos and not fractions:
        sizes = default_sizes(order.shape[0])
    levels = prefix_sizes(radius, pts.shape[0], sizes=sizes, rhos=rhos, fractions=fractions)
    tree = cKDTree(pts)
    reports = []
    for i, (s, r) in enumerate(levels):
        reports.append(
            evaluate_level(pts, pts[order[:s]], rho=r, surface=surface, k=k, input_tree=tree)
        )
        report(progress, "evaluate", i + 1, len(levels))
    return reports


@strict_keywords
def default_sizes(n: int, count: int = 10) -> list[int]:
    """About ``count`` distinct sizes, log-spaced from max(1, n/1000) to n."""
    return log_sizes(n / 1000.0, n, count)
