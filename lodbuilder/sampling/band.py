"""The offset band: a sparse set of voxels within the band radius of the points.

Automatic parameters (documented rule):
    s = typical point spacing (median distance to the 6th neighbour x sqrt(pi / 6), which is the
        spacing of a jittered grid and the mean spacing of random samples), on up to 20,000 points;
    voxel size  h = 2 s;
    band radius r = 2.5 h.
With these, the band is about 2r/h = 5 voxels thick and holds about 1.3 voxels per point.

Thin structures (automatic parameters only): two pieces of surface closer across a gap than
2r would be joined by the band (between 2r and 2r + h only by a few voxels at its edge). The local *sheet separation* of every point is measured on the
cells of the default grid (:mod:`lodbuilder._kernels.sheets`: along the local normal, the nearest
cell of another sheet at least SEP_GAP_MIN voxels = 3 point spacings away; closer layers count as
one noisy sheet). Where another sheet is found, the band is one-sided: a voxel whose nearest point
lies on a thin part is in the band only on that point's side away from the other sheet (up to
SIDE_TOLERANCE voxels, less where the gap is narrower; farther than 0.4 x the separation from that point, only clearly on the outer
side, more than 0.2 x the separation, so that a slightly misjudged normal cannot let voxels near the
middle of a gap in). So no voxel lies in the gap and no gap is bridged whatever h is, and a tight
fold is measured along its outer side (a little longer than the surface, never a shortcut through
its inside). If there is a sheet on the outer side too, the radius there is capped at
0.95 (sep - h) / 2 (never below h). Then the band is *cut between sheets*
(:func:`lodbuilder._kernels.sheets.sheet_cut`): of two neighbouring voxels whose nearest points lie
on different sheets, the one farther from its point leaves the band, and so does a voxel that is a
corner of a cell holding a point of another sheet; so a sheet between two others is bridged to
neither. In a stack joined by folds (an accordion) no choice of sides is consistent around every
fold, so the one-sided band splits it; then, when at least THIN_SHARE % of the scan is thin, the
plain band cut between sheets is used (both sides of every sheet, each up to about the middle of the
gap); with fewer thin points the plain band, as before. Both need a gap of about 2 voxels (4 point
spacings): when no band cut between sheets holds together, at least REFINE_SHARE of the scan is thin
and its median separation is under REFINE_SEP voxels, the band is built on a grid of that separation /
REFINE_SEP (3 spacings apart: 1.36 spacings instead of 2, about 2.2 x the voxels); if that does not hold
together either, the plain band of the default grid is used (5 sheets 3 spacings apart still are: a
few points at the folds' ends form islands of their own). The Euclidean tail never lowers a point from a sample farther
than 0.9 x their separation (a ball smaller than the gap does not reach the other sheet), nor along a
chord steeper than 24 degrees (sin 0.4) to either end's sheet (around a tight fold the chord is much shorter
than the surface); when at least THIN_SHARE % of the scan is thin, the band ordering goes on down
to 0.9 x the typical separation instead of 2 r, so that the tail's limits hardly ever bind.

Coarse closed scans: a closed surface sampled coarsely for its shape (a decimated bunny: head, ears
and paws only a few spacings across) is 'thin' too, its sides 3-10 spacings apart, but there the
other side is the same surface curving round, and the one-sided band measures such parts along
their outside, far longer than they are (levels 1.2-1.8 x Euclidean farthest point sampling's
covering at equal size). Two sheets are flat over less than their separation; a part a few spacings
across is not. So when at least THIN_SHARE % of the scan is thin, the normals of the thin cells
within SHEET_BALL x the separation of a thin cell are compared with its own
(:func:`lodbuilder._kernels.sheets.normal_agreement`, on up to SHEET_SAMPLE cells); unless at least
SHEET_SHARE of the cells tested agree (mean |cos| >= 1 - SHEET_BEND), the plain band is used for the
whole scan (measured: stacks of 3-5 sheets 0.93-0.97, with noise of 0.3 spacings 0.83-0.86, a
folded sheet 0.95-0.99, a flat closed shell 4 spacings thick 0.87-0.97; the bunny's decimations
0.01-0.28, a torus or a cigar 4-8 spacings across 0-0.07). The choice is the whole scan's: a few
flat sheets among many more curved thin parts take the plain band with them; scans under THIN_SHARE %
thin are not judged (bunnyDouble.e57, 14 % thin, 37 % of it flat, keeps its one-sided band: its
thin parts are the two faces of the ears, 3-11 spacings apart, one surface with no misregistration;
its levels cover within 1.06-1.09 x Euclidean farthest point sampling from 1 % of N on, as exact
farthest point sampling along its mesh does, 1.09-1.10; the plain band would give 1.01 but measure
the ears across, not along the surface).

Depth cost: the front moves through a voxel at cost 1 + DEPTH_COST * q^2, where q is the voxel's
depth ratio (distance to the nearest point over that point's band radius, 0 on the points, 1 at the
band's edge). Without it, paths on a curved surface cut through the inner side of the band, which
shortens distances by about r / R (R the radius of curvature); with it they stay near the points.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .._resources import cores as _cores
from .._resources import default_max_memory, release_freed_memory, release_pages
from ..errors import InputError, MemoryBudgetError
from .morton import morton_np, unmorton_np
from .sheets import THIN_SHARE, measure_sheets
from .spacing import axis_max, axis_min, cells, median_spacing

log = logging.getLogger(__name__)

VOXEL_PER_SPACING = 2.0
BAND_PER_VOXEL = 2.5
MIN_BAND_PER_VOXEL = 1.75  # the 8 corners of a point's cell lie in the band (sqrt(3) ~ 1.732)
DEPTH_COST = 0.2
TAIL_FACTOR = 3.0  # the band ordering hands over to the Euclidean tail below TAIL_FACTOR * r (4 r: unsafe)
TAIL_FACTOR_THIN = 2.0  # ... below this x r where sheets come close (at 3 r bunnyDouble's levels covered
# 1.23 x Euclidean FPS from 1 % of N on, 1.09 at 2 r) and on coarse closed surfaces (bun_zipper_res3 1.054)
THIN_RADIUS_MIN = 1.0  # voxels: the thinnest band radius
SIDE_TOLERANCE = 0.15  # voxels: how far on the gap side of its nearest point a voxel may lie
TAIL_PER_SEP = 0.9  # the tail lowers a point only from samples closer than this x its separation
TAIL_SLOPE = 0.4  # ... and along chords with |sin| <= this to both ends' sheets (arc/chord <= 1.03)
SHEET_SHARE = 0.6  # a scan THIN_SHARE % thin is a stack of sheets only when this share of it does
BYTES_PER_VOXEL = 96  # while ordering: keys 8, nbr 24, cs 4, T/vlab/stamp/seen/heap/vcost/cellof 36 + slack
BYTES_PER_POINT = 120
MAX_COORD = (1 << 21) - 1
MAX_POINTS = (1 << 31) - 1  # point and voxel indices are int32


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
class BandPlan:
    """The band's parameters: voxel size ``h``, largest band radius ``r``; where sheets come close
    (input order, None when there is no thin part): the band radius, the separation toward the
    nearer other sheet and the unit normal toward it; the radius below which the ordering is
    finished with Euclidean distances."""

    h: float
    r: float
    radius: np.ndarray | None
    separation: np.ndarray | None
    normal: np.ndarray | None
    handover: float
    outer: np.ndarray | None = None  # the separation on the other side (inf: none)
    found: int = 0  # the thin points measured (a plain plan may have set them aside)

    @property
    def thin_points(self) -> int:
        return 0 if self.separation is None else int(np.isfinite(self.separation).sum())

    @classmethod
    def plain(cls, h: float, r: float) -> BandPlan:
        """The plan without thin parts: one band radius everywhere."""
        return cls(h, r, None, None, None, TAIL_FACTOR * r)


def _automatic(points: np.ndarray, voxel_size: float | None, band_radius: float | None) -> bool:
    """Whether thin parts are looked for (automatic parameters and at least 16 points)."""
    return voxel_size is None and band_radius is None and points.shape[0] >= 16


def plan_band(points: np.ndarray, voxel_size: float | None, band_radius: float | None) -> BandPlan:
    """The band's parameters: the overrides as given, or the automatic rule of this module with a
    one-sided band where sheets come close."""
    h, r = choose_parameters(points, voxel_size, band_radius)
    if not _automatic(points, voxel_size, band_radius):
        return BandPlan.plain(h, r)
    return _thin_plan(points, h, r)


OVERLAP_MAX_POINTS = 200_000  # below this, the plain band is built on a second thread meanwhile ...
OVERLAP_MIN_POINTS = 1_500  # ... down to this: for fewer, starting the thread costs more than it saves


def plan_and_build_band(
    points: np.ndarray, voxel_size: float | None, band_radius: float | None, max_memory: int | None = None, *,
    lattice: np.ndarray | None = None,
) -> tuple[Band, BandPlan, int]:
    """:func:`plan_band` then :func:`build_planned_band`, and the count of thin points found (the
    plan returned may have dropped them). With two cores and fewer than OVERLAP_MAX_POINTS points,
    the plain band (which build_planned_band starts from whatever the plan) is built on a second
    thread while the sheets are measured (both kernels release the GIL; the result is the same);
    for more points one after the other, so that their memory peaks do not add up, and for fewer
    than OVERLAP_MIN_POINTS too (the thread's start and the hand-overs of the GIL between the two
    threads' NumPy steps cost more than the overlap saves: 1.14 vs 1.00 ms for 453 points, 1.70 vs
    1.65 ms for 1,065; 3.4 vs 3.9 ms the other way for 1,889, with a free core)."""

    n = points.shape[0]
    h, r = choose_parameters(points, voxel_size, band_radius)
    if not _automatic(points, voxel_size, band_radius):
        plan = BandPlan.plain(h, r)
        return build_band(points, h, r, max_memory, lattice=lattice), plan, 0
    assert lattice is None, "a lattice places a given grid (fastfps checks it)"
    if OVERLAP_MIN_POINTS <= n < OVERLAP_MAX_POINTS and _cores() >= 2:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(1) as pool:
            plain = pool.submit(build_band, points, h, r, max_memory)
            plan = _thin_plan(points, h, r)
            band = plain.result()
    else:
        plan = _thin_plan(points, h, r)
        release_freed_memory(n)
        band = build_band(points, h, r, max_memory)
        release_freed_memory(n)  # (the band's temporaries: the planned band is decided on top of it)
    found = plan.found
    thin = plan
    band, plan = build_planned_band(points, plan, max_memory, band=band)
    if plan.normal is None and thin.outer is not None:  # (kept only where a finer grid may be needed)
        del band  # (its memory is needed for the finer one)
        refined = _refined(points, thin, max_memory)
        if refined is not None:
            return refined[0], refined[1], found
        band = build_band(points, plan.h, plan.r, max_memory)
    return band, plan, found


REFINE_SHARE = 0.5  # when this share of the scan is thin and its sheets are closer than ...
REFINE_SEP = 2.2  # ... this many voxels, and no band cut between them holds together, a finer grid


def _refined(points: np.ndarray, thin: BandPlan, max_memory: int | None) -> tuple[Band, BandPlan] | None:
    """The band of ``thin`` (a plan whose band fell back to the plain one) on a grid fine enough
    that its typical separation is REFINE_SEP voxels, when it is less; None when that band still
    falls back (or does not fit in memory). The sheets are the ones measured on the default grid
    (separations and normals are lengths and directions, whatever the grid)."""

    h = _typical_separation(thin) / REFINE_SEP
    r = BAND_PER_VOXEL * h
    plan = _with_grid(thin, h, r)
    release_freed_memory(points.shape[0])
    try:
        band = build_band(points, h, r, max_memory)
    except MemoryBudgetError:
        return None
    band, plan = build_planned_band(points, plan, max_memory, band=band)
    if plan.normal is None:
        return None
    log.info("sheets close together: a grid of %.3g instead of %.3g keeps them apart", h, thin.h)
    return band, plan


def _typical_separation(thin: BandPlan) -> float:
    assert thin.separation is not None
    return float(np.median(thin.separation[np.isfinite(thin.separation)]))


def _with_grid(thin: BandPlan, h: float, r: float) -> BandPlan:
    """``thin``'s sheets on a grid of spacing h with band radius r."""
    assert thin.outer is not None
    radius = _thin_radius(thin.outer, h, r)
    return BandPlan(h, r, radius, thin.separation, thin.normal, min(TAIL_FACTOR_THIN * r, thin.handover), thin.outer)


def _thin_radius(sep_out: np.ndarray, h: float, r: float) -> np.ndarray:
    """The band radius where sheets come close: capped at 0.95 (sep_out - h) / 2 (never below h)."""
    with np.errstate(invalid="ignore"):
        return np.clip(0.95 * (sep_out - h) / 2, THIN_RADIUS_MIN * h, r)


def _thin_plan(points: np.ndarray, h: float, r: float) -> BandPlan:
    """The plan for grid spacing h and band radius r with the thin parts measured."""
    plain = BandPlan.plain(h, r)
    sep_in, sep_out, normal, flat = measure_sheets(points, h, r, judge=True)
    if not np.isfinite(sep_in).any():
        return plain
    found = int(np.isfinite(sep_in).sum())
    if flat is not None and flat < SHEET_SHARE:
        log.info(
            "%.0f %% of the scan is thin, but only %.0f %% of it lies on flat sheets (a closed surface "
            "coarse for its shape); using the plain band", 100 * found / sep_in.size, 100 * flat,
        )
        return BandPlan(h, r, None, None, None, TAIL_FACTOR_THIN * r, found=found)  # (3 r: res3 1.054 x FPS)
    radius = _thin_radius(sep_out, h, r)
    # the THIN_SHARE-th percentile of the separation over all points (inf: a smaller share is thin)
    typical = float(np.percentile(sep_in, THIN_SHARE, method="lower"))
    handover = min(TAIL_FACTOR_THIN * r, TAIL_PER_SEP * typical)
    thin = sep_in[np.isfinite(sep_in)]
    # the other side's separation is kept only where a finer grid may be needed (see _refined)
    finer = thin.size >= REFINE_SHARE * sep_in.size and float(np.median(thin)) < REFINE_SEP * h
    return BandPlan(h, r, radius, sep_in, normal, handover, sep_out if finer else None, found)


def block_plan(cell_keys: np.ndarray, reach_voxels: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the band builder: the occupied blocks (keys of BLOCK^3-voxel blocks, sorted) with their
    ranges of cells (``cell_keys``: the sorted Morton keys of the occupied cells), and the sorted
    keys of every block within ``reach_voxels`` of an occupied one."""
    from .._kernels.grid import BLOCK, BLOCK_BITS

    bk = cell_keys >> np.int64(3 * BLOCK_BITS)
    first = np.empty(bk.shape[0], dtype=bool)
    first[0] = True
    np.not_equal(bk[1:], bk[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    bkey = bk[starts]
    bstart = np.append(starts, bk.shape[0]).astype(np.int32)
    reach = (int(math.floor(reach_voxels)) + 1 + BLOCK - 1) // BLOCK
    c = unmorton_np(bkey)
    off = np.arange(-reach, reach + 1)
    d = np.stack(np.meshgrid(off, off, off, indexing="ij"), axis=-1).reshape(-1, 3)
    cand = (c[:, None, :] + d[None, :, :]).reshape(-1, 3)
    cand = cand[(cand >= 0).all(axis=1)]
    return bkey, bstart, np.unique(morton_np(cand[:, 0], cand[:, 1], cand[:, 2]))


@dataclass
class Band:
    """A sparse voxel band around points sorted by cell.

    ``u``: (M, 3) grid coordinates of the points in cell order; ``perm``: their indices in the input;
    ``keys``/``nbr``: the voxels in Morton order and their 6 neighbours; ``cs``: per-voxel point
    ranges (the points whose cell's lower corner is that voxel); ``vcost``: the cost of moving
    through each voxel (inf for corners outside the band, kept only to index cells); ``foot``: the
    nearest point of each voxel; ``near``: per point, which corner of its cell is its nearest
    marchable voxel (x + 2 y + 4 z; 255: none);
    ``radius``: the band radius of every point in grid units (None when it is r / h everywhere);
    ``pieces``: the connected piece of every point and their count
    (:func:`lodbuilder._kernels.topology.point_pieces` of this band), when already known.
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
    near: np.ndarray
    radius: np.ndarray | None = None
    pieces: tuple[np.ndarray, int] | None = None

    @property
    def n_voxels(self) -> int:
        return int(self.keys.shape[0])

    @property
    def coord(self) -> np.ndarray:
        """(V, 3) integer grid coordinates of the voxels (decoded from the keys)."""
        return unmorton_np(self.keys)

    @property
    def marchable(self) -> np.ndarray:
        return np.isfinite(self.vcost)

    @property
    def nbytes(self) -> int:
        arrays = (self.u, self.perm, self.keys, self.nbr, self.cs, self.vcost, self.foot, self.near)
        return sum(a.nbytes for a in arrays)


def build_band(points: np.ndarray, h: float, r: float, max_memory: int | None = None, *,
               radius: np.ndarray | None = None, normal: np.ndarray | None = None,
               separation: np.ndarray | None = None, depth_cost: float | None = None,
               lattice: np.ndarray | None = None) -> Band:
    """Build the band of radius ``r`` (or per-point ``radius``, input order) on a grid of spacing
    ``h`` around ``points``; where ``normal`` (input order, toward the other sheet at distance
    ``separation``) is not zero, only on the side away from it. ``lattice``: a point the grid's
    voxel corners fall on (a part of a larger scan on that scan's grid)."""
    from .._kernels.grid import band_voxels, neighbour_table
    from .._kernels.topology import nearest_corners

    n = points.shape[0]
    max_memory, origin, budget_voxels, (cell_keys, perm, u, ostart) = _cells(points, h, r, max_memory, radius,
                                                                             lattice)
    rad = np.full(n, r / h) if radius is None else np.ascontiguousarray(radius[perm] / h, dtype=np.float64)
    bkey, bstart, cand = block_plan(cell_keys, float(rad.max()))
    keys, q2, foot, count = band_voxels(u, 1.0 / (rad * rad), rad, ostart, bkey, bstart, cand, budget_voxels)
    del bkey, bstart, cand, rad
    if count < 0:
        raise _too_big(h, r, max_memory, budget_voxels, None)
    cs = ostart[np.append(np.searchsorted(cell_keys, keys), cell_keys.shape[0])]  # (ostart[-1] = n)
    del cell_keys, ostart
    nbr = neighbour_table(keys)
    beta = DEPTH_COST if depth_cost is None else depth_cost
    vcost = np.where(q2 <= 1.0, 1.0 + beta * q2, np.inf).astype(np.float32)
    del q2
    near = nearest_corners(u, nbr, cs, vcost)
    band = Band(origin, h, r, u, perm, keys, nbr, cs, vcost, foot, near, None if radius is None else radius / h)
    if normal is not None:
        band.vcost, band.near = one_sided(band, normal, separation, radius, beta)
    return band


def _cells(points: np.ndarray, h: float, r: float, max_memory: int | None, radius: np.ndarray | None,
           lattice: np.ndarray | None) -> tuple[int, np.ndarray, int, tuple[np.ndarray, ...]]:
    """The start of a band: ``max_memory`` (the default when None), the grid's origin, the voxel
    budget and the points sorted into cells (:func:`cells`); refuses a band over the budget."""
    n = points.shape[0]
    if n > MAX_POINTS:
        raise InputError(f"points has {n:,} points; at most {MAX_POINTS:,} can be ordered in one run")
    if max_memory is None:
        max_memory = default_max_memory()
    origin = _grid_origin(points, h, r, radius, lattice)
    budget_voxels = (max_memory - BYTES_PER_POINT * n) // BYTES_PER_VOXEL
    sorted_cells = cells(points, origin, h)
    release_pages(points)  # (a scan set aside: the band reads only u from here on)
    if budget_voxels < sorted_cells[3].shape[0] - 1:
        raise _too_big(h, r, max_memory, budget_voxels, sorted_cells[3].shape[0] - 1)
    return max_memory, origin, budget_voxels, sorted_cells


def band_pieces(points: np.ndarray, h: float, r: float, max_memory: int | None = None, *,
                lattice: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """The band piece of every point (input order) and their count: ``point_pieces`` of
    ``build_band(points, h, r, max_memory, lattice=lattice)`` (the same labels, the same refusals),
    from which voxels are marchable alone (:func:`lodbuilder._kernels.topology.band_marchable`: no
    nearest point of each voxel, the search over a cell's points stopped at the first within r)."""
    from .._kernels.grid import neighbour_table
    from .._kernels.topology import band_marchable, nearest_corners, point_pieces

    n = points.shape[0]
    if n == 0:
        return np.zeros(0, np.int64), 0
    max_memory, _, budget_voxels, (cell_keys, perm, u, ostart) = _cells(points, h, r, max_memory, None, lattice)
    rad = r / h
    bkey, bstart, cand = block_plan(cell_keys, rad)
    keys, march, count = band_marchable(u, 1.0 / (rad * rad), rad, ostart, bkey, bstart, cand, budget_voxels)
    if count < 0:
        raise _too_big(h, r, max_memory, budget_voxels, None)
    cs = ostart[np.append(np.searchsorted(cell_keys, keys), cell_keys.shape[0])]
    nbr = neighbour_table(keys)
    vcost = np.where(march != 0, np.float32(1.0), np.float32(np.inf))
    bpiece, npiece = point_pieces(nbr, cs, nearest_corners(u, nbr, cs, vcost), vcost)
    piece = np.empty(n, np.int64)
    piece[perm] = bpiece  # (band order -> point order)
    return piece, int(npiece)


def _grid_origin(points: np.ndarray, h: float, r: float, radius: np.ndarray | None,
                 lattice: np.ndarray | None = None) -> np.ndarray:
    """The grid's origin, a margin of the largest band radius (+ 3 voxels) below the points (on
    ``lattice`` when given: a whole number of voxels from it); refuses a grid too large to index."""
    rmax = r if radius is None else max(r, float(radius.max()))
    margin = math.ceil(rmax / h) + 3
    origin = axis_min(points) - margin * h
    if lattice is not None:
        origin = lattice + h * np.floor((origin - lattice) / h)
    extent = int(math.ceil(float((axis_max(points) - origin).max()) / h)) + margin
    if extent > MAX_COORD:
        need = h * extent / MAX_COORD
        raise InputError(
            f"voxel_size={h:g} would need {extent:,} voxels along one axis of the bounding box "
            f"(at most {MAX_COORD:,} can be indexed); use a voxel_size of at least {need:.3g}, "
            "or drop points far from the rest (outliers) if they make the box this large"
        )
    return origin


def _too_big(h: float, r: float, max_memory: int, budget_voxels: int, need: int | None) -> MemoryBudgetError:
    """The refusal of a band over the voxel budget (of at least ``need`` voxels when known)."""
    what = "more voxels than" if need is None else f"at least {need:,} voxels, more than"
    mem = f"{max_memory / 2**30:.2f} GiB" if max_memory >= 2**30 else f"{max_memory / 2**20:.3g} MiB"
    return MemoryBudgetError(
        f"voxel_size={h:g} with band_radius={r:g} needs {what} max_memory={mem} allows "
        f"({max(budget_voxels, 0):,}); increase voxel_size or max_memory"
    )


def one_sided(
    band: Band, normal: np.ndarray, separation: np.ndarray | None, radius: np.ndarray | None, beta: float
) -> tuple[np.ndarray, np.ndarray]:
    """The voxel costs and nearest marchable corners of ``band`` with its thin parts one-sided (``normal``,
    ``separation``, ``radius``: per point, input order; see the module docstring): a voxel subset."""
    from .._kernels.grid import one_sided_cost
    from .._kernels.topology import nearest_corners_since

    perm = band.perm
    nin = np.ascontiguousarray(normal[perm], dtype=np.float32)  # (float32 products are exact in float64)
    psep = np.full(perm.shape[0], np.inf) if separation is None else separation[perm] / band.h
    rad = np.full(perm.shape[0], band.r / band.h) if radius is None else radius[perm] / band.h
    inv_r2 = np.divide(1.0, rad * rad, out=rad)  # (in place: one array of N less at the peak of thin scans)
    vcost = one_sided_cost(band.keys, band.foot, band.u, nin, psep, inv_r2, SIDE_TOLERANCE, beta)
    return vcost, nearest_corners_since(band.u, band.nbr, band.cs, vcost, band.vcost, band.near)


def cut_between_sheets(band: Band, vcost: np.ndarray, plan: BandPlan,
                       near: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The voxel costs ``vcost`` of ``band`` cut between the sheets of ``plan`` (see
    :func:`lodbuilder._kernels.sheets.sheet_cut`: no two neighbouring marchable voxels, and no
    point and the voxels it reads, stand on different sheets) and the points' nearest marchable
    corners in the result (``near``: those of ``vcost``, when known: then only the cells whose
    corners the cut changed are looked at again)."""
    from .._kernels.sheets import sheet_cut
    from .._kernels.topology import nearest_corners, nearest_corners_since

    assert plan.normal is not None and plan.separation is not None
    perm = band.perm
    nin = np.ascontiguousarray(plan.normal[perm], dtype=np.float32)
    psep = np.ascontiguousarray(plan.separation[perm] / band.h)
    cut = sheet_cut(band.keys, band.nbr, band.cs, band.foot, vcost, band.u, nin, psep)
    if near is None:
        return cut, nearest_corners(band.u, band.nbr, band.cs, cut)
    return cut, nearest_corners_since(band.u, band.nbr, band.cs, cut, vcost, near)


def build_planned_band(
    points: np.ndarray, plan: BandPlan, max_memory: int | None = None, *, band: Band | None = None
) -> tuple[Band, BandPlan]:
    """The band of a plan: one-sided where sheets come close, and cut between sheets (so a sheet
    between two others is bridged to neither). A one-sided band must not split the surface into
    more pieces than the plain band does: in a stack of sheets joined by folds no choice of sides
    is consistent around every fold, and two registrations of one surface a few spacings apart, in
    a merged scan, are found as two sheets and may be cut apart that way. If the one-sided band
    alone splits it, cutting it between sheets (a subset of its voxels) is not tried, and for a
    stack (at least THIN_SHARE % thin) the plain band cut between sheets is (both sides of every
    sheet, each voxel on its nearest point's sheet); if that splits it too, or the scan is not a
    stack, the plain band is used and the plan returned says so. If only the cut splits it, the
    one-sided band alone is used.
    Every band here is a subset of the plain one's voxels, so all are decided on one band
    (``band``: the plain band, when already built). The band returned keeps the pieces of its
    points (``Band.pieces``: the ordering needs them, and they are known here already)."""
    from .._kernels.topology import point_pieces

    if band is None:
        band = build_band(points, plan.h, plan.r, max_memory)
    if plan.normal is None:
        return band, plan
    side, side_near = one_sided(band, plan.normal, plan.separation, plan.radius, DEPTH_COST)
    found = point_pieces(band.nbr, band.cs, side_near, side)  # (the piece of every point, their count)
    plain_found = point_pieces(band.nbr, band.cs, band.near, band.vcost) if found[1] > 1 else None
    if plain_found is not None and found[1] > plain_found[1]:
        del side, side_near
        return _split_fallback(band, plan, found[1], plain_found)
    vcost, near = cut_between_sheets(band, side, plan, side_near)  # the one-sided band holds: cut it
    cut = point_pieces(band.nbr, band.cs, near, vcost)
    if cut[1] > 1 and plain_found is None:
        plain_found = point_pieces(band.nbr, band.cs, band.near, band.vcost)
    if plain_found is None or cut[1] <= plain_found[1]:
        found = cut
    else:  # the cut is what splits it: the one-sided band alone
        vcost, near = side, side_near
    band.vcost, band.near, band.pieces = vcost, near, found
    return band, plan


def _split_fallback(band: Band, plan: BandPlan, pieces: int, plain_found: tuple[np.ndarray, int]
                    ) -> tuple[Band, BandPlan]:
    """:func:`build_planned_band` where the one-sided band splits the surface into more ``pieces``
    than the plain band's (``plain_found``): for a stack, its cut between sheets if that holds."""
    from .._kernels.topology import point_pieces

    stack = plan.thin_points >= THIN_SHARE / 100 * band.u.shape[0]  # (a few thin parts: as before)
    if not stack:
        log.info("one-sided band split the surface into %d pieces; using the plain band", pieces)
        band.pieces = plain_found
        return band, BandPlan.plain(plan.h, plan.r)
    vcost, near = cut_between_sheets(band, band.vcost, plan, band.near)
    found = point_pieces(band.nbr, band.cs, near, vcost)
    if found[1] > plain_found[1]:
        log.info("the band cut between sheets splits the surface into %d pieces; using the plain band", found[1])
        band.pieces = plain_found
        return band, BandPlan.plain(plan.h, plan.r)
    log.info("one-sided band splits the surface; using the plain band cut between sheets")
    band.vcost, band.near, band.pieces = vcost, near, found
    return band, BandPlan(plan.h, plan.r, None, plan.separation, plan.normal, plan.handover, plan.outer)


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
    band, plan, _ = plan_and_build_band(pts, voxel_size, band_radius)
    h = plan.h
    inv = np.empty(pts.shape[0], dtype=np.int32)
    inv[band.perm] = np.arange(pts.shape[0], dtype=np.int32)
    if plan.normal is None:
        pnrm = np.zeros((1, 3), dtype=np.float32)
    else:
        pnrm = plan.normal[band.perm]
    dq, _, _ = multi_source_distance(
        band.u, band.keys, band.nbr, band.cs, band.near, band.vcost, np.ones(1), False, band.foot,
        pnrm, TAIL_SLOPE, inv[src],
    )
    out = np.empty(pts.shape[0])
    out[band.perm] = dq * h
    return out
