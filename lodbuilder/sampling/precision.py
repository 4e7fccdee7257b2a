"""Radii that float arithmetic can promise.

The kernels measure distances in grid units ``u = (p - origin) / h`` (float64). Each coordinate of
``u h`` is ``(p - origin)(1 + t)`` with ``|t| <= 2 * 2^-53`` (one rounding for the difference, one for
the division), so it is off by at most ``2^-52 S`` in world units, where ``S`` is the largest
``|p - origin|`` (the bounding box plus the band's margin on each side). The difference of two such
coordinates is off by ``2^-51 S``, the Euclidean norm of three of them by ``sqrt(3) 2^-51 S`` plus
a relative ``~6 2^-53`` for the subtraction, squares, sum, root and the final ``* h``. Every
radius the kernels store is at least such a computed distance (a grid-phase value is ``max`` of the
band distance and the Euclidean distance to the point's labelled sample; a tail value is a
Euclidean distance to a chosen point). Hence

    true distance <= computed * (1 + REL) + ABS * S,   REL = ABS = 2^-49 (a safety factor >= 2)

and storing ``radius * (1 + REL) + ABS * S`` for every positive finite radius keeps each stored
radius an upper bound of the true covering radius (the map is increasing, so radii stay
non-increasing; 0 and inf are kept).

Where ``ABS * S`` is not small next to the radii themselves (PRECISION_SHARE of their median), the
radii say little about the points: a voxel or band far larger than the scan, or points spread far
beyond their spacing (outliers at 1e18 among unit-scale points). Those builds are refused with a
:class:`~lodbuilder.errors.PrecisionError` naming the cause and the fix.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import PrecisionError

REL = 2.0**-49
ABS = 2.0**-49
PRECISION_SHARE = 1e-4  # refuse when rounding may reach this share of the median radius


def span(extent: float, h: float, r: float) -> float:
    """``S``: an upper bound of ``|p - origin|`` over the points and axes of a scan whose largest
    bounding-box side is ``extent`` in a band of voxel size ``h`` and radius ``r`` (the band's
    origin is the box's low corner minus ``ceil(r / h) + 3`` voxels)."""
    return extent + (math.ceil(r / h) + 4) * h


def rounding_bound(s: float) -> float:
    """The absolute part ``ABS * S`` (world units) of the rounding bound."""
    return ABS * s


def promise(radius: np.ndarray, delta: float) -> np.ndarray:
    """Radii raised by the rounding bound: ``radius (1 + REL) + delta`` where positive and finite."""
    out = np.asarray(radius, dtype=np.float64).copy()
    grow = (out > 0) & np.isfinite(out)
    out[grow] = out[grow] * (1.0 + REL) + delta
    return out


def promise_one(value: float, delta: float) -> float:
    return value * (1.0 + REL) + delta if 0.0 < value < math.inf else value


def check_precision(
    radius: np.ndarray,
    delta: float,
    *,
    extent: float,
    h: float,
    r: float,
    user_grid: bool,
) -> None:
    """Refuse radii (world units, before :func:`promise`) that rounding can spoil: ``delta``
    above PRECISION_SHARE of the median finite radius (the kernels order distinct points, so a
    radius of 0 is a distance rounding took away). ``user_grid``: the voxel size or band radius was given (then a
    grid far larger than the scan is named as the cause)."""
    finite = radius[np.isfinite(radius)]
    if finite.size == 0:
        return  # seeds only: no distance was measured
    # the kernels see distinct points only: a radius of 0 is a distance lost to rounding
    typical = float(np.median(finite))
    if typical > 0 and delta <= PRECISION_SHARE * typical:
        return
    share = delta / typical if typical > 0 else math.inf
    lost = f"{share:.2g} of" if math.isfinite(share) else "all of"
    margin = (math.ceil(r / h) + 4) * h
    if user_grid and margin > extent:
        raise PrecisionError(
            f"voxel_size={h:.3g} with band_radius={r:.3g} is far larger than the scan (extent "
            f"{extent:.3g}): rounding in grid units may take {lost} the point distances, so no "
            "radius can be promised; use a voxel_size near the point spacing (leave --voxel-size "
            "and --band-radius out for the automatic one)"
        )
    near = f"about {typical:.3g} apart" if typical > 0 else "too close to tell apart"
    raise PrecisionError(
        f"the points span {extent:.3g} while most are {near}: float64 rounding at that spread may "
        f"take {lost} their distances, so no radius can be promised; points far from the rest "
        "(outliers)? drop them (crop the scan to the part you need) and build again"
    )
