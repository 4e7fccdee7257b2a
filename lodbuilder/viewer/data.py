"""What the viewer shows, as plain arrays (no PyVista here).

:class:`ViewData` holds one or more scans in farthest-point order: the points, their insertion
radii and parents (stored positions), attributes and importance maps. Several scans are merged
into one ordering by insertion radius, so the prefix of the merged ordering that the slider picks
is exactly the union of every scan's level at the same rho.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from .._validate import strict_keywords, strict_methods
from ..errors import InputError
from .colours import (  # noqa: F401 - the legends are part of the data a view shows
    ASPRS_COLOURS,
    GAP_COLOURS,
    SCAN_PALETTE,
    Categories,
    Legend,
    _to_uint8_rgb,
    _viridis,
    categorical,
    classification_legend,
    colormap,
    elevation_legend,
    importance_legend,
    intensity_legend,
    radius_legend,
    rank_legend,
    scan_legend,
)

BASE_MODES = ("rgb", "radius", "rank", "scan", "voronoi")
#: modes whose colours depend on the level shown (recomputed when it changes); ``gaps`` is asked
#: for by name (``--colour gaps``), not cycled through: it searches the level for holes
LEVEL_MODES = ("voronoi", "gaps", "radius")

#: neighbours of the PCA normals that shade the points
NORMAL_K = 12


def facing_camera(points: np.ndarray, up: str = "z") -> tuple[np.ndarray, np.ndarray]:
    """(direction from the centre to the camera, view-up) of a first view that faces the scan.

    A flat scan (its thinnest principal axis within 37 degrees of up: an airborne tile, a
    floor) is seen from above and the south (-y for z up), tilted 25 degrees. Otherwise (a
    statue, a facade) the camera looks along the thinnest principal axis, levelled to the
    horizon and raised 20 degrees, from the front side by the usual convention of scanners
    and 3D tools: +z for a y-up scan, -y for a z-up one (x up: +z)."""
    axis = "xyz".index(up[-1])
    u = np.zeros(3)
    u[axis] = -1.0 if up.startswith("-") else 1.0
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] > 50_000:
        pts = pts[:: pts.shape[0] // 50_000]
    front = np.zeros(3)
    front[{1: 2, 2: 1, 0: 2}[axis]] = 1.0 if axis != 2 else -1.0
    if pts.shape[0] < 3:
        return _unit(front + 0.35 * u), u
    w, v = np.linalg.eigh(np.cov((pts - pts.mean(axis=0)).T))
    n = v[:, int(np.argmin(w))]
    if abs(float(n @ u)) > 0.8:
        return _unit(u + 0.47 * front), u
    n = n - (n @ u) * u
    if float(np.linalg.norm(n)) < 1e-9:
        n = front
    n = _unit(n)
    if float(n @ front) < 0:
        n = -n
    return _unit(n + 0.36 * u), u


def _unit(v: np.ndarray) -> np.ndarray:
    return v / (float(np.linalg.norm(v)) or 1.0)


@strict_methods
@dataclass
class ViewData:
    """Points in farthest-point order and what can colour them.

    Attributes:
        points: (N, 3) float64, stored order (a level is a prefix).
        radius: (N,) non-increasing insertion radii (inf for seeds).
        parent: (N,) stored position of each point's parent, -1 for roots; parent[i] < i.
        attributes: per-point arrays in the same order (``red``/``green``/``blue`` give RGB).
        importance: per-point importance maps in the same order.
        scan_id: (N,) int32 index into ``scan_names``.
        scan_names: the names of the scans shown.
        crs: the scans' coordinate reference system (WKT), None when unknown or mixed.
        units: the linear unit of the coordinates (``metre``, ``foot``...), None when unknown.
        up: the scan's up axis (``z``, ``y``, ``-y``...): what ``elevation`` colours.
        stop_radius: no prefix covers finer than this: where a partial build (``--size`` or
            ``--rho``) stopped ordering (the largest over merged scans), 0 for full orderings.
    """

    points: np.ndarray
    radius: np.ndarray
    parent: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    importance: dict[str, np.ndarray] = field(default_factory=dict)
    scan_id: np.ndarray | None = None
    scan_names: tuple[str, ...] = ("scan",)
    crs: str | None = None
    units: str | None = None
    up: str = "z"
    stop_radius: float = 0.0

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        n = self.points.shape[0]
        if self.points.ndim != 2 or self.points.shape[1] != 3 or n == 0:
            raise InputError(f"points must have shape (N, 3) with N >= 1, got {self.points.shape}")
        self.radius = np.asarray(self.radius, dtype=np.float64)
        self.parent = np.asarray(self.parent, dtype=np.int64)
        for name, arr in (("radius", self.radius), ("parent", self.parent)):
            if arr.shape != (n,):
                raise InputError(f"{name} must have shape ({n},) like the points, got {arr.shape}")
        for group in (self.attributes, self.importance):
            for name, arr in group.items():
                if np.shape(arr)[0] != n:
                    raise InputError(
                        f"per-point array {name!r} has {np.shape(arr)[0]} rows, expected {n}"
                    )
        if self.scan_id is None:
            self.scan_id = np.zeros(n, dtype=np.int32)
        self._cells: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._gap_cache: tuple[int, np.ndarray] | None = None
        self._normals: np.ndarray | None = None
        finite = self.radius[np.isfinite(self.radius) & (self.radius > 0)]
        self._rmax = float(finite.max()) if finite.size else 1.0
        self._rmin = float(finite.min()) if finite.size else 1.0
        lo, hi = self.points.min(axis=0), self.points.max(axis=0)
        self.diagonal = float(np.linalg.norm(hi - lo)) or 1.0

    def __len__(self) -> int:
        return int(self.points.shape[0])

    # ---- levels -------------------------------------------------------------------------------

    # the arithmetic is lodbuilder.levels', as for every other level of an archive

    def size_for_rho(self, rho: float) -> int:
        """Shortest prefix whose next insertion radius is <= rho (at least 1 point)."""
        from ..levels import size_for_rho

        return size_for_rho(self.radius, float(rho))

    def rho_for_size(self, k: int) -> float:
        """The density a prefix of ``k`` points guarantees: the next insertion radius (0 at N;
        the largest finite radius where it is a seed's inf)."""
        from ..levels import covering_bound

        r = max(covering_bound(int(k), len(self), self.radius.__getitem__), self.stop_radius)
        return r if math.isfinite(r) else self._rmax

    def clamp_size(self, k: float) -> int:
        """A point count (the slider's) as a level size: nearest whole number, halves up, in
        [1, N]."""
        from ..levels import round_size

        return round_size(k, len(self))

    def resolve_size(self, rho=None, size=None, fraction=None) -> int:
        """Size of the level asked by exactly one of ``rho``, ``size`` or ``fraction``, as an
        archive scan's ``level`` computes it."""
        from ..levels import resolve_size

        return resolve_size(len(self), rho, size, fraction, rho_size=self.size_for_rho)

    def selective(self, k: int, lo, hi, factor: float = 4.0) -> np.ndarray:
        """Stored positions of a level finer inside the box [lo, hi], as the archive's
        ``refine_box``: the prefix of ``k`` points (density rho = ``rho_for_size(k)``) plus every
        point of the prefix at rho / ``factor`` that lies in the box grown by rho / ``factor``.

        Every point inside the box is then within rho / factor of a shown point. Sorted positions.
        """
        from ..levels import box_positions, check_box

        k = self.clamp_size(k)
        box = check_box(np.concatenate([np.ravel(lo), np.ravel(hi)]))
        rho_in = self.rho_for_size(k) / float(factor)
        k_in = self.size_for_rho(rho_in) if rho_in > 0 else len(self)
        return box_positions(self.points[:k_in], k, box, rho_in)

    # ---- Voronoi cells of a level, normals ----------------------------------------------------

    def cells(self, shown: int | np.ndarray) -> np.ndarray:
        """(N,) stored position of the shown point nearest to each point (Euclidean): the Voronoi
        cells of the displayed level, restricted to the scan's points.

        ``shown`` is a level size k (the prefix) or the stored positions of the shown points (a
        level refined in a box). The last answer is kept and updated when the level changes:
        points whose cell's point left the level are assigned again among the shown points, and
        every point closer to a newly shown point than to its cell's point moves to it (a tree
        of the new points, queried within the largest current distance), which is exact and
        several times cheaper than a new query of every point when a slider moves."""
        from scipy.spatial import cKDTree

        if np.isscalar(shown):
            pos = np.arange(self.clamp_size(shown))  # type: ignore[arg-type]
        else:
            pos = np.unique(np.asarray(shown, dtype=np.int64))
        if pos.size == 0:
            raise InputError("a level shows at least one point; got none")
        mask = np.zeros(len(self), dtype=bool)
        mask[pos] = True
        if self._cells is not None and np.array_equal(self._cells[0], mask):
            return self._cells[1]
        pts = self.points
        if self._cells is None:
            dist, j = cKDTree(pts[pos]).query(pts, k=1, workers=-1)
            cells = pos[np.asarray(j, dtype=np.int64)]
        else:
            old, cells, dist = self._cells
            cells, dist = cells.copy(), dist.copy()
            lost = np.flatnonzero(~mask[cells])  # their cell's point is no longer shown
            if lost.size:
                d, j = cKDTree(pts[pos]).query(pts[lost], k=1, workers=-1)
                cells[lost], dist[lost] = pos[np.asarray(j, dtype=np.int64)], d
            new = np.flatnonzero(mask & ~old)
            if new.size:
                bound = float(dist.max()) * (1 + 1e-9) + 1e-300
                d, j = cKDTree(pts[new]).query(pts, k=1, distance_upper_bound=bound, workers=-1)
                closer = d < dist
                cells[closer], dist[closer] = new[np.asarray(j, dtype=np.int64)[closer]], d[closer]
        self._cells = (mask, cells, dist)
        return cells

    def normals(self) -> np.ndarray:
        """(N, 3) float32 unit normals of the points (PCA over NORMAL_K neighbours in the full
        scan, unoriented; computed once). A level's points are stored points, so a level takes
        the rows of its positions."""
        if self._normals is None:
            from ..features.geometry import pca_normals

            k = min(NORMAL_K, len(self))
            if k < 3:
                self._normals = np.tile(np.array([0, 0, 1], np.float32), (len(self), 1))
            else:
                self._normals = np.ascontiguousarray(pca_normals(self.points, k=k), np.float32)
        return self._normals

    def gap_codes(self, shown: int | np.ndarray) -> np.ndarray:
        """(N,) 0 / 1 / 2: away from gaps / near a fillable gap / near a rough one, at the level
        shown (its prefix part, for a level refined in a box); see
        :func:`lodbuilder.fill.near_gaps`."""
        from ..fill import SAMPLE_FRACTION, near_gaps

        if np.isscalar(shown):
            k = self.clamp_size(shown)  # type: ignore[arg-type]
        else:
            pos = np.asarray(shown, dtype=np.int64)
            off = np.flatnonzero(pos != np.arange(pos.size))
            k = max(1, int(off[0]) if off.size else int(pos.size))
        if self._gap_cache is None or self._gap_cache[0] != k:
            rho = self.rho_for_size(k)
            codes = np.zeros(len(self), dtype=np.uint8)
            if rho > 0:
                codes = near_gaps(self.points, k, self.size_for_rho(SAMPLE_FRACTION * rho), rho)
            self._gap_cache = (k, codes)
        return self._gap_cache[1]

    # ---- colour modes -------------------------------------------------------------------------

    def colour_modes(self) -> list[str]:
        """The modes this data supports, in cycling order."""
        modes = []
        if all(c in self.attributes for c in ("red", "green", "blue")):
            modes.append("rgb")
        modes += ["radius", "rank", "elevation"]
        modes += [m for m in ("intensity", "classification") if m in self.attributes]
        modes += [f"importance:{name}" for name in self.importance]
        if len(self.scan_names) > 1:
            modes.append("scan")
        modes.append("voronoi")
        return modes

    def elevation(self) -> np.ndarray:
        """(N,) the coordinate along the up axis (negated for ``-y``...)."""
        v = self.points[:, "xyz".index(self.up[-1])]
        return -v if self.up.startswith("-") else v

    def check_mode(self, mode: str) -> str:
        if mode == "gaps":
            return mode
        modes = self.colour_modes()
        if mode == "importance" and any(m.startswith("importance:") for m in modes):
            mode = next(m for m in modes if m.startswith("importance:"))
        if mode not in modes:
            raise InputError(
                f"colour mode {mode!r} is not available here; choose one of {', '.join(modes)}"
            )
        return mode

    def legend(self, mode: str, shown: int | np.ndarray | None = None) -> Legend | Categories | None:
        """The scale of a scalar colour mode (radius, rank, importance, elevation, intensity),
        the categories of classification and scan, None for the others. With ``shown`` (the
        level displayed), radius runs from the level's rho to the radius where the level had
        1/64 of its points: the spread of radii inside the level shows (from the 1st percentile
        of every radius, a uniform level was one flat colour); finer points share the lowest
        colour, the level's coarsest the highest."""
        mode = self.check_mode(mode)
        if mode == "radius" and shown is not None:
            k = self.clamp_size(shown) if np.isscalar(shown) else int(np.size(shown))  # type: ignore[arg-type]
            rho = self.rho_for_size(k)
            lo = rho if math.isfinite(rho) and rho > 0 else self._rmin
            # top: the radius where the level had 1/64 of its points (8 x rho on a surface), so
            # its points spread over the colours; its first, coarsest points saturate
            top = self.rho_for_size(max(1, k // 64))
            hi = top if math.isfinite(top) and top > lo else self._rmax
            return Legend(f"radius ({self.units or 'scan units'}, log)", lo, max(hi, lo * (1 + 1e-9)), True)
        if mode == "elevation":
            return elevation_legend(self.elevation(), self.up, self.units)
        if mode == "intensity":
            return intensity_legend(self.attributes["intensity"])
        if mode == "classification":
            return classification_legend(self.attributes["classification"])
        if mode == "scan":
            return scan_legend(self.scan_names)
        if mode == "radius":
            return radius_legend(self.radius, self.units)
        if mode == "rank":
            return rank_legend(len(self))
        if mode.startswith("importance:"):
            name = mode.split(":", 1)[1]
            return importance_legend(name, self.importance[name])
        return None

    def colours(
        self, mode: str, shown: int | np.ndarray, positions: np.ndarray | None = None
    ) -> np.ndarray:
        """(M, 3) uint8 colours of the points at ``positions`` (default: the whole scan) when the
        level ``shown`` is displayed (a size k, or the stored positions of the shown points).

        ``voronoi`` colours a point by the cell of its nearest shown point (:meth:`cells`), so the
        full scan shows the displayed level's Voronoi diagram; the other modes do not depend on
        the level. Scalar modes map through :meth:`legend`.
        """
        mode = self.check_mode(mode)
        sel = slice(None) if positions is None else positions
        if mode == "rgb":
            rgb = np.column_stack(
                [np.asarray(self.attributes[c])[sel] for c in ("red", "green", "blue")]
            )
            return _to_uint8_rgb(rgb)
        if mode == "voronoi":
            return categorical(self.cells(shown)[sel])
        if mode == "gaps":
            return GAP_COLOURS[self.gap_codes(shown)[sel]]
        legend = self.legend(mode, shown if mode == "radius" else None)
        if isinstance(legend, Categories):
            labels = self.scan_id if mode == "scan" else self.attributes["classification"]
            return legend.colour(np.asarray(labels)[sel])
        assert legend is not None
        if mode == "elevation":
            values = self.elevation()[sel]
        elif mode == "intensity":
            values = np.asarray(self.attributes["intensity"], dtype=np.float64)[sel]
        elif mode == "radius":
            r = self.radius[sel]
            values = np.where(
                np.isfinite(r) & (r > 0), r, np.where(np.isinf(r), self._rmax, self._rmin)
            )
        elif mode == "rank":
            values = np.arange(1, len(self) + 1, dtype=np.float64)[sel]
        else:
            values = np.asarray(self.importance[mode.split(":", 1)[1]], dtype=np.float64)[sel]
        return colormap(legend.normalise(values))

    # ---- building -----------------------------------------------------------------------------

    @classmethod
    def merge(cls, parts: Sequence[ViewData], names: Sequence[str] | None = None) -> ViewData:
        """One ViewData of several scans, merged by insertion radius (stable, descending).

        Attributes and importance maps present in every part are kept.
        """
        if len(parts) == 1:
            return parts[0]
        radius = np.concatenate([p.radius for p in parts])
        offsets = np.cumsum([0] + [len(p) for p in parts])
        perm = np.argsort(-radius, kind="stable")
        inv = np.empty_like(perm)
        inv[perm] = np.arange(perm.size)
        parent = np.concatenate(
            [np.where(p.parent >= 0, p.parent + offsets[i], -1) for i, p in enumerate(parts)]
        )
        parent = np.where(parent >= 0, inv[np.maximum(parent, 0)], -1)[perm]
        scan_id = np.concatenate([np.full(len(p), i, dtype=np.int32) for i, p in enumerate(parts)])

        def common(getter) -> dict[str, np.ndarray]:
            keys = set(getter(parts[0]))
            for p in parts[1:]:
                keys &= set(getter(p))
            return {
                k: np.concatenate([np.asarray(getter(p)[k]) for p in parts])[perm]
                for k in sorted(keys)
            }

        return cls(
            points=np.concatenate([p.points for p in parts])[perm],
            radius=radius[perm],
            parent=parent,
            attributes=common(lambda p: p.attributes),
            importance=common(lambda p: p.importance),
            scan_id=scan_id[perm],
            scan_names=tuple(names) if names else tuple(n for p in parts for n in p.scan_names),
            crs=parts[0].crs if all(p.crs == parts[0].crs for p in parts) else None,
            units=parts[0].units if all(p.units == parts[0].units for p in parts) else None,
            stop_radius=max(p.stop_radius for p in parts),
        )


def crs_label(crs: str | None, units: str | None) -> str:
    """One line naming the coordinates' CRS and unit (``CRS unknown`` when there is none)."""
    unit = units or "scan units"
    if not crs:
        return f"CRS unknown, coordinates in {unit}"
    from ..io.crs import crs_name  # (pyproj names it, when installed)

    return f"CRS {crs_name(crs) or 'given as WKT (install pyproj to name it)'}, coordinates in {unit}"


@strict_keywords
def from_arrays(
    points,
    radius,
    parent,
    *,
    attributes: Mapping[str, np.ndarray] | None = None,
    importance: Mapping[str, np.ndarray] | None = None,
    name: str = "scan",
    crs: str | None = None,
    units: str | None = None,
) -> ViewData:
    """ViewData of one scan whose arrays are already in stored (farthest-point) order."""
    return ViewData(
        points=points,
        radius=radius,
        parent=parent,
        attributes=dict(attributes or {}),
        importance=dict(importance or {}),
        scan_names=(name,),
        crs=crs,
        units=units,
    )
