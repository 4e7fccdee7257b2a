"""One scan of an open archive: its arrays in stored (farthest point) order, read and checked
only as far as a query needs, and its levels (by rho, size, fraction, box, viewpoint).

Like :mod:`lodbuilder.archive.reader`, clear of numba, pyvista and dask.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from .._validate import check_positive, check_size, quoted_names, strict_methods
from ..errors import InputError, LevelBeyondOrderingError
from ..levels import (
    Level,
    box_positions,
    cell_average,
    check_box,
    check_viewpoint,
    check_within_ordering,
    covering_bound,
    nonempty,
    prefix_for_rho,
    representatives,
    resolve_size,
    size_for_rho,
    viewpoint_bound,
    viewpoint_positions,
    viewpoint_sizes,
)
from . import checks, safety
from . import layout as L

if TYPE_CHECKING:
    from .reader import Archive


@safety.guarded(lambda self: self.archive.path)
@strict_methods
@safety.open_only()
class ScanView:
    """Read access to one scan of an archive. Arrays are in the stored (farthest point) order."""

    def __init__(self, archive: Archive, name: str, group: Any, io: Any = None) -> None:
        self.archive = archive
        self.name = name
        self._g = group
        self._io = io  # the remote file the group is read through (None: local)
        self._prefetch: Any = None
        m = self._meta = checks.check_scan_group(group, archive.path, name)
        self.n_points = m.n_points
        if io is not None:  # a remote archive: a level's rows are fetched in one go
            from .remote import Prefetcher

            self._prefetch = Prefetcher(io, group, self.n_points)
        self.n_ordered, self.encoding = m.n_ordered, m.encoding
        #: covering bound of the whole ordered prefix: 0, or where a partial build stopped
        self.stop_radius = m.stop_radius
        self.bounds = (m.bounds_min, m.bounds_max)
        self._step = m.step
        self._rindex: np.ndarray | None = None
        self._radius: np.ndarray | None = None
        self._offset, self._scale = m.offset, m.scale

    def __repr__(self) -> str:
        return f"<ScanView {self.name!r} n_points={self.n_points}>"

    def _check_open(self) -> None:
        """Every public method and property calls this first (see :func:`safety.open_only`)."""
        if not self._g.id.valid:
            raise safety.closed_error(self.archive.path)

    # -- raw reads ---------------------------------------------------------------------------
    def _read(self, ds: Any, sel: Any = slice(None)) -> np.ndarray:
        prefetch = None if self._prefetch is None else self._prefetch.before
        arr = checks.read(self._meta, ds, sel, prefetch)
        rows = checks.rows_of(sel, ds.shape[0]) if ds.ndim else None
        if rows is not None:  # what a query reads is checked as it is read
            rel = ds.name[len(self._g.name) + 1 :]
            checks.check_rows(self._meta, rel, arr, rows[0], self._raw_rows)
        return arr

    def _raw_rows(self, rel: str, lo: int, hi: int) -> np.ndarray:
        return checks.read(self._meta, self._g[rel], slice(lo, hi))

    def _rows(self, rel: str, lo: int, hi: int) -> np.ndarray:
        return self._read(self._g[rel], slice(lo, hi))

    def dataset(self, rel: str) -> Any:
        """The dataset ``rel`` of the scan (e.g. ``orderings/weighted/order``); reads are checked."""
        return checks.CheckedDataset(self._g[rel], self._read)

    def _json_attr(self, key: str) -> dict[str, Any]:
        return checks.json_attr(self._meta, self._g.attrs, key)

    # -- metadata ----------------------------------------------------------------------------
    @property
    def build(self) -> dict[str, Any]:
        """Build parameters: voxel_size, band_radius, seeds count, engine stats, ..."""
        return self._json_attr(L.S_BUILD)

    parameters = build

    @property
    def provenance(self) -> dict[str, Any]:
        return self._json_attr(L.S_PROVENANCE)

    @property
    def format_metadata(self) -> dict[str, Any]:
        return self._json_attr(L.S_FORMAT_METADATA)

    @property
    def attribute_names(self) -> list[str]:
        return list(self._g[L.G_ATTRIBUTES]) if L.G_ATTRIBUTES in self._g else []

    @property
    def importance_names(self) -> list[str]:
        return list(self._g[L.G_IMPORTANCE]) if L.G_IMPORTANCE in self._g else []

    @property
    def ordering_names(self) -> list[str]:
        return list(self._g[L.G_ORDERINGS]) if L.G_ORDERINGS in self._g else []

    # -- arrays (stored order) ---------------------------------------------------------------
    def points(self, k: int | None = None) -> np.ndarray:
        """(k, 3) float64 coordinates of the first k stored points (all when k is None)."""
        sel = slice(None) if k is None else slice(0, k)
        raw = self._read(self._g[L.D_POINTS], sel)
        return L.decode_points(raw, self.encoding, self._offset, self._scale)

    @property
    def radius(self) -> np.ndarray:
        if self._radius is None:
            self._radius = self._read(self._g[L.D_RADIUS])
        return self._radius

    @property
    def parent(self) -> np.ndarray:
        return self._read(self._g[L.D_PARENT])

    @property
    def source_index(self) -> np.ndarray:
        return self._read(self._g[L.D_SOURCE_INDEX])

    @property
    def seeds(self) -> np.ndarray:
        return self._read(self._g[L.D_SEEDS]) if L.D_SEEDS in self._g else np.zeros(0, np.int64)

    def attributes(self, k: int | None = None, names: Any = True) -> dict[str, np.ndarray]:
        """Attributes of the first k stored points; ``names`` True (all), False/None, or a list."""
        if names is False or names is None:
            return {}
        grp = self._g[L.G_ATTRIBUTES]
        wanted = list(grp) if names is True else list(names)
        sel = slice(None) if k is None else slice(0, k)
        out = {}
        for key in wanted:
            if key not in grp:
                raise InputError(
                    f"scan {self.name!r} has no attribute {key!r}; it has {quoted_names(grp)}"
                )
            out[key] = self._read(grp[key], sel)
        return out

    def importance(self, name: str) -> np.ndarray:
        """(N,) float32 importance map ``name`` in stored order."""
        grp = self._g[L.G_IMPORTANCE]
        if name not in grp:
            raise InputError(
                f"scan {self.name!r} has no importance map {name!r}; it has {quoted_names(grp)}"
            )
        return self._read(grp[name])

    def stored_rows(self, lo: int, hi: int) -> dict[str, Any]:
        """Every per-point array of stored rows ``lo:hi``, each checked as it is read: points
        (decoded), source_index, radius, parent, and the dicts attributes and importance."""
        sel = slice(int(lo), int(hi))
        g = self._g
        return {
            "points": L.decode_points(self._read(g[L.D_POINTS], sel), self.encoding, self._offset, self._scale),
            "source_index": self._read(g[L.D_SOURCE_INDEX], sel),
            "radius": self._read(g[L.D_RADIUS], sel),
            "parent": self._read(g[L.D_PARENT], sel),
            "attributes": {k: self._read(g[L.G_ATTRIBUTES][k], sel) for k in self.attribute_names},
            "importance": {k: self._read(g[L.G_IMPORTANCE][k], sel) for k in self.importance_names},
        }

    def ordering(self, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The extra ordering ``name``: (stored positions, radius, parent), checked."""
        og = self._ordering_group(name)
        return self._read(og[L.D_ORDER]), self._read(og[L.D_RADIUS]), self._read(og[L.D_PARENT])

    def importance_parameters(self, name: str) -> dict[str, Any]:
        return checks.json_attr(self._meta, self._g[L.G_IMPORTANCE][name].attrs, L.M_PARAMETERS)

    def ordering_parameters(self, name: str) -> dict[str, Any]:
        return checks.json_attr(self._meta, self._ordering_group(name).attrs, L.M_PARAMETERS)

    def ordering_positions(self, name: str) -> np.ndarray:
        """(n,) int64 stored positions of the extra ordering ``name``, in that ordering's order
        (its prefix of length k is the ordering's level of size k)."""
        return self._read(self._ordering_group(name)[L.D_ORDER])

    def _ordering_group(self, name: str) -> Any:
        grp = self._g[L.G_ORDERINGS] if L.G_ORDERINGS in self._g else {}
        if name not in grp:
            raise InputError(
                f"scan {self.name!r} has no ordering {name!r}; it has {quoted_names(['uniform', *grp])}"
            )
        return grp[name]

    # -- level sizes -------------------------------------------------------------------------
    def size_for_rho(self, rho: Any) -> int:
        """Length of the shortest prefix whose covering bound is <= rho (at least 1)."""
        rho = check_positive(rho, "rho", allow_none=False)
        assert rho is not None
        if self._rindex is None:
            self._rindex = self._read(self._g[L.D_RADIUS_INDEX])
        ds = self._g[L.D_RADIUS]
        k = prefix_for_rho(
            self._rindex,
            self._step,
            lambda lo, hi: self._read(ds, slice(lo, hi)),
            self.n_ordered,
            rho,
        )
        if k >= self.n_ordered:
            check_within_ordering(self.name, rho, self.n_ordered, self.n_points, self.stop_radius)
        checks.check_rho_prefix(self._meta, nonempty(k), rho, self._rows)
        return nonempty(k)

    def _bound(self, k: int) -> float:
        """Covering bound of the prefix of length k: radius[k], 0 for the whole ordering."""
        ds = self._g[L.D_RADIUS]
        return covering_bound(
            k, self.n_ordered, lambda i: self._read(ds, slice(i, i + 1))[0], self.stop_radius
        )

    def largest_finite_radius(self) -> float:
        """The first finite insertion radius (the one after the seeds): a rho at or above it gives
        the first point(s) only. 0 when the ordering holds only seeds."""
        ds = self._g[L.D_RADIUS]
        hi = min(self.n_ordered, self._meta.n_seeds + 1)
        head = self._read(ds, slice(0, hi))
        finite = head[np.isfinite(head)]
        if finite.size:
            return float(finite[0])
        return float(self._read(ds, slice(hi, hi + 1))[0]) if hi < self.n_ordered else 0.0

    def resolve_size(self, rho: Any = None, size: Any = None, fraction: Any = None) -> int:
        if (
            self.stop_radius > 0
            and isinstance(size, (int, np.integer))
            and self.n_ordered < size <= self.n_points
        ):
            raise LevelBeyondOrderingError(
                f"scan {self.name!r} is ordered only down to covering radius {self.stop_radius:.4g} "
                f"({self.n_ordered:,} of {self.n_points:,} points: a partial build), so no level holds "
                f"{size:,} points; rebuild it with --size {size} or without --size: lodbuilder build "
                "SOURCE -o ARCHIVE --force"
            )
        return resolve_size(self.n_ordered, rho, size, fraction, rho_size=self.size_for_rho)

    # -- levels ------------------------------------------------------------------------------
    def level(
        self,
        rho: Any = None,
        *,
        size: Any = None,
        fraction: Any = None,
        ordering: str | None = None,
        attributes: Any = True,
    ) -> Level:
        """A prefix level by ``rho``, ``size`` or ``fraction`` (exactly one), reading only the prefix.

        With ``ordering`` the prefix is taken from an extra ordering stored with the scan."""
        if ordering not in (None, "uniform"):
            return self._ordering_level(ordering, rho, size, fraction, attributes)
        k = self.resolve_size(rho, size, fraction)
        return self._prefix_level(k, attributes)

    def _prefix_level(self, k: int, attributes: Any) -> Level:
        g = self._g
        radius = self._read(g[L.D_RADIUS], slice(0, k + 1))  # radius[k] is the covering bound
        return Level(
            points=self.points(k),
            attributes=self.attributes(k, attributes),
            source_index=self._read(g[L.D_SOURCE_INDEX], slice(0, k)),
            radius=radius[:k],
            rank=np.arange(k, dtype=np.int64),
            rho=covering_bound(k, self.n_ordered, radius.__getitem__, self.stop_radius),
            size=k,
            scan=self.name,
            crs=self.crs,
            units=self.units,
        )

    def _ordering_level(
        self, name: str, rho: Any, size: Any, fraction: Any, attributes: Any
    ) -> Level:
        og = self._ordering_group(name)
        rad_ds = og[L.D_RADIUS]
        kmax = rad_ds.shape[0]
        k = resolve_size(
            kmax, rho, size, fraction, rho_size=lambda r: size_for_rho(self._read(rad_ds), r)
        )
        pos = self._read(og[L.D_ORDER], slice(0, k))
        bound = covering_bound(k, kmax, lambda i: self._read(rad_ds, slice(i, i + 1))[0])
        return self._gather(pos, self._read(rad_ds, slice(0, k)), bound, attributes, ordering=name)

    def positions_level(
        self, positions: Any, *, rho: float, attributes: Any = True, ordering: str | None = None
    ) -> Level:
        """The level of the stored ``positions`` (any order, e.g. from :meth:`ordering_positions`),
        reading the rows up to the largest; ``rho`` is the covering bound the caller's choice of
        positions guarantees, ``ordering`` the name the level reports."""
        pos = np.asarray(positions, dtype=np.int64)
        if pos.ndim != 1 or (pos.size and (pos.min() < 0 or pos.max() >= self.n_points)):
            raise InputError(
                f"positions must be a list of stored positions 0..{self.n_points - 1} of scan "
                f"{self.name!r}"
            )
        return self._gather(pos, None, rho, attributes, ordering=ordering)

    def _gather(
        self,
        pos: np.ndarray,
        radius: np.ndarray | None,
        rho: float,
        attributes: Any,
        ordering: str | None = None,
        region: dict[str, Any] | None = None,
    ) -> Level:
        """Level of the stored positions ``pos`` (any order), reading the span up to max(pos)."""
        g = self._g
        span = int(pos.max()) + 1 if pos.size else 0
        attrs = {key: arr[pos] for key, arr in self.attributes(span, attributes).items()}
        if radius is None:
            radius = self._read(g[L.D_RADIUS], slice(0, span))[pos]
        return Level(
            points=self.points(span)[pos],
            attributes=attrs,
            source_index=self._read(g[L.D_SOURCE_INDEX], slice(0, span))[pos],
            radius=radius,
            rank=pos.astype(np.int64),
            rho=rho,
            size=int(pos.size),
            scan=self.name,
            ordering=ordering,
            region=region or {},
            crs=self.crs,
            units=self.units,
        )

    def refine_box(
        self, box: Any, rho_inner: Any, rho_outer: Any, *, attributes: Any = True
    ) -> Level:
        """Finer level inside ``box`` ((2, 3) or 6 numbers): see :mod:`lodbuilder.levels`.

        Every input point inside the box is within ``rho_inner`` of a kept point; every input
        point is within ``rho_outer``."""
        b = check_box(box)
        r_in = check_positive(rho_inner, "rho_inner", allow_none=False)
        r_out = check_positive(rho_outer, "rho_outer", allow_none=False)
        assert r_in is not None and r_out is not None
        if r_in > r_out:
            raise InputError(
                f"the rho inside the box ({r_in}) must not be larger than the rho outside ({r_out})"
            )
        k_out, k_in = self.size_for_rho(r_out), self.size_for_rho(r_in)
        pos = box_positions(self.points(k_in), k_out, b, r_in)
        region = {"box": b.tolist(), "rho_inner": r_in, "rho_outer": r_out}
        return self._gather(pos, None, self._bound(k_out), attributes, region=region)

    def refine_viewpoint(
        self, viewpoint: Any, rho0: Any, slope: Any, rho_max: Any = None, *, attributes: Any = True
    ) -> Level:
        """Level whose density falls with distance from ``viewpoint``:
        ``rho(x) = min(rho0 + slope * |x - viewpoint|, rho_max)``; every input point ``p`` is within
        ``rho(p)`` of a kept point."""
        v, r0, s, rmax = check_viewpoint(viewpoint, rho0, slope, rho_max)
        k_coarse, k_fine = viewpoint_sizes(self.size_for_rho, r0, s, rmax)
        rad = self._read(self._g[L.D_RADIUS], slice(0, k_fine))
        pos = viewpoint_positions(self.points(k_fine), rad, v, r0, s, rmax, k_coarse)
        region = {"viewpoint": v.tolist(), "rho0": r0, "slope": s, "rho_max": rmax}
        bound = viewpoint_bound(self.bounds, v, r0, s, rmax)
        return self._gather(pos, rad[pos], bound, attributes, region=region)

    # -- representatives ---------------------------------------------------------------------
    def representatives(self, k: int, *, input_order: bool = True) -> np.ndarray:
        """For every point, the stored position (< k) of its representative at the level of size
        k: the first ancestor along the parent links of rank < k (-1 if none). Indexed by input
        index when ``input_order`` (default), else by stored position."""
        k = check_size(k, self.n_points, "k")
        rep = representatives(self.parent, k)
        if not input_order:
            return rep
        out = np.empty_like(rep)
        out[self.source_index] = rep
        return out

    def cell_averaged_attributes(
        self, k: int, names: Any = True
    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Attributes of the level of size k averaged over each kept point's cell (the points it
        represents), and the (k,) cell sizes."""
        k = check_size(k, self.n_points, "k")
        rep = representatives(self.parent, k)
        counts = np.bincount(rep[rep >= 0], minlength=k)
        attrs = self.attributes(None, names)
        return {key: cell_average(rep, k, arr) for key, arr in attrs.items()}, counts

    # -- CRS (helper io; see lodbuilder.io.crs) -------------------------------------------------

    @property
    def crs(self) -> str | None:
        """The scan's coordinate reference system as WKT text, or None when unknown."""
        wkt = self.format_metadata.get("crs_wkt")
        return str(wkt) if wkt else None

    @property
    def units(self) -> str | None:
        """Linear unit name of the CRS (``"metre"``, ``"US survey foot"``, ``"foot"``...): the
        one pyproj gave at build time, else pyproj's answer now; None when unknown (no CRS, or
        no pyproj): never guessed."""
        meta = self.format_metadata
        if meta.get("crs_units"):
            return str(meta["crs_units"])
        from ..io.crs import linear_units

        return linear_units(self.crs)
