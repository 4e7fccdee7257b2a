"""Checks of the viewer's options, shared by :class:`~lodbuilder.viewer.app.LevelViewer` and the
``view`` command (no PyVista here, so the command refuses bad options before loading anything)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from ..errors import InputError

# Off-screen rendering allocates a framebuffer of W x H pixels (several bytes each, plus the
# screenshot copy): 100000 x 100000 aborted inside VTK (std::bad_alloc). Mesa's llvmpipe renders
# at most 16384 pixels a side (wider comes back blank); 8192 keeps a 2-panel frame near 0.5 GB.
MIN_WINDOW = 32
MAX_WINDOW = 8192


def check_window_size(value: Sequence[Any], name: str = "--window-size") -> tuple[int, int]:
    """Return ``value`` as (width, height) in whole pixels within [MIN_WINDOW, MAX_WINDOW]."""
    vals = tuple(value)
    ok = len(vals) == 2 and all(
        isinstance(v, int) or (isinstance(v, float) and v.is_integer()) for v in vals
    )
    if ok and all(MIN_WINDOW <= int(v) <= MAX_WINDOW for v in vals):
        return int(vals[0]), int(vals[1])
    got = " ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in vals) if len(vals) == 2 else repr(vals)
    raise InputError(
        f"{name} must be two whole numbers of pixels between {MIN_WINDOW} and {MAX_WINDOW} "
        f"(WIDTH HEIGHT), got {got}"
    )


def check_point_scale(value: Any, name: str = "--point-scale") -> float:
    """Return ``value`` as a finite float > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a finite number > 0, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise InputError(f"{name} must be a finite number > 0, got {value!r}")
    return v
