"""Argument checks shared by the public functions.

``check_*`` functions raise; ``validate_*`` functions coerce and return. Every message names the
argument and the value or shape that was wrong.
"""

from __future__ import annotations

import difflib
import functools
import inspect
import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any, ParamSpec, TypeVar, overload

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
    if _repeats(arr, n):
        raise InputError(f"{name} contains repeated indices; list each point once")
    return arr


def _repeats(arr: np.ndarray, n: int) -> bool:
    """Whether ``arr`` (indices in [0, n)) holds an index twice: a mask of the n indices where that
    is not much larger than ``arr`` (no sort: a tile's timed seeds are checked in each ordering),
    else a sort."""
    if arr.size < 2:
        return False
    if n <= 16 * arr.size:
        seen = np.zeros(n, bool)
        seen[arr] = True
        return int(np.count_nonzero(seen)) != arr.size
    return bool(np.unique(arr).size != arr.size)


# -- keyword arguments ---------------------------------------------------------------------------

_P = ParamSpec("_P")
_R = TypeVar("_R")


_Extra = Iterable[str] | Callable[[], Iterable[str]] | None


@overload
def strict_keywords(func: Callable[_P, _R]) -> Callable[_P, _R]: ...


@overload
def strict_keywords(
    *, extra: _Extra = None
) -> Callable[[Callable[_P, _R]], Callable[_P, _R]]: ...


def strict_keywords(func: Any = None, *, extra: _Extra = None) -> Any:
    """Decorator of a public function or method: an unknown keyword argument raises
    :class:`~lodbuilder.errors.InputError` naming the function, the closest valid keyword and
    every valid one, instead of Python's bare TypeError::

        @strict_keywords
        def read_scan(path, *, name=None): ...

        read_scan("a.ply", nmae="x")
        # InputError: read_scan() got an unknown keyword argument 'nmae' (did you mean 'name'?);
        # its keywords are: path, name

    A function taking ``**kwargs`` names what they accept with ``extra`` (a list, or a function
    returning one, called at the first unknown keyword). Keywords starting with ``_`` are
    accepted but not listed. The check costs one set lookup per keyword of a call."""

    def decorate(f: Callable[_P, _R]) -> Callable[_P, _R]:
        params = inspect.signature(f).parameters.values()
        kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        own = [p.name for p in params if p.kind in kinds and p.name not in ("self", "cls")]
        if extra is None and any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
            raise TypeError(f"{f.__qualname__} takes **kwargs: name them with extra=")
        valid: set[str] = set(own)
        loaded = extra is None or not callable(extra)
        if extra is not None and not callable(extra):
            own += [k for k in extra if k not in valid]
            valid = set(own)

        @functools.wraps(f)
        def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
            nonlocal loaded, valid
            if kwargs and not valid.issuperset(kwargs):
                if not loaded:
                    own.extend(k for k in extra() if k not in valid)  # type: ignore[misc, operator]
                    valid, loaded = set(own), True
                bad = [k for k in kwargs if k not in valid]
                if bad:
                    where = f.__qualname__.removesuffix(".__init__")  # a class: Level(...)
                    raise InputError(unknown_keywords_message(where, bad, own))
            return f(*args, **kwargs)

        return wrapper

    return decorate(func) if func is not None else decorate


_C = TypeVar("_C", bound=type)


def strict_methods(cls: _C) -> _C:
    """Class decorator: :func:`strict_keywords` on the constructor and on every public method
    defined in the class (names not starting with ``_``; properties, static and class methods are
    left alone). Put it above ``@dataclass`` so that the generated ``__init__`` is checked too."""
    for name, value in list(vars(cls).items()):
        if inspect.isfunction(value) and (name == "__init__" or not name.startswith("_")):
            setattr(cls, name, strict_keywords(value))
    return cls


def quoted_names(items: Iterable[Any], limit: int = 10) -> str:
    """A comma-separated list of names for a message, each quoted with repr (as a message quotes
    one name: so control characters stay escaped and commas in names stay readable), cut after
    ``limit`` with ', ...'; 'none' when empty."""
    items = list(items)
    text = ", ".join(repr(str(x)) for x in items[:limit])
    if len(items) > limit:
        text += ", ..."
    return text or "none"


def unknown_keywords_message(where: str, bad: Sequence[str], valid: Sequence[str]) -> str:
    """One line naming the unknown keyword(s), the closest valid one and every valid one."""
    shown = [k for k in valid if not k.startswith("_")]
    hint = difflib.get_close_matches(bad[0], shown, n=1)
    what = "argument" if len(bad) == 1 else "arguments"
    return (
        f"{where}() got an unknown keyword {what} {', '.join(repr(b) for b in bad)}"
        + (f" (did you mean {hint[0]!r}?)" if hint else "")
        + f"; its keywords are: {', '.join(shown) or 'none'}"
    )
