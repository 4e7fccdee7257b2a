"""Importance weights -> a per-point cost F for the weighted farthest point ordering.

    w_norm = clip((w - P_lo(w)) / (P_hi(w) - P_lo(w)), 0, 1)       robust percentile normalisation
    w      = mean or max of the normalised maps                     several maps combined
    F      = max(eps, (1 - a) + a * w)                             a = adaptivity in [0, 1]

F lies in [eps, 1]: a = 0 gives F = 1 (the uniform ordering); a = 1 gives F = w, so points at or
below the P_lo percentile cost eps (distances there count 1/eps times less: on a surface the
sample density ends up about (F_max / F_min)^2 = 1/eps^2 times lower there than at the most
important points). eps = 0.1 by default; a smaller eps starves flat regions further, and makes the
band engine's Euclidean tail slower (its search radius grows as 1/F_min).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .._validate import strict_keywords
from ..errors import InputError

DEFAULT_PERCENTILES = (5.0, 95.0)
DEFAULT_EPS = 0.1


@strict_keywords
def validate_weights(values: Any, n: int, name: str = "weights") -> np.ndarray:
    """Return an importance map as (N,) float64, finite and >= 0, or raise an InputError naming it."""
    try:
        arr = np.asarray(values)
    except Exception as exc:
        raise InputError(f"importance map {name!r} is not an array of numbers: {exc}") from None
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating)
        or np.issubdtype(arr.dtype, np.integer)
        or arr.dtype == np.bool_
    ):
        raise InputError(f"importance map {name!r} must hold real numbers, got dtype {arr.dtype}")
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.ndim != 1 or arr.shape[0] != n:
        got = f"{arr.shape[0]} values" if arr.ndim == 1 else f"shape {arr.shape}"
        raise InputError(
            f"importance map {name!r} has {got} but the scan has {n} points; give one value per point"
        )
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        raise InputError(
            f"importance map {name!r} has {int(bad.sum())} NaN or inf value(s) (first at index "
            f"{int(np.flatnonzero(bad)[0])}); fill them (e.g. with np.nan_to_num) before use"
        )
    neg = arr < 0
    if neg.any():
        i = int(np.argmin(arr))
        raise InputError(
            f"importance map {name!r} has {int(neg.sum())} negative value(s) (min {arr[i]:g} at "
            f"index {i}); importance must be >= 0: shift or clip it"
        )
    return arr


@strict_keywords
def check_adaptivity(a: Any) -> float:
    try:
        v = float(a)
    except (TypeError, ValueError):
        raise InputError(f"adaptivity must be a number in [0, 1], got {a!r}") from None
    if not math.isfinite(v) or v < 0 or v > 1:
        raise InputError(f"adaptivity must be a number in [0, 1], got {a!r}")
    return v


@strict_keywords
def normalise(
    values: np.ndarray, percentiles: tuple[float, float] = DEFAULT_PERCENTILES
) -> np.ndarray:
    """Map values to [0, 1] by robust percentiles: P_lo -> 0, P_hi -> 1, clipped outside.

    When the features are rare (fewer points than 100 - P_hi percent, e.g. a folded edge on a
    mostly flat sheet) P_hi equals P_lo; the range then falls back to P_lo .. max so the rare
    features still stand out. Only a constant map has no contrast and maps to 0.
    """
    lo_p, hi_p = percentiles
    if not (0 <= lo_p < hi_p <= 100):
        raise InputError(
            f"percentiles must satisfy 0 <= low < high <= 100, got ({lo_p!r}, {hi_p!r})"
        )
    lo, hi = np.percentile(values, [lo_p, hi_p])
    if not hi > lo:
        hi = float(np.max(values))
        if not hi > lo:
            return np.zeros(values.shape[0])
    return np.clip((values - lo) / (hi - lo), 0.0, 1.0)


@strict_keywords
def combine_maps(
    maps: Mapping[str, Any] | Sequence[Any],
    n: int,
    *,
    combine: str = "mean",
    percentiles: tuple[float, float] = DEFAULT_PERCENTILES,
) -> np.ndarray:
    """Validate, normalise and combine importance maps into one (N,) array in [0, 1].

    ``maps`` is a dict name -> values (or name -> (values, params)) or a list of arrays.
    """
    if combine not in ("mean", "max"):
        raise InputError(f"combine must be 'mean' or 'max', got {combine!r}")
    items = (
        list(maps.items())
        if isinstance(maps, Mapping)
        else [(f"map {i}", m) for i, m in enumerate(maps)]
    )
    if not items:
        raise InputError("no importance map given; name at least one (e.g. curvature)")
    normed = []
    for name, m in items:
        if isinstance(m, tuple):
            m = m[0]
        normed.append(normalise(validate_weights(m, n, name), percentiles))
    stack = np.stack(normed)
    return stack.mean(axis=0) if combine == "mean" else stack.max(axis=0)


@strict_keywords
def cost_from_weights(w: np.ndarray, adaptivity: float, eps: float = DEFAULT_EPS) -> np.ndarray:
    """F = max(eps, (1 - a) + a * w) for a combined map ``w`` in [0, 1]."""
    a = check_adaptivity(adaptivity)
    if not (0 < eps <= 1):
        raise InputError(f"eps must be a number in (0, 1], got {eps!r}")
    f = (1.0 - a) + a * np.asarray(w, dtype=np.float64)
    return np.clip(f, eps, 1.0)
