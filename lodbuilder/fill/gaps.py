"""Where a level cannot meet rho: enclosed surface regions far from every input point.

A level at rho covers the *input points* within rho. Where the scanner left a hole wider than rho
(grazing angles, dark or shiny material, occlusion), the *surface* has points farther than rho from
every input point, and no subset of the input can cover them. This module finds those regions.

Inputs are two prefixes of the scan's farthest point ordering: the level ``L`` (prefix at rho) and
a denser *sample* ``S`` (prefix at ``rho / 4``; every input point is within rho/4 of it), or the
whole scan for exact distances.

1. **Seeds** (on the level, a few thousand points for a typical level). Each level point's
   neighbours are projected on its PCA tangent plane and sorted by angle; for each pair of
   angularly consecutive neighbours the circumcentre of the triangle (point, neighbour, next
   neighbour) is a local Voronoi vertex of the level: the locally farthest surface point from it.
   Where the angle between the two neighbours is 180 degrees or more (an open side: the scan's
   border or a large hole) probes along the bisector play that part. A vertex farther than rho
   from the level is moved onto the plane of its nearest sample points (same normal: this takes
   off the surface's curvature) and is a *seed* when it is farther than rho/2 from the sample,
   in 3D and along that plane. Where no seed exists, the level covers the surface within rho (up
   to the tangent-plane approximation).
2. **Groups.** Seeds closer than 2 rho are linked; a group wider than ``2 * max_hole * rho`` (a
   long border) is open and left alone.
3. **Regions** (per group, in the plane of the seeds' level normals; where that leaves it
   open, again in the seeds' own plane when they spread over one that most of the normals
   face within 60 degrees: the rim's normals turn with the surface). The sample points around the
   group, near that plane (``|height| <= rho + |distance in the plane| / 2``, which drops other
   sheets across the plane) are projected on it; a square grid of candidate nodes at spacing
   rho/4 is laid over them, first a little wider than the seeds' spread, then (for groups of
   several seeds whose region reached its edge) ``max_hole * rho`` wide. The nodes farther than
   rho/2 (in the plane) from every projected sample point form regions (4-connected). A region
   that contains a seed and stays inside the grid is **enclosed**: input points bound it all
   round (a region that reaches the edge only through a channel in which no node is farther
   than rho from the input, a seam of sparser points, is cut there; enclosed only so, it is
   kept when it is a fillable gap; and where some of the points face away from the seeds'
   side, normals oriented along the surface: the other face of a thin part, reached round its
   edge, the group is searched first with those set aside, keeping only fillable gaps, then
   as it is). A region that reaches the grid's edge leaks into empty space (the scan's border,
   or a hole wider than ``max_hole * rho``), or through a part of its rim that the cone dropped
   (the rim of a hole on a strongly curved place is steep over any one plane). Such a group is
   searched again **along the surface**: only the sample points on the seeds' own sheet
   (reached from the points next to the seeds within the grid's reach, over links to each
   point's 8 nearest points within 1.5 rho: :func:`~lodbuilder.fill.local.on_sheet`), in a
   cone twice as steep (45 degrees). Another sheet is not on it, so the steep rim can stay;
   a region enclosed there that is a fillable gap (steps 4-5) is kept; a rough one is counted
   apart (``n_bent``: enclosed along the surface, which bends too much across it to fill).
   Anything else stays *open* and is not filled.
4. **Surface.** The ring of sample points within 2 rho of the region fixes the hole's plane (least
   squares; the grid is laid again if it moved, unless more of the ring's normals are tilted
   over 60 degrees from the new plane than from the old; where more than 25 % of the inner
   ring's normals are, the grid is laid again over the plane, within 60 degrees, from which
   the fewest are: the lopsided rim of a hole beside a corner, a nose or a chin is a height
   field over that plane and not over its least-squares one) and a height field over it
   (:class:`~lodbuilder.fill.surface.HeightField`, fitted without the ring points facing away:
   :func:`~lodbuilder.fill.local.same_face`; for a gap, the spline that cross-validates best
   on the ring). The region is *rough* (reported, not filled) when the ring is not a height
   field (more than 25 % of the normals of its inner part, the points within rho of the region,
   tilted over 60 degrees from the plane's normal: the outer ring of a hole on a tube or a
   small sphere turns farther, and is not what the fill bridges) or not one smooth piece:
   fitted to five sixths of the ring (angular sectors around the hole), the surface misses the
   inner ring points (within rho of the region) of the sixth left out by more than rho/2 RMS
   (e.g. an occlusion shadow, whose rim lies on two surfaces at different depths). A ring
   missed by rho/2 to 0.8 rho (carved detail, as on Igea) is still filled where the surface
   stays within the inner ring's heights (it interpolates them, never climbing a bump's flank
   beyond them) and the ring is one layer (not a plate over a sheet: :func:`_interpolates`).
5. **Candidates** are the region's nodes lifted onto the height field; those within rho/2 of a
   sample point in 3D (another sheet) are dropped. The region's *gap* is the part of it farther
   than rho from every sample point: its area (node count x node area x the height field's
   slope factor), bounding box and largest distance are reported. Only regions with a gap are
   assessed (step 4) and filled; smaller ones (farther than rho/2 but not rho from the input:
   a real scan's sparse spots) are kept in the search's list, never filled.
6. **No height field.** A group left without a fillable gap but open, bent or rough over every
   plane (or with seeds left open beside a fillable gap) is searched once more on an implicit
   surface fitted round its seeds (:mod:`lodbuilder.fill.implicit`, :mod:`~lodbuilder.fill.folded`):
   a region enclosed on that surface whose fit predicts its surroundings (within rho/4 RMS, and
   fixed by them: gradient at least 0.6 over it) is a fillable gap; it replaces the group's rough
   gaps it covers. Nothing else is taken from it (a rough cap there is no gap: an open tube's
   end is capped the same way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..features.neighbours import Neighbourhoods, local_pca
from .folded import implicit_regions
from .local import (
    FACING,
    K_SAMPLE,
    NEAR_FRACTION,
    Grid,
    facing,
    flood,
    group_normal,
    groups,
    inside,
    near_plane,
    normals_at,
    on_sheet,
    same_face,
    stacked,
    two_layers,
)
from .region import STATUS_FILLABLE, STATUS_ROUGH, Region
from .surface import (
    MAX_TILT,
    MAX_TILTED,
    Frame,
    HeightField,
    height_field_normal,
    plane_normal,
    tangents,
    tilted_share,
)

#: the sample is the prefix at SAMPLE_FRACTION * rho
SAMPLE_FRACTION = 0.25
#: candidate grid spacing, in units of rho
GRID_FRACTION = 0.25
#: default widest hole filled, in units of rho
MAX_HOLE = 12.0
#: ring width around a region (for the surface fit), in units of rho
RING = 2.0
#: the ring's inner part (whose prediction judges the fit), in units of rho
INNER = 1.0
#: neighbours of a level point in the seed search
K_LEVEL = 10
#: the cone around the hole's plane that keeps input points, over the plane and over the sheet
SLOPE, SHEET_SLOPE = 0.5, 1.0
#: a group of fewer seeds is a small hole: its first grid (the seeds' spread + 1.5 rho) is final
MIN_SEEDS_WIDE = 4
#: largest RMS error predicting a sixth of the ring from the rest, in units of rho
MAX_RESIDUAL = 0.5
#: a rougher ring (up to MAX_ROUGH rho) is bridged where the surface leaves the inner ring's
#: heights by at most MAX_OVERSHOOT rho
MAX_ROUGH, MAX_OVERSHOOT = 0.8, 0.1


@dataclass
class Search:
    """What :func:`find_regions` found: the regions and how many seed groups were open."""

    rho: float
    max_hole: float
    regions: list[Region] = field(default_factory=list)
    n_open: int = 0
    n_seeds: int = 0
    #: groups open over the plane whose gap is enclosed along the surface but rough there
    n_bent: int = 0
    #: the rough gaps searched for fillable ones only and left out (not in ``regions``)
    refused: list[Region] = field(default_factory=list)


def _level_vertices(level: np.ndarray, tree_l: Any, rho: float) -> tuple[np.ndarray, np.ndarray]:
    """Local Voronoi vertices of the level farther than rho from their three points (and probes
    on open sides), on each level point's tangent plane; with the level normal at each."""
    n = level.shape[0]
    k = min(K_LEVEL, n - 1)
    _, nb = tree_l.query(level, k=k + 1, workers=-1)
    nb = np.asarray(nb, dtype=np.int64)
    _, normals, _ = local_pca(level, Neighbourhoods(n, knn=nb))
    t1, t2 = tangents(normals)
    off = level[nb[:, 1:]] - level[:, None, :]
    x = np.einsum("nki,ni->nk", off, t1)
    y = np.einsum("nki,ni->nk", off, t2)
    ang = np.arctan2(y, x)
    order = np.argsort(ang, axis=1)
    x = np.take_along_axis(x, order, 1)
    y = np.take_along_axis(y, order, 1)
    ang = np.take_along_axis(ang, order, 1)
    x2, y2 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    dang = np.roll(ang, -1, axis=1) - ang
    dang[:, -1] += 2 * np.pi
    # circumcentre (ux, uy) of the triangle (0, 0), (x, y), (x2, y2)
    d = 2.0 * (x * y2 - y * x2)
    a, b = x * x + y * y, x2 * x2 + y2 * y2
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (y2 * a - y * b) / d
        uy = (x * b - x2 * a) / d
    r = np.hypot(ux, uy)
    cap = 3.0 * rho
    open_side = dang >= np.pi - 1e-6
    vertex = ~open_side & np.isfinite(r) & (r > rho) & (r <= cap)
    # most such triangles are not Delaunay: another neighbour lies within rho of the vertex
    rows = np.flatnonzero(vertex.any(axis=1))
    vx, vy = ux[rows], uy[rows]
    d2 = (vx[:, :, None] - x[rows, None, :]) ** 2 + (vy[:, :, None] - y[rows, None, :]) ** 2
    vertex[rows] &= d2.min(axis=2) > rho * rho
    # (a far vertex of a wide angle: a big hole's rim; of a narrow one: a skinny triangle)
    probe = open_side | ((dang > 0.5 * np.pi) & ~(np.isfinite(r) & (r <= cap)))
    rv, cv = np.nonzero(vertex)
    pts = [level[rv] + ux[rv, cv, None] * t1[rv] + uy[rv, cv, None] * t2[rv]]
    src = [rv]
    # beyond an open side, or where the vertex is far away: probes along the bisector
    rp, cp = np.nonzero(probe)
    mid = ang[rp, cp] + 0.5 * dang[rp, cp]
    direction = np.cos(mid)[:, None] * t1[rp] + np.sin(mid)[:, None] * t2[rp]
    for dist in (1.5 * rho, cap):
        pts.append(level[rp] + dist * direction)
        src.append(rp)
    source = np.concatenate(src)
    return np.concatenate(pts), normals[source]


def _seeds(
    level: np.ndarray, tree_l: Any, tree_s: Any, rho: float
) -> tuple[np.ndarray, np.ndarray]:
    """Seeds (S, 3): level vertices farther than rho from the level and farther than rho/2
    from the sample; and the level normal at each (S, 3)."""
    empty = np.zeros((0, 3))
    if level.shape[0] < 4:
        return empty, empty
    cand, nrm = _level_vertices(level, tree_l, rho)
    d_l, _ = tree_l.query(cand, k=1, workers=-1)
    cand, nrm = cand[d_l > rho], nrm[d_l > rho]
    # a vertex within rho/2 of a sample point is no seed: that point, its nearest, is within
    # rho/2 of it along its tangent plane too (the test below). Most stop here, before 16-NN.
    d_0, _ = tree_s.query(cand, k=1, distance_upper_bound=rho, workers=-1)
    keep = ~(d_0 <= NEAR_FRACTION * rho)
    cand, nrm = cand[keep], nrm[keep]
    if cand.shape[0] == 0:
        return empty, empty
    # a vertex lies on its level point's tangent plane: move it onto the plane of the sample
    # points around it (same normal), which takes off most of the surface's curvature
    k = min(2 * K_SAMPLE, tree_s.n)
    _, nn = tree_s.query(cand, k=k, workers=-1)
    near = tree_s.data[np.asarray(nn).reshape(cand.shape[0], k)]
    cand = cand - np.einsum("ni,ni->n", cand - near[:, :K_SAMPLE].mean(axis=1), nrm)[:, None] * nrm
    # nothing of the sample within rho/2, in 3D nor along the tangent plane (a vertex off a
    # curved surface can be far from the sample in 3D but not along the surface)
    off = near - cand[:, None, :]
    along = off - np.einsum("nki,ni->nk", off, nrm)[:, :, None] * nrm[:, None, :]
    lim = (NEAR_FRACTION * rho) ** 2
    far = (np.einsum("nki,nki->nk", along, along) > lim).all(axis=1)
    d_s, _ = tree_s.query(cand, k=1, workers=-1)
    far &= d_s > NEAR_FRACTION * rho
    return cand[far], nrm[far]


def find_regions(
    level: np.ndarray,
    sample: np.ndarray,
    rho: float,
    *,
    max_hole: float = MAX_HOLE,
    tree_l: Any = None,
    tree_s: Any = None,
) -> Search:
    """Enclosed regions of the surface farther than rho/2 from every point of ``sample``, where
    the ``level`` (a subset of the sample covering it within rho) cannot meet rho.

    Args:
        level: (K, 3) points of the level at rho.
        sample: (M, 3) input points (the whole scan, or a prefix of its ordering covering it
            within rho/4).
        rho: the density.
        max_hole: widest region examined, in units of rho.
        tree_l, tree_s: optional prebuilt ``cKDTree`` of ``level`` and ``sample``.
    """
    from scipy.spatial import cKDTree

    rho = float(rho)
    out = Search(rho=rho, max_hole=float(max_hole))
    if level.shape[0] < 4 or sample.shape[0] < 4:
        return out
    tree_l = cKDTree(level, balanced_tree=False) if tree_l is None else tree_l
    tree_s = cKDTree(sample, balanced_tree=False) if tree_s is None else tree_s
    seeds, seed_normals = _seeds(level, tree_l, tree_s, rho)
    out.n_seeds = int(seeds.shape[0])
    width = max_hole * rho
    for grp in groups(seeds, rho):
        sp = seeds[grp]
        if float(np.linalg.norm(np.ptp(sp, axis=0))) > 2.0 * width:  # a long border
            out.n_open += 1
            continue
        new = ~_inside(out.regions, sp, rho)  # seeds of a region already found are done
        grp, sp = grp[new], sp[new]
        if grp.size == 0:
            continue
        summed, flat = group_normal(sp, seed_normals[grp], rho, MIN_SEEDS_WIDE)
        before = (len(out.regions), out.n_open, out.n_bent)
        _search_group(out, sample, tree_s, sp, summed, width)
        now = (len(out.regions), out.n_open, out.n_bent)
        if flat is not None and now[0] == before[0] and now != before:
            # open or bent over the plane of the level normals: again over the seeds' plane
            out.n_open, out.n_bent = before[1:]
            _search_group(out, sample, tree_s, sp, flat, width)
        _search_folded(out, sample, tree_s, sp, summed, width, before)
    for i, reg in enumerate(r for r in out.regions if r.is_gap):
        reg.id = i
    return out


def _search_folded(out: Search, sample, tree_s, sp, normal, width, before) -> None:
    """Where the search over a plane left the group ``sp`` without a fillable gap but open,
    bent or rough (its surroundings no height field), or left some of its seeds open beside a
    fillable gap: search them again on an implicit surface
    (:func:`~lodbuilder.fill.folded.implicit_regions`). A fillable gap found there replaces the
    group's rough gaps it covers, or counts off one open or bent group."""
    new = out.regions[before[0] :]
    rough = [r for r in new if r.is_gap and r.status == STATUS_ROUGH]
    opened = out.n_open - before[1] + out.n_bent - before[2]
    if not (rough or opened):
        return
    if any(r.is_gap and r.status == STATUS_FILLABLE for r in new):
        if not opened:
            return
        sp = sp[~_inside(new, sp, out.rho)]  # the seeds left open beside a fillable gap
        if sp.shape[0] == 0:
            return
    rho = out.rho
    found, _ = implicit_regions(sample, tree_s, sp, normal, rho, width, GRID_FRACTION * rho)
    # (a rough one is not reported: an open tube's end is a closed loop of border too, which
    # the implicit surface caps, and the fit's checks refuse)
    found = [r for r in found if r.is_gap and r.status == STATUS_FILLABLE]
    found = [r for r in found if not _inside(out.regions[: before[0]], r.candidates[:1], rho)[0]]
    for reg in found:
        drop = [
            r for r in rough if _inside([reg], r.candidates.mean(axis=0, keepdims=True), rho)[0]
        ]
        out.regions = [r for r in out.regions if not any(r is x for x in drop)]
        rough = [r for r in rough if not any(r is x for x in drop)]
        if not drop and out.n_bent > before[2]:
            out.n_bent -= 1
        elif not drop and out.n_open > before[1]:
            out.n_open -= 1
        out.regions.append(reg)


def _search_group(out: Search, sample, tree_s, sp, normal, width) -> None:
    """Find the regions of one group of seeds ``sp`` (step 3) and add them to ``out``."""
    rho = out.rho
    away: list = []
    regions = _regions_of_group(sample, tree_s, sp, normal, rho, width, False, away)
    kept = 0
    if away:  # with the other faces of thin parts set aside: only fillable gaps, then without
        kept = _add(out, regions, tree_s, rho, fillable_only=True)[0]
        regions = _regions_of_group(sample, tree_s, sp, normal, rho, width, False)
    n_open = max(0, sum(r is None for r in regions) - kept)
    enclosed = [r for r in regions if r is not None]
    n_open += _add(out, enclosed, tree_s, rho, fillable_only=False)[2]
    enclosed = [r for r in enclosed if not r.opened or any(r is x for x in out.regions)]
    rest = sp[~_inside(enclosed, sp, rho)] if enclosed and n_open else sp
    if n_open and float(np.linalg.norm(np.ptp(rest, axis=0))) <= width:
        # open over the plane, and its seeds fit in one hole: look again over the seeds' sheet
        # only (along the surface); a fillable gap found there is kept, anything else stays open
        again = _regions_of_group(sample, tree_s, rest, normal, rho, width, True)
        added, refused, _ = _add(out, again, tree_s, rho, fillable_only=True)
        out.n_bent += min(n_open, refused)
        n_open -= min(n_open, added + refused)
    out.n_open += n_open


def _add(
    out: Search, regions: list, tree_s: Any, rho: float, fillable_only: bool
) -> tuple[int, int, int]:
    """Finish the enclosed ``regions`` not found already and add them to ``out`` (with
    ``fillable_only``, and for an opened region, only the fillable gaps): (how many were added,
    how many gaps were left out as rough, how many opened regions were left out)."""
    added = refused = dropped = 0
    for reg in regions:
        if reg is None or _inside(out.regions, reg.candidates.mean(axis=0, keepdims=True), rho)[0]:
            continue  # open, or found already
        _finish_region(reg, tree_s, rho)
        if not reg.candidates.shape[0]:
            continue
        if (fillable_only or reg.opened) and not (reg.is_gap and reg.status == STATUS_FILLABLE):
            refused += reg.is_gap if fillable_only else 0
            if reg.is_gap and fillable_only:
                out.refused.append(reg)
            dropped += reg.opened and not fillable_only
            continue
        reg.id = sum(r.is_gap for r in out.regions) if reg.is_gap else -1
        out.regions.append(reg)
        added += 1
    return added, refused, dropped


def _inside(regions: list[Region], points: np.ndarray, rho: float) -> np.ndarray:
    return inside(regions, points, rho, GRID_FRACTION * rho)


def _regions_of_group(sample, tree_s, seeds, normal, rho, width, along=False, away=None) -> list:
    """Regions around one group of seeds (``None`` for each open one): a grid a little wider
    than the seeds' spread first, then (when a region reaches its edge) ``width`` across, then
    once more centred on the region that reached the edge (the seeds' mean can sit off a
    hole's centre). An enclosed region found on one grid is kept; the next grid looks only for
    the regions of the seeds outside it (a group can hold a hole and a border next to it).
    ``along``: only the points on the seeds' sheet, in the steeper cone (step 3). ``away``: a
    list; the points facing away from the hole's side are set aside on every grid (the other
    face of a thin part), and True appended to it where some were."""
    from scipy.spatial import cKDTree

    g = GRID_FRACTION * rho
    centre = seeds.mean(axis=0)
    spread = float(np.sqrt(((seeds - centre) ** 2).sum(axis=1).max()))
    first = max(2.0 * rho, spread + 1.5 * rho)
    steps = [first] if first < 0.5 * width else []
    if not steps or seeds.shape[0] >= MIN_SEEDS_WIDE:
        steps += [0.5 * width, 0.5 * width]
    frame = Frame.of(centre, normal)
    found: list = []  # enclosed regions of the grids laid so far
    regions: list = []
    for i, half_width in enumerate(steps):
        half = int(math.ceil(half_width / g))
        idx = tree_s.query_ball_point(frame.origin, math.sqrt(2.0) * half * g + RING * rho)
        idx = np.asarray(idx, dtype=np.int64)
        if along and idx.size >= 8:
            idx = idx[on_sheet(sample[idx], seeds, rho, math.sqrt(2.0) * half * g + RING * rho)]
        slope = SHEET_SLOPE if along else SLOPE
        idx = idx[near_plane(sample[idx], frame, rho, slope)]
        if idx.size < 8:
            return found
        tree2 = cKDTree(frame.uv(sample[idx]))
        if i == 0:  # quick exit: every seed is near a sample point in the plane
            d, _ = tree2.query(frame.uv(seeds), k=1, distance_upper_bound=NEAR_FRACTION * rho)
            if np.isfinite(d).all():
                return []
        local = _Local(sample, idx, tree2, slope, away)
        regions, leak_at = _regions_on_grid(frame, local, seeds, rho, g, half, refit=2)
        enclosed = [r for r in regions if r is not None]
        for r in enclosed:
            r.along = along
        found += enclosed
        if leak_at is None:
            return found
        if enclosed:  # the next grid: only the seeds of the regions that reached the edge
            seeds = seeds[~_inside(enclosed, seeds, rho)]
            if seeds.shape[0] == 0:
                return found
        if half_width >= 0.5 * width:  # the last try: the widest grid, centred on the leak
            frame = Frame.of(leak_at, normal)
    return found + [r for r in regions if r is None]


@dataclass
class _Local:
    """The sample points around a group (``idx`` into ``sample``), projected on a plane."""

    sample: np.ndarray
    idx: np.ndarray
    tree2: Any
    slope: float
    away: list | None = None

    @property
    def points(self) -> np.ndarray:
        return self.sample[self.idx]


def _regions_on_grid(frame, local: _Local, seeds, rho, g, half, refit: int):
    """(regions, where): the regions of the seeds on a grid laid in ``frame`` (``None`` for one
    reaching the grid's edge), and the centre of the nodes of those that did (None if none).
    The grid is laid again, at most ``refit`` times, where a region's ring asks for another
    plane (:func:`~lodbuilder.fill.surface.height_field_normal`)."""
    from scipy.spatial import cKDTree

    if (
        local.away is not None
        and local.idx.size > K_SAMPLE
        and stacked(local.tree2, frame.height(local.points), rho)
    ):
        off = facing(local.points, frame.normal, seeds, rho, local.points) <= FACING
        if off.any():
            local.away.append(True)
            idx = local.idx[~off]
            local = _Local(local.sample, idx, cKDTree(frame.uv(local.sample[idx])), local.slope)
    grid = Grid(frame, g, half)
    found = flood(grid, local.tree2, frame.uv(seeds), rho)
    regions: list = []
    leaked: list[np.ndarray] = []
    pts = local.points
    for nodes, leak, opened in found:
        if leak:
            leaked.append(grid.uv[nodes])
            regions.append(None)
            continue
        uv = grid.uv[nodes]
        d, _ = cKDTree(uv).query(local.tree2.data, k=1, distance_upper_bound=RING * rho)
        ring = np.isfinite(d)
        if ring.sum() < 12:
            continue
        normals = normals_at(pts[ring], pts)
        inner = d[ring] <= INNER * rho
        n_new, again = height_field_normal(
            normals[inner], plane_normal(pts[ring], frame.normal), frame.normal
        )
        if refit > 0 and again:
            # the hole's plane moved: lay the grid again in the plane of this ring
            frame2 = Frame.of(pts[ring].mean(axis=0), n_new)
            idx = local.idx[near_plane(pts, frame2, rho, local.slope)]
            tree2 = cKDTree(frame2.uv(local.sample[idx]))
            local2 = _Local(local.sample, idx, tree2, local.slope, local.away)
            return _regions_on_grid(frame2, local2, seeds, rho, g, half, refit - 1)
        ring[ring] = face = same_face(ring, pts, frame, seeds, rho)[ring]
        reg = _fit_region(
            frame, grid, nodes, local.idx[ring], pts[ring], normals[face], inner[face], rho
        )
        reg.opened = opened
        regions.append(reg)
    if not leaked:
        return regions, None
    uv = np.concatenate(leaked).mean(axis=0, keepdims=True)
    return regions, frame.lift(uv, np.zeros(1))[0]


def _fit_region(frame, grid, nodes, ring_idx, ring, ring_normals, inner, rho) -> Region:
    surface = HeightField(frame.uv(ring), frame.height(ring), rho, inner)
    uv, g = grid.uv[nodes], grid.g
    h = surface(uv)
    factor = grid.area_factor(nodes, h)
    return Region(
        id=-1,
        status=STATUS_FILLABLE,
        candidates=frame.lift(uv, h),
        distance=np.zeros(uv.shape[0]),
        rho=rho,
        area=0.0,
        region_area=0.0,
        node_area=g * g * factor,
        residual=float("nan"),
        frame=frame,
        uv=uv,
        surface=surface,
        ring=ring_idx,
        tilted=tilted_share(ring_normals[inner], frame.normal),
    )


def _assess(reg: Region) -> None:
    """Fillable or rough: is the ring one smooth height field over the hole's plane?"""
    rho = reg.rho
    assert isinstance(reg.surface, HeightField)  # (implicit regions are assessed in folded.py)
    reg.residual = reg.surface.cv
    if reg.tilted > MAX_TILTED:
        reg.status = STATUS_ROUGH
        reg.reason = (
            f"{100 * reg.tilted:.0f} % of the input points next to the hole have normals tilted "
            f"more than {math.degrees(MAX_TILT):.0f} degrees from the hole's plane (more than "
            f"{100 * MAX_TILTED:.0f} %)"
        )
    elif reg.residual > MAX_RESIDUAL * rho and not _interpolates(reg):
        reg.status = STATUS_ROUGH
        reg.reason = (
            f"the surface fitted to the surrounding points misses those next to the hole, when "
            f"fitted without them, by {reg.residual / rho:.2f} rho (RMS; more than "
            f"{MAX_RESIDUAL:g} rho)"
        )


def _interpolates(reg: Region) -> bool:
    """A ring rough at its own scale (residual up to :data:`MAX_ROUGH` rho: carved detail)
    is still bridged where the surface stays within the heights of the points next to the
    hole: the fill interpolates them. A surface that rises above or dips below all of them
    extrapolates a peak or a dip the ring does not show (a bump's flank in the ring). Not
    where the ring lies in two layers over the plane (a plate over the sheet: its heights span
    both depths, and a fill between them is no surface), nor along the surface (the ring's
    heights over the plane bound nothing there)."""
    surface = reg.surface
    assert isinstance(surface, HeightField)
    if reg.along or reg.residual > MAX_ROUGH * reg.rho:
        return False
    if surface.overshoot(reg.frame.height(reg.candidates)) > MAX_OVERSHOOT * reg.rho:
        return False
    ring = reg.frame.lift(surface.ring_uv, surface.ring_h)
    return not two_layers(ring, reg.frame.normal, reg.rho)


def _finish_region(reg: Region, tree_s: Any, rho: float) -> None:
    """3D distances to the sample; drop candidates within rho/2 of it (another sheet). A gap's
    surface is the spline its ring chooses by cross-validation (``HeightField.select``); its
    candidates are lifted again onto it (their area weights stay those of the first fit)."""
    assert isinstance(reg.surface, HeightField)
    d, _ = tree_s.query(reg.candidates, k=1)
    if (d > rho).any() and reg.surface.select():
        reg.candidates = reg.frame.lift(reg.uv, reg.surface(reg.uv))
        d, _ = tree_s.query(reg.candidates, k=1)
    keep = d > NEAR_FRACTION * rho
    reg.candidates = reg.candidates[keep]
    reg.uv = reg.uv[keep]
    reg.distance = np.asarray(d)[keep]
    reg.node_area = reg.node_area[keep]
    reg.region_area = float(reg.node_area.sum())
    reg.area = float(reg.node_area[reg.distance > rho].sum())
    if reg.is_gap:
        _assess(reg)
