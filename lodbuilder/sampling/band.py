"""The offset band: a sparse set of voxels within the band radius r of the points.

Automatic parameters (documented rule):
    s = typical point spacing (median distance to the 6th neighbour x sqrt(pi / 6), which is the
        spacing of a jittered grid and the mean spacing of random samples), on up to 50,000 points;
    voxel size  h = 2 s;
    band radius r = 2.5 h.
With these, the band is about 2r/h = 5 voxels thick and holds about 1.3 voxels per point; sheets closer
than about 2r (5 point spacings) are bridged, so pass a smaller ``voxel_size`` for thin structures.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ..errors import InputError, MemoryBudgetError

VOXEL_PER_SPACING = 2.0
BAND_PER_VOXEL = 2.5
MIN_BAND_PER_VOXEL = 1.75  # the 8 corners of a point's cell must lie in the band (sqrt(3) ~ 1.732)
BYTES_PER_VOXEL = 120  # coord 12, nbr 24, cs 8, key 8, hash 24, T 4, label 8, stamp 4, cell 4, cost 4 + slack
BYTES_PER_POINT = 200
MAX_COORD = (1 << 21) - 1


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
    ``keys``/``coord``/``nbr``: the voxels in Morton order; ``cs``: per-voxel point ranges;
    ``hkeys``/``hvals``: hash map Morton key -> voxel index.
    """

    origin: np.ndarray
    h: float
    r: float
    u: np.ndarray
    perm: np.ndarray
    keys: np.ndarray
    coord: np.ndarray
    nbr: np.ndarray
    cs: np.ndarray
    hkeys: np.ndarray
    hvals: np.ndarray

    @property
    def n_voxels(self) -> int:
        return int(self.keys.shape[0])

    @property
    def nbytes(self) -> int:
        return sum(
            a.nbytes for a in (self.u, self.perm, self.keys, self.coord, self.nbr, self.cs, self.hkeys, self.hvals)
        )


def build_band(
    points: np.ndarray, h: float, r: float, max_memory: int | None = None
) -> Band:
    """Build the band of radius ``r`` on a grid of spacing ``h`` around (distinct) ``points``."""
    from .._kernels.grid import band_keys, build_index, morton_keys

    if max_memory is None:
        max_memory = default_max_memory()
    rad = r / h
    margin = math.ceil(rad) + 3
    lo = points.min(axis=0)
    origin = lo - margin * h
    u = (points - origin) / h
    extent = int(math.ceil(float(u.max()))) + margin
    if extent > MAX_COORD:
        need = h * extent / MAX_COORD
        raise InputError(
            f"voxel_size={h:g} would need {extent:,} voxels along one axis of the bounding box "
            f"(at most {MAX_COORD:,} can be indexed); use a voxel_size of at least {need:.3g}"
        )
    cells = np.floor(u).astype(np.int64)
    ckeys = morton_keys(cells)
    perm = np.argsort(ckeys, kind="stable")
    ckeys = ckeys[perm]
    u = np.ascontiguousarray(u[perm])
    _, ostart = np.unique(ckeys, return_index=True)
    occ = cells[perm[ostart]]
    ostart = np.append(ostart, ckeys.shape[0]).astype(np.int64)
    budget_voxels = (max_memory - BYTES_PER_POINT * points.shape[0]) // BYTES_PER_VOXEL

    def too_big(count: str) -> MemoryBudgetError:
        return MemoryBudgetError(
            f"voxel_size={h:g} with band_radius={r:g} needs {count} voxels, more than max_memory="
            f"{max_memory / 2**30:.2f} GiB allows ({max(budget_voxels, 0):,}); increase voxel_size or max_memory"
        )

    if budget_voxels < occ.shape[0]:
        raise too_big(f"at least {occ.shape[0]:,}")
    hk, count = band_keys(u, occ, ostart, rad, budget_voxels)
    if count < 0:
        raise too_big(f"more than {budget_voxels:,}")
    keys = np.sort(hk[hk >= 0])
    del hk
    hkeys, hvals, coord, nbr = build_index(keys)
    cs = np.searchsorted(ckeys, keys).astype(np.int64)
    cs = np.append(cs, ckeys.shape[0])
    return Band(origin, h, r, u, perm, keys, coord, nbr, cs, hkeys, hvals)


def band_distance(
    points: np.ndarray,
    sources: np.ndarray,
    voxel_size: float | None = None,
    band_radius: float | None = None,
) -> np.ndarray:
    """Band (surface) distance from the points ``sources`` (indices) to every point, by one march.

    This is the metric the ordering uses: first-order Fast Marching in the band, then each point's
    value min over its cell's 8 corner voxels of T[v] + |p - v|.
    """
    from .._kernels.march import multi_source_distance
    from .._validate import validate_indices, validate_points

    pts = validate_points(points)
    src = validate_indices(sources, pts.shape[0], "sources")
    h, r = choose_parameters(pts, voxel_size, band_radius)
    band = build_band(pts, h, r)
    inv = np.empty(pts.shape[0], dtype=np.int64)
    inv[band.perm] = np.arange(pts.shape[0])
    vcost = np.ones(band.n_voxels, dtype=np.float32)
    dq, _, _ = multi_source_distance(
        band.u, band.coord, band.nbr, band.cs, band.hkeys, band.hvals, vcost,
        np.ones(pts.shape[0]), inv[src],
    )
    out = np.empty(pts.shape[0])
    out[band.perm] = dq * h
    return out
