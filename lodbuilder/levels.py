"""Level results and the array logic behind level queries (no HDF5 here).

Definitions (``radius`` is the stored, non-increasing insertion radius; ``k(rho)`` the number of
leading points with ``radius > rho``):

* **Level by rho** = the prefix of length ``k(rho)``. Every input point lies within
  ``radius[k] <= rho`` of a kept point (in the band metric of the build, which bounds the
  Euclidean distance from above).
* **Level by size / fraction** = the prefix of that length; its covering bound is ``radius[size]``.
* **Box refinement** (finer ``rho_inner`` inside an axis-aligned box, ``rho_outer`` elsewhere):
  the prefix ``k(rho_outer)`` plus every point of the prefix ``k(rho_inner)`` that lies in the box
  grown by ``rho_inner``. Guarantee: every input point inside the box is within ``rho_inner`` of a kept
  point, and every input point is within ``rho_outer``. (The point that covers ``p`` in the fine prefix
  is within ``rho_inner`` of ``p``, so it lies in the grown box.)
* **Viewpoint refinement** (``rho(x) = min(rho0 + slope * |x - v|, rho_max)``): a point ``q`` is
  kept when ``radius[q] > rho(q) / (1 + slope)``. Guarantee: every input point ``p`` is within
  ``rho(p)`` of a kept point. (``p`` is covered within ``rho(p)`` by some ``q`` with
  ``radius[q] > rho(p)``; since ``rho`` is ``slope``-Lipschitz, ``rho(q) <= (1 + slope) rho(p)``, so
  ``q`` passes the test.)
* **Representative** of a point at level ``k``: follow parents to the first ancestor of rank < k.

Every rho/size/fraction/box/viewpoint-to-prefix computation of the package is a function of this
module (the archive reader, ``slice``, ``view``, ``info``, ``evaluate``, the collection queries,
the density-floor query and :class:`~lodbuilder.sampling.ordering.Ordering` call them), so that a
level asked the same way has the same size everywhere. The one rounding rule: a fraction ``f`` of
``n`` points is ``f * n`` rounded to the nearest whole number, halves up, clamped to ``[1, n]``
(:func:`size_for_fraction`). Each function states its guarantee with its proof; ``tests/
test_levels.py`` checks each against brute force.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import numpy as np

from ._validate import check_fraction, check_positive, check_size, strict_methods
from .errors import InputError


@strict_methods
@dataclass
class Level:
    """One level of detail of a scan.

    Attributes:
        points: (K, 3) float64 coordinates.
        attributes: per-point arrays (the input's attributes), same order as ``points``.
        source_index: (K,) int64 index of each point in the input file.
        radius: (K,) float64 insertion radius of each point (inf for seeds).
        rank: (K,) int64 position of each point in the archive's stored order.
        rho: the covering bound: every input point is within ``rho`` of a kept point (for a
            refined level, the bound outside the refined region).
        size: K.
        scan: the scan's name.
        ordering: the ordering it is a prefix of (``None`` for the default uniform ordering).
        region: parameters of a selective refinement, if any.
        crs: the scan's coordinate reference system as WKT text (None when unknown); writing the
            level with :func:`lodbuilder.io.write_points` keeps it.
        units: linear unit name of the CRS (``"metre"``, ``"US survey foot"``...), None when unknown.
    """

    points: np.ndarray
    attributes: dict[str, np.ndarray]
    source_index: np.ndarray
    radius: np.ndarray
    rank: np.ndarray
    rho: float
    size: int
    scan: str = ""
    ordering: str | None = None
    region: dict[str, Any] = field(default_factory=dict)
    crs: str | None = None
    units: str | None = None

    def __len__(self) -> int:
        return self.size

    def to_polydata(self) -> Any:
        """A ``pyvista.PolyData`` of the level with its attributes as point data."""
        from ._optional import require

        pv = require("pyvista", "Level.to_polydata")
        poly = pv.PolyData(np.ascontiguousarray(self.points))
        for key, arr in self.attributes.items():
            poly.point_data[key] = np.ascontiguousarray(arr)
        poly.point_data["radius"] = self.radius
        poly.point_data["rank"] = self.rank
        poly.point_data["source_index"] = self.source_index
        return poly


# -- level sizes ------------------------------------------------------------------------------


def count_above(radius: np.ndarray, rho: float) -> int:
    """``k(rho)``: the number of leading entries of the non-increasing ``radius`` that are > rho.

    Proof: ``radius`` is non-increasing, so ``{i : radius[i] > rho}`` is a prefix ``[0, k)``;
    ``-radius`` is non-decreasing and ``searchsorted(-radius, -rho, side="left")`` is the first
    ``i`` with ``-radius[i] >= -rho``, i.e. with ``radius[i] <= rho``: that is ``k``. Then
    ``radius[k] <= rho`` (or ``k = n``): the prefix of length ``k`` covers within rho, and no
    shorter prefix does, since its covering bound ``radius[k - 1]`` is > rho."""
    return int(np.searchsorted(-np.asarray(radius), -rho, side="left"))


def prefix_for_rho(
    radius_index: np.ndarray,
    step: int,
    read_block: Callable[[int, int], np.ndarray],
    n_ordered: int,
    rho: float,
) -> int:
    """:func:`count_above` of the archive's radius array, reading one block of it.

    ``radius_index`` is ``radius[::step]``; ``read_block(lo, hi)`` returns ``radius[lo:hi]``.
    Proof: ``j = count_above(radius_index, rho)`` entries of the index are > rho, so
    ``radius[(j - 1) * step] > rho`` and (when ``j * step < n``) ``radius[j * step] <= rho``; the
    answer therefore lies in ``[(j - 1) * step, min(j * step, n)]`` and is ``lo`` plus the count
    inside that block (0 when ``j == 0``: even ``radius[0]`` is <= rho)."""
    j = count_above(radius_index, rho)
    if j == 0:
        return 0
    lo = (j - 1) * step
    hi = min(j * step, n_ordered)
    return lo + count_above(read_block(lo, hi), rho)


def nonempty(k: int) -> int:
    """A level holds at least one point: ``max(1, k)`` (a rho above every radius gives the
    first point, whose radius is inf for a seed)."""
    return max(1, int(k))


def size_for_rho(radius: np.ndarray, rho: float) -> int:
    """Size of the level by rho: the shortest non-empty prefix whose covering bound is <= rho,
    ``nonempty(count_above(radius, rho))`` (see :func:`count_above` for the proof)."""
    return nonempty(count_above(radius, rho))


def _round_half_up(x: Fraction) -> int:
    return math.floor(x + Fraction(1, 2))


def round_size(count: float, n: int) -> int:
    """A real point count made a level size: rounded to the nearest whole number, halves up,
    and clamped to ``[1, n]`` (the viewer's slider).

    The rounding is exact on the shortest decimal that reads back as ``count`` (``repr``), so
    ``944.5`` gives 945 (Python's ``round`` would give 944)."""
    return min(int(n), max(1, _round_half_up(Fraction(repr(float(count))))))


def size_for_fraction(fraction: float, n: int) -> int:
    """Size of the level holding ``fraction`` of ``n`` points: ``fraction * n`` rounded to the
    nearest whole number, halves up, clamped to ``[1, n]``.

    Guarantee: ``|size - fraction * n| <= 1/2`` unless clamped, and equal distances go up, where
    ``fraction`` is the shortest decimal that reads back as the given float (``0.35`` of 10 points
    is 4 although the binary 0.35 is a little below 0.35). Proof: ``Fraction(repr(f))`` is that
    decimal exactly and the product with ``n`` is exact in rational arithmetic; ``floor(x + 1/2)``
    is the integer nearest ``x``, halves going up; the clamp only acts when it is 0 (f < 1/(2n))."""
    return min(int(n), max(1, _round_half_up(Fraction(repr(float(fraction))) * int(n))))


def log_sizes(lo: float, n: int, count: int) -> list[int]:
    """Distinct level sizes for a coarse-to-fine series (evaluate's default levels, the viewer's
    animation): ``count`` values log-spaced from ``lo`` to ``n``, each a :func:`round_size`,
    increasing, the last one ``n``."""
    values = np.geomspace(max(1.0, float(lo)), float(n), max(1, int(count)))
    return sorted({round_size(float(v), n) for v in values} | {int(n)})


def covering_bound(k: int, n: int, radius_at: Callable[[int], Any], stop: float = 0.0) -> float:
    """Covering bound of the prefix of length ``k`` of an ordering of ``n`` points:
    ``radius[k]`` (``radius_at(k)``; read only when ``k < n``), ``stop`` for the whole ordering
    (0 when it holds every point; a partial build's ``stop_radius`` otherwise).

    Proof: ``radius[k]`` is the distance, when point ``k`` was inserted, from the farthest input
    point to the first ``k`` points (farthest point order inserts the farthest point next);
    distances to a fixed prefix do not change afterwards. The whole ordering holds every point,
    or (stopped early) was left when the next candidate, the farthest point, was at ``stop``."""
    return float(stop) if k >= n else float(radius_at(k))


def pieces_reached(entries: Any, k: int) -> int:
    """How many pieces of the band the prefix of length ``k`` holds a point of, from the ascending
    ranks at which each piece's first point entered (``entries``, the build record's
    ``piece_entries``): the count of entries below k."""
    import bisect

    return bisect.bisect_left(list(entries), int(k))


def check_within_ordering(
    scan: str, rho: float, n_ordered: int, n_points: int, stop: float
) -> None:
    """Refuse a level by ``rho`` finer than a partial ordering reaches: the whole ordered prefix
    covers only within ``stop`` (> rho), so no prefix of it covers within rho.

    Raises :class:`~lodbuilder.errors.LevelBeyondOrderingError` naming the radius and the fix."""
    if rho >= stop:
        return
    from .errors import LevelBeyondOrderingError

    raise LevelBeyondOrderingError(
        f"scan {scan!r} is ordered only down to covering radius {stop:.4g} ({n_ordered:,} of "
        f"{n_points:,} points: a partial build), so no level covers within rho={rho:.4g}; rebuild it "
        "without --size to order every point: lodbuilder build SOURCE -o ARCHIVE --force"
    )


def resolve_size(
    n: int,
    rho: Any = None,
    size: Any = None,
    fraction: Any = None,
    *,
    rho_size: Callable[[float], int],
) -> int:
    """The size of the level asked by exactly one of ``rho``, ``size`` or ``fraction`` in an
    ordering of ``n`` points; ``rho_size(rho)`` is the ordering's :func:`size_for_rho` (an
    archive reads it from its radius index). Checks each value and raises InputError."""
    given = [x is not None for x in (rho, size, fraction)]
    if sum(given) != 1:
        raise InputError("give exactly one of rho, size or fraction")
    if rho is not None:
        return rho_size(check_positive(rho, "rho", allow_none=False))  # type: ignore[arg-type]
    if size is not None:
        return check_size(size, n)
    return size_for_fraction(check_fraction(fraction), n)


def check_box(box: Any) -> np.ndarray:
    """(2, 3) float64 [[xmin, ymin, zmin], [xmax, ymax, zmax]] from 6 numbers."""
    try:
        b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    except (TypeError, ValueError):
        raise InputError(
            f"box must be 6 numbers XMIN YMIN ZMIN XMAX YMAX ZMAX, got {box!r}"
        ) from None
    if not np.isfinite(b).all() or (b[0] > b[1]).any():
        raise InputError(
            f"box must be finite with min <= max on every axis, got {b.ravel().tolist()}"
        )
    return b


def in_box(points: np.ndarray, box: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Mask of the points inside ``box`` grown by ``margin`` on every side (bounds included)."""
    lo, hi = box[0] - margin, box[1] + margin
    return np.all((points >= lo) & (points <= hi), axis=1)


def box_positions(
    fine_points: np.ndarray, k_out: int, box: np.ndarray, rho_inner: float
) -> np.ndarray:
    """Stored positions (sorted) of the box refinement: the coarse prefix ``0 .. k_out - 1`` and
    every later position of ``fine_points`` (the points of the fine prefix ``k(rho_inner)``)
    whose point lies in ``box`` grown by ``rho_inner``.

    Guarantee (``k_out = k(rho_outer)``): every input point is within ``rho_outer`` of a kept
    point, and every input point inside the box within ``rho_inner``. Proof: the coarse prefix
    alone covers within ``rho_outer`` (:func:`count_above`). A point ``p`` inside the box is
    within ``rho_inner`` of some point ``q`` of the fine prefix; if ``q`` is not in the coarse
    prefix, ``|q - p| <= rho_inner`` puts ``q`` in the grown box, so ``q`` is kept."""
    inside = in_box(fine_points[k_out:], box, rho_inner)
    return np.concatenate([np.arange(k_out, dtype=np.int64), k_out + np.flatnonzero(inside)])


def viewpoint_sizes(
    rho_size: Callable[[float], int], rho0: float, slope: float, rho_max: float | None
) -> tuple[int, int]:
    """``(k_coarse, k_fine)`` of the viewpoint refinement, ``rho_size`` being the ordering's
    :func:`size_for_rho`: every kept point lies in the fine prefix ``k(rho0 / (1 + slope))``, and
    every point of the coarse prefix ``k(rho_max)`` (1 without ``rho_max``) is kept.

    Proof: ``rho(x) >= rho0``, so a point with ``radius <= rho0 / (1 + slope)`` fails the rule
    ``radius > rho(x) / (1 + slope)``; ``rho(x) <= rho_max``, so a point with
    ``radius > rho_max >= rho(x) / (1 + slope)`` passes it."""
    k_fine = rho_size(rho0 / (1.0 + slope))
    k_coarse = rho_size(rho_max) if rho_max is not None else 1
    return min(k_coarse, k_fine), k_fine


def viewpoint_positions(
    fine_points: np.ndarray,
    fine_radius: np.ndarray,
    viewpoint: np.ndarray,
    rho0: float,
    slope: float,
    rho_max: float | None,
    k_coarse: int,
) -> np.ndarray:
    """Stored positions (sorted) of the viewpoint refinement, from the fine prefix's points and
    radii (:func:`viewpoint_sizes`): the coarse prefix and every point passing
    :func:`viewpoint_keep`. The guarantee and its proof are in the module docstring."""
    keep = viewpoint_keep(fine_points, fine_radius, viewpoint, rho0, slope, rho_max)
    keep[:k_coarse] = True
    return np.flatnonzero(keep).astype(np.int64)


def viewpoint_bound(
    bounds: tuple[np.ndarray, np.ndarray],
    viewpoint: np.ndarray,
    rho0: float,
    slope: float,
    rho_max: float | None,
) -> float:
    """The largest ``rho(x)`` over the scan's bounding box ``(lo, hi)``: a covering bound of the
    whole viewpoint level (every input point ``p`` is covered within ``rho(p)``, and ``rho``
    grows with the distance to ``viewpoint``, largest at a corner of the box)."""
    lo, hi = bounds
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    far = float(np.sqrt(((corners - viewpoint) ** 2).sum(axis=1)).max())
    return rho0 + slope * far if rho_max is None else min(rho_max, rho0 + slope * far)


def viewpoint_keep(
    points: np.ndarray,
    radius: np.ndarray,
    viewpoint: np.ndarray,
    rho0: float,
    slope: float,
    rho_max: float | None,
) -> np.ndarray:
    """Mask of points kept by the viewpoint rule ``radius > rho(x) / (1 + slope)``."""
    dist = np.sqrt(((points - viewpoint) ** 2).sum(axis=1))
    rho = rho0 + slope * dist
    if rho_max is not None:
        rho = np.minimum(rho, rho_max)
    return radius > rho / (1.0 + slope)


def check_viewpoint(viewpoint: Any, rho0: Any, slope: Any, rho_max: Any):
    try:
        v = np.asarray(viewpoint, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise InputError(f"viewpoint must be 3 numbers x y z, got {viewpoint!r}") from None
    if not np.isfinite(v).all():
        raise InputError(f"viewpoint must be finite, got {v.tolist()}")
    rho0 = check_positive(rho0, "rho0", allow_none=False)
    try:
        s = float(slope)
    except (TypeError, ValueError):
        raise InputError(f"slope must be a number >= 0, got {slope!r}") from None
    if not np.isfinite(s) or s < 0:
        raise InputError(f"slope must be a finite number >= 0, got {slope!r}")
    rho_max = check_positive(rho_max, "rho_max")
    if rho_max is not None and rho_max < rho0:
        raise InputError(f"rho_max ({rho_max}) must be >= rho0 ({rho0})")
    return v, rho0, s, rho_max


def representatives(parent: np.ndarray, k: int) -> np.ndarray:
    """For every stored position, the position of its first ancestor of rank < k (itself when
    its rank is < k), or -1 when its chain of parents ends at a root of rank >= k.

    Pointer doubling: O(N log D) for parent chains of depth D."""
    n = parent.shape[0]
    a = np.empty(n + 1, dtype=np.int64)
    a[:n] = parent
    a[:n][parent < 0] = n  # sentinel
    a[n] = n
    a[:k] = np.arange(k, dtype=np.int64)
    while True:
        b = a[a]
        if np.array_equal(a, b):
            break
        a = b
    out = a[:n]
    out[out == n] = -1
    return out


def cell_average(rep: np.ndarray, k: int, values: np.ndarray) -> np.ndarray:
    """Mean of ``values`` (stored order, (N,) or (N, c)) over the points represented by each of the
    first k points; integer attributes are rounded back to their dtype."""
    ok = rep >= 0
    r = rep[ok]
    counts = np.bincount(r, minlength=k).astype(np.float64)
    vals = np.asarray(values)[ok]
    flat = vals.reshape(vals.shape[0], -1).astype(np.float64)
    sums = np.stack(
        [np.bincount(r, weights=flat[:, j], minlength=k) for j in range(flat.shape[1])], 1
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = sums / counts[:, None]
    mean = mean.reshape((k,) + vals.shape[1:])
    dt = np.asarray(values).dtype
    if np.issubdtype(dt, np.integer):
        info = np.iinfo(dt)
        return np.clip(np.rint(np.nan_to_num(mean)), info.min, info.max).astype(dt)
    if dt.kind == "b":
        return np.nan_to_num(mean) >= 0.5
    return mean.astype(dt if np.issubdtype(dt, np.floating) else np.float64)


# --- the one level query ----------------------------------------------------------------------

@strict_methods
@dataclass(frozen=True)
class LevelQuery:
    """Which level of a scan to read, checked once: every command and the Python API ask for a level
    through one of these, and :func:`lodbuilder.query.read_level` answers it with the level and the
    sentence stating its guarantee.

    * a prefix: exactly one of ``rho`` / ``size`` / ``fraction``, of the uniform ordering or of the
      stored extra ``ordering``;
    * refined inside a box: ``rho`` outside, ``box_rho`` inside ``box`` (6 numbers);
    * refined near a point: ``rho`` at ``viewpoint``, growing by ``slope`` per unit distance,
      capped at ``rho_max``;
    * a density floor chosen at query time: ``floor_rho`` with ``size`` (and ``ordering``, default
      weighted): the uniform level at ``floor_rho`` filled to exactly ``size`` points;
    * filled: ``fill`` (the widest hole to fill, in units of ``rho``) with ``rho``.
    """

    rho: float | None = None
    size: int | None = None
    fraction: float | None = None
    ordering: str | None = None
    box: tuple[float, ...] | None = None
    box_rho: float | None = None
    viewpoint: tuple[float, ...] | None = None
    slope: float | None = None
    rho_max: float | None = None
    floor_rho: float | None = None
    fill: float | None = None

    def __post_init__(self) -> None:
        if self.box is not None and self.box_rho is None:
            raise InputError("--box needs --box-rho (the finer rho inside the box)")
        if self.box_rho is not None and self.box is None:
            raise InputError("--box-rho needs --box XMIN YMIN ZMIN XMAX YMAX ZMAX")
        if (self.viewpoint is None) != (self.slope is None):
            raise InputError("--viewpoint and --slope go together")
        if self.rho_max is not None and self.viewpoint is None:
            raise InputError("--rho-max caps rho far from --viewpoint: give --viewpoint X Y Z and --slope")
        refine = self.box is not None or self.viewpoint is not None
        if refine and self.rho is None:
            raise InputError("--box / --viewpoint need --rho (the coarse rho, or rho at the viewpoint)")
        if self.box is not None and self.viewpoint is not None:
            raise InputError("give either --box or --viewpoint, not both")
        if self.fill is not None:
            if self.rho is None:
                raise InputError("--fill needs --rho R (the density the filled level meets)")
            if refine or self.ordering not in (None, "uniform"):
                raise InputError("--fill fills the plain --rho level of the uniform ordering; leave out --box, "
                                 "--viewpoint and --ordering")
            if self.floor_rho is not None:
                raise InputError("--fill fills one scan's --rho level; leave out --all-scans and --floor-rho")
        if self.floor_rho is not None and self.size is None:
            raise InputError("--floor-rho needs --size N (the exact number of points)")

    @property
    def kind(self) -> str:
        """``"fill"``, ``"box"``, ``"viewpoint"``, ``"floor"`` or ``"prefix"``."""
        if self.fill is not None:
            return "fill"
        if self.box is not None:
            return "box"
        if self.viewpoint is not None:
            return "viewpoint"
        if self.floor_rho is not None:
            return "floor"
        return "prefix"

    @property
    def chosen(self) -> bool:
        """True when one of rho / size / fraction is given (else: every ordered point)."""
        return (self.rho, self.size, self.fraction) != (None, None, None)

    def prefix_size(self, n_ordered: int, rho_size: Callable[[float], int]) -> int:
        """The prefix size of a plain query over ``n_ordered`` ordered points (all of them when
        none of rho / size / fraction is given); see :func:`resolve_size`."""
        if not self.chosen:
            return n_ordered
        return resolve_size(n_ordered, self.rho, self.size, self.fraction, rho_size=rho_size)
