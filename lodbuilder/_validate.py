"""Argument checks shared by the public functions.

``check_*`` functions raise; ``validate_*`` functions coerce and return. Every message names the
argument and the value or shape that was wrong.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .errors import InputError


def validate_points(points: Any, name: str = "points") -> np.ndarray:
    """Return ``points`` as a C-contiguous (N, 3) float64 array of finite values, N >= 1."""
    try:
        arr = np.asarray(points)
    except Exception as exc:  # ragged lists and the like
        raise InputError(f"{name} must be an (N, 3) array of numbers: {exc}") from None
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise InputError(
            f"{name} must hold real numbers, got dtype {arr.dtype}; convert it with np.asarray(..., float)"
        )
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    if arr.shape[0] == 0:
        raise InputError(f"{name} is empty: a scan needs at least one point")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    finite = np.isfinite(arr).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InputError(
            f"{name} has {bad.size} point(s) with NaN or inf coordinates (first at index {bad[0]}); "
            "remove them before building"
        )
    return arr


def check_positive(value: Any, name: str, *, allow_none: bool = True) -> float | None:
    """Return ``value`` as a float if it is a finite number > 0 (or None when allowed)."""
    if value is None and allow_none:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a positive number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise InputError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def check_size(value: Any, n: int, name: str = "size") -> int:
    """Return ``value`` as an int in [1, n]."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            value = int(value)
        else:
            raise InputError(f"{name} must be a whole number of points, got {value!r}")
    v = int(value)
    if v < 1 or v > n:
        raise InputError(f"{name} must be between 1 and the number of points ({n}), got {v}")
    return v


def check_fraction(value: Any, name: str = "fraction") -> float:
    """Return ``value`` as a float in (0, 1]."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number in (0, 1], got {value!r}") from None
    if not math.isfinite(v) or v <= 0 or v > 1:
        raise InputError(f"{name} must be a number in (0, 1], got {value!r}")
    return v


def validate_indices(values: Any, n: int, name: str) -> np.ndarray:
    """Return ``values`` as a 1-D int64 array of distinct indices in [0, n)."""
    arr = np.asarray(values)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise InputError(f"{name} must be a 1-D list of point indices, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise InputError(f"{name} must hold integer point indices, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    if arr.size and (arr.min() < 0 or arr.max() >= n):
        raise InputError(f"{name} must be indices in [0, {n}), got values from {arr.min()} to {arr.max()}")
    if np.unique(arr).size != arr.size:
        raise InputError(f"{name} contains repeated indices; list each point once")
    return arr
