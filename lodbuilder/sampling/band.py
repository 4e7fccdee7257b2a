"""The offset band: a sparse set of voxels within the band radius of the points.

Automatic parameters (documented rule):
    s = typical point spacing (median distance to the 6th neighbour x sqrt(pi / 6), which is the
        spacing of a jittered grid and the mean spacing of random samples), on up to 50,000 points;
    voxel size  h = 2 s;
    band radius r = 2.5 h.
With these, the band is about 2r/h = 5 voxels thick and holds about 1.3 voxels per point.

Depth cost: the front moves through a voxel at cost 1 + DEPTH_COST * q^2, where q is the voxel's
depth ratio (distance to the nearest point over that point's band radius, 0 on the points, 1 at the
band's edge). Without it, paths on a curved surface cut through the inner side of the band, which
shortens distances by about r / R (R the radius of curvature); with it they stay near the points.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ..errors import InputError, MemoryBudgetError

VOXEL_PER_SPACING = 2.0
BAND_PER_VOXEL = 2.5
MIN_BAND_PER_VOXEL = 1.75  # the 8 corners of a point's cell lie in the band (sqrt(3) ~ 1.732)
DEPTH_COST = 0.2
BYTES_PER_VOXEL = 96  # while ordering: keys 8, nbr 24, cs 4, T/vlab/stamp/seen/heap/vcost/cellof 36 + slack
BYTES_PER_POINT = 120
MAX_COORD = (1 << 21) - 1
MAX_POINTS = (1 << 31) - 1  # point and voxel indices are int32


def median_spacing(
    points: np.ndarray, sample: int = 50_000, k: int = 6, subset: int = 500_000
) -> float:
    """Typical point spacing: the median distance to the k-th neighbour times sqrt(pi / k).

    On a surface sampled at density 1/s^2 this is about s whether the samples are a jittered grid
    (like a range scan) or random; the plain nearest-neighbour distance would be half of s for random
    samples. Measured on a deterministic sample of the points; above ``subset`` points the
    neighbours are searched in a random subset of that size and the spacing scaled by
    sqrt(subset / n) (a surface's spacing grows as the square root of the thinning).
    """
    from scipy.spatial import cKDTree

    n = points.shape[0]
    if n < 2:
        return 0.0
    rng = np.random.default_rng(0)
    scale = 1.0
    if n > subset:
        points = points[np.sort(rng.choice(n, subset, replace=False))]
        scale = math.sqrt(subset / n)
        n = subset
    tree = cKDTree(points)
    q = points[rng.choice(n, sample, replace=False)] if n > sample else points
    k = min(k, n - 1)
    d, _ = tree.query(q, k=k + 1, workers=-1)
    dk = d[:, k]
    s = float(np.median(dk)) * math.sqrt(math.pi / k) * scale
    if s <= 0.0:
        s = float(dk[dk > 0].min()) if (dk > 0).any() else 0.0
    return s


def default_max_memory() -> int:
    """60 % of the physical memory."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        total = 8 << 30
    return int(0.6 * total)


def choose_parameters(
    points: np.ndarray, voxel_size: float | None, band_radius: float | None
) -> tuple[float, float]:
    """Voxel size and band radius: the overrides, or the automatic rule of this module."""
    if voxel_size is None:
        if band_radius is not None:
            voxel_size = band_radius / BAND_PER_VOXEL
        else:
            s = median_spacing(points)
            if s <= 0.0:
                extent = float(np.ptp(points, axis=0).max())
                s = extent if extent > 0 else 1.0
            voxel_size = VOXEL_PER_SPACING * s
    if band_radius is None:
        band_radius = BAND_PER_VOXEL * voxel_size
    if band_radius < MIN_BAND_PER_VOXEL * voxel_size:
        raise InputError(
            f"band_radius={band_radius:g} is too small for voxel_size={voxel_size:g}: it must be at "
            f"least {MIN_BAND_PER_VOXEL} x voxel_size ({MIN_BAND_PER_VOXEL * voxel_size:g})"
        )
    return float(voxel_size), float(band_radius)


@dataclass
class Band:
    """A sparse voxel band around points sorted by cell.

    ``u``: (M, 3) grid coordinates of the points in cell order; ``perm``: their indices in the input;
    ``keys``/``nbr``: the voxels in Morton order and their 6 neighbours; ``cs``: per-voxel point
    ranges (the points whose cell's lower corner is that voxel); ``vcost``: the cost of moving
    through each voxel (inf for corners outside the band radius, kept only to index cells);
    ``radius``: the band radius of every point in grid units (None when it is r / h everywhere).
    """

    origin: np.ndarray
    h: float
    r: float
    u: np.ndarray
    perm: np.ndarray
    keys: np.ndarray
    nbr: np.ndarray
    cs: np.ndarray
    vcost: np.ndarray
    foot: np.ndarray
    radius: np.ndarray | None = None

    @property
    def n_voxels(self) -> int:
        return int(self.keys.shape[0])

    @property
    def coord(self) -> np.ndarray:
        """(V, 3) integer grid coordinates of the voxels (decoded from the keys)."""
        k = self.keys.astype(np.uint64)
        out = np.zeros((k.shape[0], 3), dtype=np.int64)
        for bit in range(21):
            for a in range(3):
                out[:, a] |= ((k >> np.uint64(3 * bit + a)) & np.uint64(1)).astype(np.int64) << bit
        return out

    @property
    def marchable(self) -> np.ndarray:
        return np.isfinite(self.vcost)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.u, self.perm, self.keys, self.nbr, self.cs, self.vcost, self.foot))


def build_band(
    points: np.ndarray,
    h: float,
    r: float,
    max_memory: int | None = None,
    *,
    radius: np.ndarray | None = None,
    depth_cost: float | None = None,
) -> Band:
    """Build the band of radius ``r`` (or per-point ``radius``, input order) on a grid of spacing
    ``h`` around ``points``."""
    from .._kernels.grid import band_voxels, cell_order, grid_coords, neighbour_table

    n = points.shape[0]
    if n > MAX_POINTS:
        raise InputError(f"points has {n:,} points; at most {MAX_POINTS:,} can be ordered in one run")
    if max_memory is None:
        max_memory = default_max_memory()
    rmax = r if radius is None else max(r, float(radius.max()))
    margin = math.ceil(rmax / h) + 3
    lo = points.min(axis=0)
    origin = lo - margin * h
    extent = int(math.ceil(float((points.max(axis=0) - origin).max()) / h)) + margin
    if extent > MAX_COORD:
        need = h * extent / MAX_COORD
        raise InputError(
            f"voxel_size={h:g} would need {extent:,} voxels along one axis of the bounding box "
            f"(at most {MAX_COORD:,} can be indexed); use a voxel_size of at least {need:.3g}"
        )
    budget_voxels = (max_memory - BYTES_PER_POINT * n) // BYTES_PER_VOXEL
    ckeys = cell_order(points, origin, h)
    perm = np.argsort(ckeys, kind="stable").astype(np.int32)
    ckeys = ckeys[perm]
    u = grid_coords(points, perm, origin, h)
    new = np.empty(n, dtype=bool)
    new[0] = True
    np.not_equal(ckeys[1:], ckeys[:-1], out=new[1:])
    ostart = np.append(np.flatnonzero(new), n).astype(np.int32)
    del new

    def too_big(count: str) -> MemoryBudgetError:
        return MemoryBudgetError(
            f"voxel_size={h:g} with band_radius={r:g} needs {count} voxels, more than max_memory="
            f"{max_memory / 2**30:.2f} GiB allows ({max(budget_voxels, 0):,}); increase voxel_size or max_memory"
        )

    if budget_voxels < ostart.shape[0] - 1:
        raise too_big(f"at least {ostart.shape[0] - 1:,}")
    rad = np.full(n, r / h) if radius is None else np.ascontiguousarray(radius[perm] / h, dtype=np.float64)
    keys, q2, foot, count = band_voxels(u, 1.0 / (rad * rad), rad, ostart, budget_voxels)
    del rad, ostart
    if count < 0:
        raise too_big(f"more than {budget_voxels:,}")
    nbr = neighbour_table(keys)
    cs = np.empty(keys.shape[0] + 1, dtype=np.int32)
    cs[:-1] = np.searchsorted(ckeys, keys)
    cs[-1] = n
    del ckeys
    beta = DEPTH_COST if depth_cost is None else depth_cost
    vcost = np.where(q2 <= 1.0, 1.0 + beta * q2, np.inf).astype(np.float32)
    return Band(origin, h, r, u, perm, keys, nbr, cs, vcost, foot, None if radius is None else radius / h)


def band_distance(
    points: np.ndarray,
    sources: np.ndarray,
    voxel_size: float | None = None,
    band_radius: float | None = None,
) -> np.ndarray:
    """Band (surface) distance from the points ``sources`` (indices) to every point, by one march.

    This is the metric the ordering uses: Fast Marching in the band from exact distances near the
    sources, then each point's value: min over its cell's corner voxels v of T[v] + |p - v|, or its
    exact distance to a source near it.
    """
    from .._kernels.march import multi_source_distance
    from .._validate import validate_indices, validate_points

    pts = validate_points(points)
    src = validate_indices(sources, pts.shape[0], "sources")
    h, r = choose_parameters(pts, voxel_size, band_radius)
    band = build_band(pts, h, r)
    inv = np.empty(pts.shape[0], dtype=np.int32)
    inv[band.perm] = np.arange(pts.shape[0], dtype=np.int32)
    dq, _, _ = multi_source_distance(
        band.u, band.keys, band.nbr, band.cs, band.vcost, np.ones(1), False, inv[src],
    )
    out = np.empty(pts.shape[0])
    out[band.perm] = dq * h
    return out
