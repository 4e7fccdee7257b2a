"""Regions of a group of seeds on an implicit surface fitted round them (see
:mod:`lodbuilder.fill.implicit`): the search for holes whose surroundings are no height field
over any plane, which :mod:`lodbuilder.fill.gaps` runs where its search over a plane left a
group open, bent or rough."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .implicit import ImplicitSurface, cell_area, sector_error, zero_set_cells
from .local import NEAR_FRACTION, normals_at, oriented_normals
from .region import STATUS_FILLABLE, STATUS_ROUGH, Region
from .surface import Frame, plane_normal, tilted_share

#: the grid's ball reaches this far beyond the seeds' spread, and the fit this far beyond it (rho)
BALL_MARGIN, FIT_MARGIN = 2.5, 1.0
#: the ring (for the fit's check and the attributes) and its inner part, in rho
RING, INNER = 2.0, 1.0
#: largest RMS distance of the inner ring's points of each sixth of the ring to the surface
#: fitted to the rest, in rho: the accuracy asked of synthetic points (a distance to the surface,
#: not a height over a plane as :data:`~lodbuilder.fill.gaps.MAX_RESIDUAL`)
MAX_RESIDUAL = 0.25
#: smallest gradient of the fit over a gap: where ``|grad f|`` falls below it, ``f`` is no
#: distance and the surface there is not fixed by the surroundings (on thin plates, a hole
#: wider than about 1.6 x the half thickness through the rounded edge: its zero set cut across
#: the plate 0.4-1.2 rho off, at gradients 0.33-0.53; where it lay within 0.07 rho, and round
#: the bunny's ears, 0.62-0.92)
MIN_GRADIENT = 0.6
#: the implicit surface is tried only where more than this share of the input round the seeds
#: has normals tilted over 60 degrees from the seeds' (a fold, a steep or curled rim: no height
#: field); a flat sheet's border is left to the plane search
FOLDED = 0.1
#: input points of a fit (the first of the sample's farthest point order: evenly spread)
FIT_POINTS = 300


def implicit_regions(
    sample: np.ndarray,
    tree_s: Any,
    seeds: np.ndarray,
    normal: np.ndarray,
    rho: float,
    width: float,
    grid: float,
) -> tuple[list[Region], int]:
    """(the enclosed regions of the ``seeds`` on an implicit surface fitted to the ``sample``
    points round them, how many of the seeds' regions reach empty space). ``sample`` is a prefix
    of a farthest point order (its first points spread evenly); ``normal`` orients the fit;
    ``width`` is the widest hole; ``grid`` the spacing of the cells."""
    from scipy import ndimage

    centre = seeds.mean(axis=0)
    spread = float(np.sqrt(((seeds - centre) ** 2).sum(axis=1).max()))
    if spread > 0.5 * width:
        return [], 1
    ball = spread + BALL_MARGIN * rho
    idx = np.sort(np.asarray(tree_s.query_ball_point(centre, ball + FIT_MARGIN * rho), np.int64))
    if idx.size < 12:
        return [], 1
    near = sample[idx]
    if tilted_share(normals_at(near, near), normal / np.linalg.norm(normal)) <= FOLDED:
        return [], 1  # one height field all round (a border of a flat sheet): seen right already
    nrm = oriented_normals(near, normal, seeds, rho, near)
    surface = ImplicitSurface(near[:FIT_POINTS], nrm[:FIT_POINTS], rho)
    ijk, pts, shell, shape = zero_set_cells(surface, centre, ball, grid, project=False)
    # a cell's point moves less than the cell's diagonal onto the zero set: only the points
    # that may then lie farther than rho/2 from the sample are moved (the others are never used)
    d, _ = tree_s.query(pts, k=1)
    move = d > NEAR_FRACTION * rho - math.sqrt(3.0) * grid
    pts[move] = surface.project(pts[move])
    d[move] = tree_s.query(pts[move], k=1)[0]
    far = move & (d > NEAR_FRACTION * rho)
    if not far.any():
        return [], 0
    box = np.zeros(shape, dtype=bool)
    box[tuple(ijk[far].T)] = True
    labels, _ = ndimage.label(box, structure=np.ones((3, 3, 3)))
    lab = np.zeros(pts.shape[0], dtype=np.int64)
    lab[far] = labels[tuple(ijk[far].T)]
    on = surface.project(seeds)
    from scipy.spatial import cKDTree

    dd, nn = cKDTree(pts[far]).query(on, k=1, distance_upper_bound=rho)
    hit = np.unique(lab[far][nn[np.isfinite(dd)]])
    regions, n_open = [], 0
    for label in hit:
        cells = np.flatnonzero(lab == label)
        if shell[cells].any() or np.linalg.norm(np.ptp(pts[cells], axis=0)) > width:
            n_open += 1
            continue
        regions.append(_region(surface, pts[cells], d[cells], near, nrm, idx, normal, rho, grid))
    return regions, n_open


def _region(surface, cand, dist, near, near_nrm, near_idx, normal, rho, grid) -> Region:
    """The region of the candidates ``cand`` (distances ``dist`` to the sample) on ``surface``,
    fitted to the first points of ``near`` (sample indices ``near_idx``), assessed when it is a
    gap: fitted without each sixth of the ring in turn, how far the surface misses every point
    of that sixth next to the hole."""
    from scipy.spatial import cKDTree

    d_ring, _ = cKDTree(cand).query(near, k=1)
    ring = d_ring <= RING * rho
    area = cell_area(surface.normals(cand), grid)
    frame = Frame.of(near[ring].mean(axis=0), plane_normal(near[ring], normal))
    reg = Region(
        id=-1,
        status=STATUS_FILLABLE,
        candidates=cand,
        distance=dist,
        rho=rho,
        area=float(area[dist > rho].sum()),
        region_area=float(area.sum()),
        node_area=area,
        residual=float("nan"),
        frame=frame,
        uv=frame.uv(cand),
        surface=surface,
        ring=near_idx[ring],
    )
    if reg.is_gap:
        axes = np.stack([frame.t1, frame.t2])
        fit, fit_nrm = near[:FIT_POINTS], near_nrm[:FIT_POINTS]
        test = near[d_ring <= INNER * rho]
        reg.residual = sector_error(fit, fit_nrm, test, axes, rho, cand.mean(axis=0))
        slope = float(np.linalg.norm(surface.gradient(cand), axis=1).min())
        if slope < MIN_GRADIENT:
            reg.status = STATUS_ROUGH
            reg.reason = (
                f"the implicit surface fitted to the surrounding points is not fixed by them "
                f"across the hole (its gradient falls to {slope:.2f}, under {MIN_GRADIENT:g}): "
                "the surface there is not known"
            )
        elif not reg.residual <= MAX_RESIDUAL * rho:
            reg.status = STATUS_ROUGH
            reg.reason = (
                f"the implicit surface fitted to the surrounding points misses those next to the "
                f"hole, when fitted without them, by {reg.residual / rho:.2f} rho (RMS; more than "
                f"{MAX_RESIDUAL:g} rho)"
            )
    return reg
