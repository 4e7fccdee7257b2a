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
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validate import check_positive
from ..errors import InputError


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
        try:
            import pyvista as pv
        except ImportError:
            from ..errors import MissingDependencyError

            raise MissingDependencyError(
                "Level.to_polydata needs pyvista: pip install 'lodbuilder[viz]'"
            ) from None
        poly = pv.PolyData(np.ascontiguousarray(self.points))
        for key, arr in self.attributes.items():
            poly.point_data[key] = np.ascontiguousarray(arr)
        poly.point_data["radius"] = self.radius
        poly.point_data["rank"] = self.rank
        poly.point_data["source_index"] = self.source_index
        return poly


def prefix_for_rho(
    radius_index: np.ndarray, step: int, read_block, n_ordered: int, rho: float
) -> int:
    """Number of leading points with radius > rho, reading one block of the radius array.

    ``radius_index`` is ``radius[::step]``; ``read_block(lo, hi)`` returns ``radius[lo:hi]``."""
    j = int(np.searchsorted(-radius_index, -rho, side="left"))  # entries of the index > rho
    if j == 0:
        return 0
    lo = (j - 1) * step
    hi = min(j * step, n_ordered)
    block = read_block(lo, hi)
    return lo + int(np.searchsorted(-block, -rho, side="left"))


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
    lo, hi = box[0] - margin, box[1] + margin
    return np.all((points >= lo) & (points <= hi), axis=1)


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
