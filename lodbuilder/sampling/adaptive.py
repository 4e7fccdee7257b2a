"""Feature-sensitive orderings on top of :func:`lodbuilder.fastfps`: weighted FastFPS and the
paper's density floor.

Weighted ordering
    Importance maps give a per-point cost ``F = max(eps, (1 - a) + a * w)`` in [eps, 1]
    (see :mod:`lodbuilder.features.weights`), passed as ``cost=`` to the engine, which measures a
    path by the integral of F along it (the band metric with |grad T| = F). Points where F is large
    are "far" from everything and get sampled densely; where F is small they are cheap to leave out.

    **What the weighted radius means.** ``radius[k]`` of a weighted ordering is the insertion radius in
    the *weighted* metric: every ordered point is within weighted distance ``radius[k]`` of the prefix
    ``order[:k]``. Because F <= 1, weighted distances are never larger than unweighted ones, so the
    weighted radius is **not** a Euclidean covering radius: a prefix with weighted radius r covers
    every point within r / F_min (F_min the smallest cost on the way, >= eps) in the unweighted
    metric, and within r only where F = 1. Use the density floor when a Euclidean guarantee is needed.

Density floor (Moenning & Dodgson 2003)
    Uniform until rho0, then the rest by the weighted metric: the uniform ordering's prefix of
    ``n0 = n(rho0)`` points (covering radius <= rho0) seeds a weighted ordering, and both are stored as
    one full ordering. Every prefix of size >= n0 contains the uniform prefix, so it covers every
    ordered point within rho0. Its radii are the uniform insertion radii for k < n0 and the weighted
    ones for k >= n0; they stay non-increasing because the weighted distance to the uniform prefix
    is at most its unweighted covering radius <= rho0 when F <= 1. So a level of this ordering taken
    by a radius R is a true covering level only for R >= rho0; below rho0 its radii are weighted
    (use the instant query below for a guarantee at a smaller rho).

Instant query for any rho
    :func:`floor_query` picks, for a rho chosen at query time, the uniform prefix that covers within
    rho, and fills it to an exact size with the weighted ordering's points in weighted order
    (skipping those already taken). Exact size; covering <= rho, measured by the uniform ordering's
    radii (its metric, Euclidean or band, which is >= Euclidean). O(N) NumPy, no engine run.

Outliers
    ``exclude`` (a boolean mask, e.g. ``noise > threshold``) leaves points out of an ordering: the
    engine runs on the other points and the indices are mapped back, so an ordering then holds
    N - n_excluded input indices. The excluded points remain in the scan; the archive stores them
    after the ordered points, flagged.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .._validate import check_positive, check_size, validate_indices, validate_points
from ..errors import InputError
from ..progress import ProgressCallback, report
from .ordering import Ordering

log = logging.getLogger(__name__)


def check_exclude(exclude: Any, n: int) -> np.ndarray | None:
    """Return a boolean mask (N,) of points to leave out, or None when nothing is left out."""
    if exclude is None:
        return None
    arr = np.asarray(exclude)
    if arr.dtype != np.bool_ or arr.shape != (n,):
        raise InputError(
            f"exclude must be a boolean mask of shape ({n},), got dtype {arr.dtype} shape {arr.shape}"
        )
    if arr.all():
        raise InputError("exclude leaves no point to order; raise the outlier threshold")
    return arr if arr.any() else None


def order_subset(
    points: np.ndarray,
    exclude: np.ndarray | None,
    *,
    cost: np.ndarray | None = None,
    seeds: np.ndarray | None = None,
    rho: float | None = None,
    size: int | None = None,
    **engine: Any,
) -> Ordering:
    """:func:`lodbuilder.fastfps` on the points not excluded, with indices mapped back to the input.

    ``seeds`` are input indices (none of them excluded); ``order`` and ``seeds`` of the result are
    input indices, ``parent`` stays a position in the ordering, ``n_points`` is the input's N.
    """
    from .fastfps import fastfps

    n = points.shape[0]
    if exclude is None:
        return fastfps(points, rho=rho, size=size, seeds=seeds, cost=cost, **engine)
    keep = np.flatnonzero(~exclude)
    local = np.full(n, -1, dtype=np.int64)
    local[keep] = np.arange(keep.size)
    sub_seeds = None
    if seeds is not None:
        sub_seeds = local[validate_indices(seeds, n, "seeds")]
        if (sub_seeds < 0).any():
            raise InputError("seeds include excluded (outlier) points; seed with kept points only")
    if size is not None:
        size = min(size, keep.size)
    o = fastfps(
        points[keep],
        rho=rho,
        size=size,
        seeds=sub_seeds,
        cost=None if cost is None else cost[keep],
        **engine,
    )
    stats = dict(o.stats) | {"excluded": int(n - keep.size)}
    return Ordering(
        keep[o.order], o.radius, o.parent, o.voxel_size, o.band_radius, keep[o.seeds], n, stats
    )


def weighted_ordering(
    points: Any,
    cost: Any,
    *,
    exclude: Any = None,
    seeds: Any = None,
    **engine: Any,
) -> Ordering:
    """Full farthest point ordering under the F-weighted metric (see the module docstring for what
    its radii mean). ``cost`` (N,) finite and > 0; ``exclude`` a boolean outlier mask."""
    from .fastfps import validate_cost

    pts = validate_points(points)
    n = pts.shape[0]
    f = validate_cost(cost, n)
    ex = check_exclude(exclude, n)
    o = order_subset(pts, ex, cost=f, seeds=seeds, **engine)
    stats = dict(o.stats) | {
        "kind": "weighted",
        "cost_min": float(f.min()),
        "cost_max": float(f.max()),
    }
    return Ordering(o.order, o.radius, o.parent, o.voxel_size, o.band_radius, o.seeds, n, stats)


def density_floor_ordering(
    points: Any,
    cost: Any,
    rho0: float,
    *,
    uniform: Ordering | None = None,
    exclude: Any = None,
    **engine: Any,
) -> Ordering:
    """The paper's density floor: the uniform ordering until its radius falls to ``rho0``, then every
    other point by the weighted metric with that uniform prefix as seeds, as one full ordering.

    Args:
        points: (N, 3) coordinates.
        cost: (N,) per-point cost F in (0, 1] (F > 1 would break the non-increasing radii).
        rho0: the density floor: every prefix of size >= ``stats["n_floor"]`` covers every ordered
            point within rho0 (in the uniform ordering's metric, >= Euclidean).
        uniform: an existing uniform ordering of the same points (with the same ``exclude``), full or
            stopped at rho0 or later; computed when None.
        exclude: boolean mask of outliers left out of the ordering.
        **engine: ``voxel_size``, ``band_radius``, ``max_memory``, ``progress`` for fastfps.
    """
    from .fastfps import validate_cost

    pts = validate_points(points)
    n = pts.shape[0]
    f = validate_cost(cost, n)
    if f.max() > 1.0:
        raise InputError(f"cost must be <= 1 for a density floor, got max {f.max():g}; rescale it")
    rho0 = float(check_positive(rho0, "rho0", allow_none=False))  # type: ignore[arg-type]
    ex = check_exclude(exclude, n)
    uniform, n0 = _floor_prefix(pts, ex, rho0, uniform, engine)
    w = order_subset(pts, ex, cost=f, seeds=uniform.order[:n0], **engine)
    radius, parent, clamped = _join_at_floor(w, uniform, n0)
    stats = dict(w.stats) | {
        "kind": "density_floor",
        "rho0": rho0,
        "n_floor": int(n0),
        "capped": clamped,
        "cost_min": float(f.min()),
        "cost_max": float(f.max()),
    }
    return Ordering(w.order, radius, parent, w.voxel_size, w.band_radius, uniform.seeds, n, stats)


def floor_query_arrays(
    uniform_order: np.ndarray,
    uniform_radius: np.ndarray,
    weighted_order: np.ndarray,
    n_points: int,
    rho: float,
    size: int,
) -> np.ndarray:
    """Array form of :func:`floor_query` (what an archive reader calls with its stored datasets)."""
    rho = float(check_positive(rho, "rho", allow_none=False))  # type: ignore[arg-type]
    u_order = np.asarray(uniform_order, dtype=np.int64)
    w_order = np.asarray(weighted_order, dtype=np.int64)
    radius = np.asarray(uniform_radius, dtype=np.float64)
    n_ordered = u_order.shape[0]
    from ..levels import count_above

    n_u = count_above(radius, rho)
    if n_u == n_ordered and n_ordered < n_points and (n_ordered == 0 or radius[-1] > rho):
        raise InputError(
            f"the uniform ordering stops at radius {radius[-1]:g}, above rho = {rho:g}; "
            "ask for a larger rho or store a full uniform ordering"
        )
    size = check_size(size, w_order.shape[0])
    if size < n_u:
        raise InputError(
            f"size {size} is too small for rho = {rho:g}: the uniform prefix covering within rho has "
            f"{n_u} points; ask for at least {n_u} points or a larger rho"
        )
    taken = np.zeros(n_points, dtype=bool)
    taken[u_order[:n_u]] = True
    fill = w_order[~taken[w_order]][: size - n_u]
    if fill.size < size - n_u:
        raise InputError(
            f"size {size} exceeds the {n_u + fill.size} points the two orderings share; ask for fewer"
        )
    return np.concatenate([u_order[:n_u], fill])


def floor_query(uniform: Ordering, weighted: Ordering, rho: float, size: int) -> np.ndarray:
    """Input indices of a level for a rho chosen at query time: the uniform prefix that covers
    within ``rho`` united with the weighted ordering's prefix, filled to exactly ``size`` points.

    The result has exactly ``size`` distinct indices; its covering radius is <= rho in the uniform
    ordering's metric (it contains that prefix), and the remaining ``size - n(rho)`` points are the
    most important ones by the weighted ordering. ``size`` below n(rho) is an error naming n(rho).
    """
    if uniform.n_points != weighted.n_points:
        raise InputError(
            f"uniform ordering has {uniform.n_points} points but weighted has "
            f"{weighted.n_points}; both must order the same scan"
        )
    return floor_query_arrays(
        uniform.order, uniform.radius, weighted.order, uniform.n_points, rho, size
    )


def _floor_prefix(pts: np.ndarray, ex: np.ndarray | None, rho0: float, uniform: Ordering | None,
                  engine: dict[str, Any]) -> tuple[Ordering, int]:
    """The uniform ordering of a density floor (given, or ordered down to ``rho0``) and the size of
    its prefix at ``rho0``, checked against the points and the excluded ones."""
    n = pts.shape[0]
    n_ordered = n - (0 if ex is None else int(ex.sum()))
    if uniform is None:
        uniform = order_subset(pts, ex, rho=rho0, **engine)
        n0 = len(uniform)
    else:
        if uniform.n_points != n:
            raise InputError(
                f"uniform ordering is of {uniform.n_points} points but points has {n}; "
                "pass the ordering of these points"
            )
        n0 = uniform.size_for_rho(rho0)
        if n0 == len(uniform) and len(uniform) < n_ordered:
            raise InputError(
                f"uniform ordering stops at radius {uniform.radius[-1]:g} > rho0 = {rho0:g}; "
                "pass a full uniform ordering or one stopped at rho0"
            )
    if ex is not None and ex[uniform.order[:n0]].any():
        raise InputError(
            "uniform ordering includes excluded points; build it with the same exclude"
        )
    return uniform, n0


def _join_at_floor(w: Ordering, uniform: Ordering, n0: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Radii and parents of the floor ordering: the uniform prefix's for its first ``n0`` points,
    the weighted ordering's after, capped at the floor's last radius (and how many were capped)."""
    radius = w.radius.copy()
    parent = w.parent.copy()
    radius[:n0] = uniform.radius[:n0]
    parent[:n0] = uniform.parent[:n0]
    clamped = 0
    if n0 and n0 < radius.size and radius[n0] > radius[n0 - 1]:
        # only numerical slack of the band engine can get here (the bound says <= rho0 < radius[n0-1])
        cap = radius[n0 - 1]
        clamped = int((radius[n0:] > cap).sum())
        # (INFO, not a warning: nothing for the user to do, and no guarantee changes)
        log.info(
            "density floor: %d weighted radii just past the floor were above its last radius "
            "(numerical slack of the band metric) and were capped to it, so that radii never "
            "increase; every level past the floor still covers within rho0", clamped
        )
        radius[n0:] = np.minimum(radius[n0:], cap)
    return radius, parent, clamped


def build_orderings(
    points: Any,
    maps: Mapping[str, Any],
    adaptive: float | None,
    density_floor: float | None,
    *,
    combine: str = "mean",
    eps: float | None = None,
    percentiles: tuple[float, float] | None = None,
    exclude: Any = None,
    uniform: Ordering | None = None,
    weight_maps: Sequence[str] | None = None,
    seeds: Any = None,
    progress: ProgressCallback = None,
    **engine: Any,
) -> dict[str, Ordering]:
    """The feature-sensitive orderings a build stores beside its main (uniform) ordering.

    Args:
        points: (N, 3) coordinates.
        maps: ``{name: values}`` or ``{name: (values, params)}`` (as from
            :func:`lodbuilder.features.compute_importance`).
        adaptive: the adaptivity a in [0, 1]; None means 1 when a density floor is asked for and
            no weighted ordering otherwise.
        density_floor: rho0, or None for no density-floor ordering.
        combine: ``"mean"`` or ``"max"`` of the normalised maps.
        eps, percentiles: see :mod:`lodbuilder.features.weights`.
        exclude: boolean mask of outliers left out of every ordering.
        uniform: the main ordering (same ``exclude``), reused for the density floor's prefix.
        weight_maps: names of the maps that drive the cost (default: every map except ``noise``,
            which flags outliers rather than features).
        seeds: must-keep input indices that start the weighted ordering (the density floor
            starts with the uniform prefix, which starts with the main ordering's seeds).

    Returns:
        ``{"weighted": Ordering}`` when ``adaptive`` is set, plus ``{"floor": Ordering}`` when
        ``density_floor`` is set. Each Ordering's ``stats`` names its kind and parameters.
    """
    pts = validate_points(points)
    if adaptive is None and density_floor is None:
        return {}
    a = 1.0 if adaptive is None else adaptive
    cost, params = _cost(maps, pts.shape[0], a, weight_maps, combine, eps, percentiles)
    out: dict[str, Ordering] = {}
    total = int(adaptive is not None) + int(density_floor is not None)
    report(progress, "orderings", 0, total)
    if adaptive is not None:
        o = weighted_ordering(pts, cost, exclude=exclude, seeds=seeds, **engine)
        out["weighted"] = _with_stats(o, params)
        report(progress, "orderings", 1, total)
    if density_floor is not None:
        o = density_floor_ordering(
            pts, cost, density_floor, uniform=uniform, exclude=exclude, **engine
        )
        out["floor"] = _with_stats(o, params)
        report(progress, "orderings", total, total)
    return out


def _cost(maps: Mapping[str, Any], n: int, a: float, weight_maps: Sequence[str] | None, combine: str,
          eps: float | None, percentiles: tuple[float, float] | None) -> tuple[np.ndarray, dict[str, Any]]:
    """The per-point cost of adaptivity ``a`` from the weight maps, and its parameters."""
    from ..features.weights import DEFAULT_EPS, DEFAULT_PERCENTILES, combine_maps, cost_from_weights

    names = list(weight_maps) if weight_maps is not None else [m for m in maps if m != "noise"]
    missing = [m for m in names if m not in maps]
    if missing:
        raise InputError(f"weight maps {missing} were not computed; add them to --importance")
    if not names:
        raise InputError(
            "an adaptive ordering needs an importance map other than noise; "
            "add e.g. curvature to --importance"
        )
    eps = DEFAULT_EPS if eps is None else eps
    pct = DEFAULT_PERCENTILES if percentiles is None else percentiles
    w = combine_maps({m: maps[m] for m in names}, n, combine=combine, percentiles=pct)
    params = {
        "maps": names,
        "adaptivity": float(a),
        "combine": combine,
        "eps": float(eps),
        "percentiles": [float(pct[0]), float(pct[1])],
    }
    return cost_from_weights(w, a, eps), params


def _with_stats(o: Ordering, params: dict[str, Any]) -> Ordering:
    return Ordering(
        o.order,
        o.radius,
        o.parent,
        o.voxel_size,
        o.band_radius,
        o.seeds,
        o.n_points,
        dict(o.stats) | params,
    )


# ---------------------------------------------------------------------------------------------
# glue for build_archive: maps, outliers, the main ordering and the extra orderings of one scan

#: name of the boolean per-point attribute that flags outliers left out of the orderings
OUTLIER_ATTRIBUTE = "outlier"


@dataclass
class FeatureBuild:
    """What a feature-sensitive build adds to an archive record.

    ``scan`` is the input scan, with a boolean ``outlier`` attribute added when outliers were left
    out; ``ordering`` the main (uniform) ordering without the outliers; ``importance`` the maps
    ``{name: (values, params)}`` in input order; ``orderings`` the extra orderings
    ``{name: (Ordering, params)}``; ``build`` the parameters for the archive's build record.
    """

    scan: Any
    ordering: Ordering
    importance: dict[str, tuple[np.ndarray, dict[str, Any]]]
    orderings: dict[str, tuple[Ordering, dict[str, Any]]]
    build: dict[str, Any]


def feature_build(
    scan: Any,
    *,
    importance: Any = None,
    adaptive: float | None = None,
    density_floor: float | None = None,
    outlier_threshold: float | None = None,
    importance_k: int = 16,
    combine: str = "mean",
    seeds: Any = None,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    max_memory: int | None = None,
    progress: ProgressCallback = None,
) -> FeatureBuild:
    """Importance maps, outlier flags and every ordering of one scan, ready for the archive writer.

    Args:
        scan: a :class:`lodbuilder.io.base.Scan`.
        importance: map names (``"curvature,colour,noise"``, see
            :mod:`lodbuilder.features.registry`); default ``curvature`` when ``adaptive`` or
            ``density_floor`` is set.
        adaptive: adaptivity a in [0, 1] of the ``weighted`` ordering (None: no weighted ordering,
            except 1 for the density floor).
        density_floor: rho0 of the ``floor`` ordering (None: none).
        outlier_threshold: leave points whose ``noise`` score exceeds this out of every ordering;
            they stay in the scan, flagged by the boolean attribute ``outlier`` and counted in
            ``build["outliers"]``. ``noise`` is computed (and stored) when not asked for.
        importance_k: neighbours per point of the built-in maps.
    """
    from ..features.registry import compute_importance

    pts = validate_points(scan.points)
    names, thr = _map_names(scan, importance, adaptive is not None or density_floor is not None, outlier_threshold)
    maps = compute_importance(scan, names, k=importance_k, progress=progress) if names else {}
    engine: dict[str, Any] = {"voxel_size": voxel_size, "band_radius": band_radius}
    engine |= {} if max_memory is None else {"max_memory": max_memory}
    build: dict[str, Any] = {}
    exclude = None
    if thr is not None:
        scan, exclude, build["outliers"] = _flag_outliers(scan, maps["noise"][0], thr)
    main = order_subset(pts, exclude, seeds=seeds, progress=progress, **engine)
    extra = build_orderings(pts, maps, adaptive, density_floor, combine=combine, exclude=exclude, uniform=main,
                            seeds=seeds, progress=progress, **engine)
    orderings = {name: (o, _ordering_params(o)) for name, o in extra.items()}
    if maps:
        build["importance"] = {name: params for name, (_, params) in maps.items()}
    if orderings:
        build["orderings"] = {name: p for name, (_, p) in orderings.items()}
    return FeatureBuild(scan, main, dict(maps), orderings, build)


def _map_names(scan: Any, importance: Any, ordered_by_maps: bool, outlier_threshold: Any) -> tuple[list[str], float | None]:
    """The importance maps to compute (curvature when an ordering needs one and none is named;
    noise when outliers are flagged) and the checked outlier threshold."""
    from ..features.registry import map_name, parse_names

    names: list[str] = [] if importance is None else parse_names(importance)
    if not names and ordered_by_maps:
        names = ["curvature"]
    if outlier_threshold is None:
        return names, None
    thr = float(check_positive(outlier_threshold, "outlier threshold", allow_none=False))  # type: ignore[arg-type]
    if "noise" not in [map_name(s) for s in names]:
        names.append("noise")
    if OUTLIER_ATTRIBUTE in scan.attributes:
        raise InputError(
            f"scan {scan.name!r} already has an attribute {OUTLIER_ATTRIBUTE!r}; rename it "
            "before flagging outliers"
        )
    return names, thr


def _flag_outliers(scan: Any, noise: np.ndarray, thr: float) -> tuple[Any, np.ndarray | None, dict[str, Any]]:
    """The scan with its ``outlier`` attribute (when any point's noise score exceeds ``thr``), the
    mask to exclude from the orderings (None when none) and the build record's entry."""
    mask = noise > thr
    n_out = int(mask.sum())
    exclude = None
    if n_out:
        exclude = check_exclude(mask, mask.shape[0])
        scan = replace(scan, attributes=dict(scan.attributes) | {OUTLIER_ATTRIBUTE: mask})
    log.info("outliers: %d point(s) with noise score > %g left out of the orderings", n_out, thr)
    return scan, exclude, {"map": "noise", "threshold": thr, "count": n_out}


def _ordering_params(o: Ordering) -> dict[str, Any]:
    keys = ("kind", "maps", "adaptivity", "combine", "eps", "percentiles", "rho0", "n_floor")
    return {k: o.stats[k] for k in keys if k in o.stats}


def floor_positions(
    stored_radius: np.ndarray, n_ordered: int, weighted_positions: np.ndarray, rho: float, size: int
) -> np.ndarray:
    """:func:`floor_query_arrays` on an archive's stored arrays: the stored order *is* the uniform
    ordering (positions 0..n_ordered-1) and an extra ordering is stored as positions. Returns
    stored positions."""
    return floor_query_arrays(
        np.arange(n_ordered, dtype=np.int64),
        np.asarray(stored_radius)[:n_ordered],
        weighted_positions,
        len(stored_radius),
        rho,
        size,
    )
