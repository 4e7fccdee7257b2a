"""Levels that meet rho over the surface, not only over the input points (issue 14).

A level at rho covers every *input point* within rho. Where the scanner left holes wider than rho,
the surface there is farther than rho from every input point, and no level made of input points
can cover it. :func:`find_gaps` finds those regions; :func:`fill_level` adds *synthetic* points on
a surface fitted across them until every point of each region is within rho of the level.

The flow is level -> gaps -> fill, through the public archive API only (two prefixes of the stored
ordering: the level at rho and a sample at rho/4), computed on the fly: nothing is stored.

What is filled: regions farther than rho/2 from every input point, bounded by input points all
round (over the plane of the surrounding surface, or, where the surface curves away from that
plane, by the points of their own sheet, reached along the surface), at most ``max_hole * rho``
wide, whose surroundings are one smooth height field; where no height field fits them (the rim of
a thin part's edge, an ear, folds over every plane; a steep trough), holes enclosed on an implicit
surface fitted round them that predicts its surroundings within rho/4
(:mod:`lodbuilder.fill.implicit`). What is not: open borders (the scan's edge, a hole
reaching it), holes wider than ``max_hole * rho``, and *rough* holes (surroundings tilted or not
one smooth surface, e.g. occlusion shadows whose rim lies at two depths): these are reported, not
filled. See :mod:`lodbuilder.fill.gaps` for the method.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validate import check_positive, strict_keywords, strict_methods
from ..errors import InputError
from .gaps import (
    GRID_FRACTION,
    MAX_HOLE,
    SAMPLE_FRACTION,
    STATUS_FILLABLE,
    STATUS_ROUGH,
    Region,
    find_regions,
)
from .insert import farthest_insert, region_attributes, stop_distance

__all__ = [
    "GapReport",
    "Filled",
    "Region",
    "find_gaps",
    "fill_level",
    "gaps_of_points",
    "archive_gaps",
    "near_gaps",
    "MAX_HOLE",
    "SAMPLE_FRACTION",
    "SYNTHETIC",
]

#: the attribute that flags synthetic points (1) among measured ones (0)
SYNTHETIC = "synthetic"


@strict_methods
@dataclass
class GapReport:
    """The undersampled regions of a scan at one rho.

    Attributes:
        scan: the scan's name.
        rho: the density asked for.
        max_hole: widest region examined, in units of rho.
        regions: the enclosed regions farther than rho/2 from every input point (a region is a
            *gap* when part of it is farther than rho: ``region.is_gap``).
        n_open: groups of far surface that reach into empty space (open borders, or holes wider
            than ``max_hole * rho``): not filled.
        n_bent: groups open over the hole's plane whose gap is enclosed along the surface, but
            rough there (the surface bends too much across it to fill): not filled.
        sample_size: input points the search used (a prefix covering the scan within
            ``sample_rho``; the whole scan when ``sample_rho`` is 0).
        sample_rho: covering radius of that sample over the scan.
        level_size: points of the level at rho.
        seconds: time spent.
    """

    scan: str
    rho: float
    max_hole: float
    regions: list[Region] = field(default_factory=list)
    n_open: int = 0
    n_bent: int = 0
    sample_size: int = 0
    sample_rho: float = 0.0
    level_size: int = 0
    seconds: float = 0.0

    @property
    def gaps(self) -> list[Region]:
        """Regions part of which is farther than rho from every input point."""
        return [r for r in self.regions if r.is_gap]

    @property
    def area(self) -> float:
        return float(sum(r.area for r in self.gaps))

    def as_dict(self) -> dict[str, Any]:
        return {
            "scan": self.scan,
            "rho": self.rho,
            "max_hole": self.max_hole,
            "n_gaps": len(self.gaps),
            "area": self.area,
            "n_fillable": sum(r.status == STATUS_FILLABLE for r in self.gaps),
            "n_rough": sum(r.status == STATUS_ROUGH for r in self.gaps),
            "n_open": self.n_open,
            "n_bent": self.n_bent,
            "n_regions": len(self.regions),
            "sample_size": self.sample_size,
            "sample_rho": self.sample_rho,
            "level_size": self.level_size,
            "seconds": self.seconds,
            "gaps": [r.as_dict() for r in self.gaps],
        }

    def table(self) -> str:
        """The report as text: one line per gap."""
        g = self.gaps
        lines = [
            f"scan {self.scan!r}: {len(g)} gap(s) at rho {self.rho:.6g} (surface farther than rho "
            f"from every input point, enclosed, at most {self.max_hole:g} rho wide), area "
            f"{self.area:.4g}"
        ]
        if g:
            lines.append(
                f"{'id':>4} {'area':>10} {'max dist':>10} {'status':>9}  bounding box "
                "(xmin ymin zmin .. xmax ymax zmax)"
            )
        # coordinates to a hundredth of rho, whatever their magnitude (survey data at 1e6)
        dec = int(min(12, max(0, np.ceil(-np.log10(self.rho)) + 2)))
        for r in g:
            lo, hi = r.bounds
            box = (
                " ".join(f"{x:.{dec}f}" for x in lo) + " .. " + " ".join(f"{x:.{dec}f}" for x in hi)
            )
            lines.append(f"{r.id:>4} {r.area:10.4g} {r.max_distance:10.4g} {r.status:>9}  {box}")
        rough = [r for r in g if r.status == STATUS_ROUGH]
        for r in rough:
            lines.append(f"  gap {r.id} is not filled: {r.reason}")
        if self.n_open:
            lines.append(
                f"  {self.n_open} open region(s) not examined: they reach into empty space (the "
                f"scan's border, or a hole wider than {self.max_hole:g} rho)"
            )
        if self.n_bent:
            lines.append(
                f"  {self.n_bent} region(s) enclosed only along the surface not filled: the surface "
                "bends too much across them for one smooth height field"
            )
        return "\n".join(lines)


@strict_methods
@dataclass
class Filled:
    """A filled level and the gaps it filled.

    ``level`` holds the measured points of the level at rho first, then the synthetic points;
    its ``synthetic`` attribute is 0 for measured and 1 for synthetic points, which have
    ``source_index`` and ``rank`` -1 and their insertion distance as ``radius``.
    """

    level: Any
    report: GapReport
    n_synthetic: int

    @property
    def n_measured(self) -> int:
        return int(self.level.size - self.n_synthetic)

    def summary(self, n_points: int) -> str:
        """``"K of N points + M synthetic (synthetic = 1) in G filled gap(s)"`` (thousands
        separated by commas, as every count the command line prints)."""
        gaps = sum(r.n_synthetic > 0 for r in self.report.regions)
        rough = sum(r.status == STATUS_ROUGH for r in self.report.gaps)
        text = (
            f"{self.n_measured:,} of {n_points:,} points + {self.n_synthetic:,} synthetic "
            f"(synthetic = 1) in {gaps} filled gap(s)"
        )
        if rough:
            text += f", {rough} rough gap(s) left open"
        return text


def _check(rho: Any, max_hole: Any) -> tuple[float, float]:
    r = check_positive(rho, "rho", allow_none=False)
    assert r is not None
    bad = InputError(
        f"max_hole (the widest hole filled, in units of rho) must be a number > 1, got {max_hole!r}"
    )
    try:
        m = float(max_hole)
    except (TypeError, ValueError):
        raise bad from None
    if not np.isfinite(m) or m <= 1.0:
        raise bad
    return float(r), m


@strict_keywords
def gaps_of_points(
    level: np.ndarray,
    sample: np.ndarray,
    rho: float,
    *,
    max_hole: float = MAX_HOLE,
    sample_rho: float = 0.0,
    scan: str = "",
    trees: tuple[Any, Any] | None = None,
) -> GapReport:
    """:class:`GapReport` of a level (K, 3) at ``rho`` over the input ``sample`` (M, 3)."""
    rho, max_hole = _check(rho, max_hole)
    t0 = time.perf_counter()
    tl, ts = trees if trees is not None else (None, None)
    search = find_regions(
        np.asarray(level, dtype=np.float64),
        np.asarray(sample, dtype=np.float64),
        rho,
        max_hole=max_hole,
        tree_l=tl,
        tree_s=ts,
    )
    return GapReport(
        scan=scan,
        rho=rho,
        max_hole=max_hole,
        regions=search.regions,
        n_open=search.n_open,
        n_bent=search.n_bent,
        sample_size=int(sample.shape[0]),
        sample_rho=float(sample_rho),
        level_size=int(level.shape[0]),
        seconds=time.perf_counter() - t0,
    )


def _sample_size(scan: Any, rho: float, exact: bool) -> tuple[int, float]:
    if exact:
        return scan.n_ordered, 0.0
    k = scan.size_for_rho(SAMPLE_FRACTION * rho)
    return k, (0.0 if k >= scan.n_ordered else SAMPLE_FRACTION * rho)


@strict_keywords
def find_gaps(scan: Any, rho: Any, *, max_hole: Any = MAX_HOLE, exact: bool = False) -> GapReport:
    """The undersampled regions of an archive scan (a ``ScanView``) at ``rho``.

    By default the input is represented by the prefix at rho/4 (every input point within rho/4
    of it), which is fast; ``exact`` uses every stored point (distances to the input exact)."""
    rho, max_hole = _check(rho, max_hole)
    k_level = scan.size_for_rho(rho)
    k_sample, sample_rho = _sample_size(scan, rho, exact)
    sample = scan.points(max(k_sample, k_level))
    return gaps_of_points(
        sample[:k_level],
        sample,
        rho,
        max_hole=max_hole,
        sample_rho=sample_rho,
        scan=scan.name,
    )


@strict_keywords
def archive_gaps(
    path: Any, scan: str | None, rhos: Any, *, max_hole: Any = MAX_HOLE
) -> list[GapReport]:
    """Exact :func:`find_gaps` reports of one scan of the archive at ``path``, one per rho."""
    from ..archive.reader import open_archive

    with open_archive(path) as arc:
        view = arc.scan(scan)
        return [find_gaps(view, r, max_hole=max_hole, exact=True) for r in rhos]


#: ``near_gaps`` codes: away from every gap, near a fillable gap, near a rough gap
NEAR_NONE, NEAR_FILLABLE, NEAR_ROUGH = 0, 1, 2


@strict_keywords
def near_gaps(
    points: np.ndarray, k_level: int, k_sample: int, rho: float, *, max_hole: Any = MAX_HOLE
) -> np.ndarray:
    """(N,) uint8 code of every point of a scan in stored order: :data:`NEAR_FILLABLE` or
    :data:`NEAR_ROUGH` within rho of a gap of the level ``points[:k_level]`` (the input represented
    by ``points[:k_sample]``), else :data:`NEAR_NONE`. The viewer's ``gaps`` colours."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    out = np.zeros(pts.shape[0], dtype=np.uint8)
    k_sample = max(k_sample, k_level)
    rep = gaps_of_points(pts[:k_level], pts[:k_sample], rho, max_hole=max_hole)
    for code, status in ((NEAR_ROUGH, STATUS_ROUGH), (NEAR_FILLABLE, STATUS_FILLABLE)):
        far = [g.gap_points() for g in rep.gaps if g.status == status]
        if far:
            d, _ = cKDTree(np.concatenate(far)).query(pts, k=1, distance_upper_bound=1.5 * rho)
            out[np.isfinite(d)] = code
    return out


def _insert(
    gaps: list[Region], tree_l: Any, stop: float
) -> list[tuple[Region, np.ndarray, np.ndarray]]:
    """Farthest-point insertion in every fillable gap, each starting from the level and the points
    inserted in the gaps before it: ``(region, candidate indices, radii)`` of the gaps that got points."""
    from scipy.spatial import cKDTree

    picks: list[tuple[Region, np.ndarray, np.ndarray]] = []
    done: Any = None  # k-d tree of the points inserted so far
    for reg in gaps:
        if reg.status != STATUS_FILLABLE:
            continue
        start, _ = tree_l.query(reg.candidates, k=1)
        if done is not None:
            start = np.minimum(start, done.query(reg.candidates, k=1)[0])
        idx, radii = farthest_insert(reg.candidates, start, stop)
        reg.n_synthetic = int(idx.size)
        if idx.size:
            picks.append((reg, idx, radii))
            done = cKDTree(np.concatenate([r.candidates[i] for r, i, _ in picks]))
    return picks


def _filled_attributes(
    scan: Any,
    level: Any,
    k_sample: int,
    sample: np.ndarray,
    picks: list[tuple[Region, np.ndarray, np.ndarray]],
    m: int,
) -> dict[str, np.ndarray]:
    """The level's attributes followed by the synthetic points' (interpolated around each hole),
    with the ``synthetic`` flag."""
    attrs = dict(level.attributes)
    if attrs and picks:
        names = list(attrs)
        measured = scan.attributes(k_sample, names)
        extra = [region_attributes(measured, sample, r, i) for r, i, _ in picks]
        attrs = {k: np.concatenate([attrs[k]] + [e[k] for e in extra]) for k in names}
    flag = np.concatenate([np.zeros(level.size, np.uint8), np.ones(m, np.uint8)])
    if SYNTHETIC in attrs:  # filling a level of a scan that was built from a filled level
        attrs[SYNTHETIC] = np.where(flag == 1, 1, attrs[SYNTHETIC]).astype(attrs[SYNTHETIC].dtype)
    else:
        attrs[SYNTHETIC] = flag
    return attrs


@strict_keywords
def fill_level(scan: Any, rho: Any, *, max_hole: Any = MAX_HOLE, attributes: Any = True) -> Filled:
    """The level of an archive scan (a ``ScanView``) at ``rho``, with synthetic points added in
    its fillable gaps until every point of them is within rho of the level.

    The measured points come first, exactly the level ``scan.level(rho=rho)``; the synthetic
    points follow, flagged by the ``synthetic`` attribute (1; 0 for measured points).
    """
    from scipy.spatial import cKDTree

    rho, max_hole = _check(rho, max_hole)
    t0 = time.perf_counter()
    level = scan.level(rho=rho, attributes=attributes)
    k_sample, sample_rho = _sample_size(scan, rho, False)
    k_sample = max(k_sample, level.size)
    sample = scan.points(k_sample)
    # unbalanced trees build 3x faster and query as fast on scan points
    tree_l = cKDTree(level.points, balanced_tree=False)
    tree_s = cKDTree(sample, balanced_tree=False)
    report = gaps_of_points(
        level.points,
        sample,
        rho,
        max_hole=max_hole,
        sample_rho=sample_rho,
        scan=scan.name,
        trees=(tree_l, tree_s),
    )
    picks = _insert(report.gaps, tree_l, stop_distance(rho, GRID_FRACTION * rho))
    pts = np.concatenate([r.candidates[i] for r, i, _ in picks]) if picks else np.zeros((0, 3))
    rad = np.concatenate([d for _, _, d in picks]) if picks else np.zeros(0)
    m = pts.shape[0]
    attrs = _filled_attributes(scan, level, k_sample, sample, picks, m)
    minus = np.full(m, -1, dtype=np.int64)
    # the level's other fields (scan, ordering, and any the reader adds) are kept as they are
    filled = dataclasses.replace(
        level,
        points=np.concatenate([level.points, pts]),
        attributes=attrs,
        source_index=np.concatenate([level.source_index, minus]),
        radius=np.concatenate([level.radius, rad]),
        rank=np.concatenate([level.rank, minus]),
        size=level.size + m,
        region={"fill": {"rho": rho, "max_hole": max_hole, "synthetic": m}},
    )
    report.seconds = time.perf_counter() - t0
    return Filled(level=filled, report=report, n_synthetic=m)
