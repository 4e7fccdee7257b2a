"""Reading archives: open, list scans, per-scan views, level queries reading only the prefix.

This module and the ones it imports stay clear of numba, pyvista and dask, so that
``lodbuilder slice`` starts fast.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import check_fraction, check_positive, check_size
from ..errors import (
    InputError,
    NotAnArchiveError,
    ScanFileError,
    ScanNotFoundError,
    SchemaVersionError,
)
from . import checks, safety
from . import layout as L
from .levels import (
    Level,
    cell_average,
    check_box,
    check_viewpoint,
    in_box,
    prefix_for_rho,
    representatives,
    viewpoint_keep,
)


def check_archive_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Root attributes of the archive at ``path``; raise a one-line error if it is not one we can read."""
    path = Path(path)
    _check_path(path)
    f, attrs = _open_checked(path)
    f.close()
    return attrs


def _check_path(path: Path) -> None:
    """The one-line errors for a path that is missing, a directory or not an HDF5 file."""
    import h5py

    if not path.exists():
        raise ScanFileError(f"archive {path} does not exist; build one with 'lodbuilder build'")
    if path.is_dir():
        raise NotAnArchiveError(f"{path} is a directory, not an lodbuilder archive")
    if not h5py.is_hdf5(path):
        raise NotAnArchiveError(
            f"{path} is not an lodbuilder archive (not an HDF5 file); build one with 'lodbuilder build'"
        )


def _open_checked(path: Path) -> tuple[Any, dict[str, Any]]:
    """The archive open for reading, checked before anything but metadata is read, and its root
    attributes."""
    f = safety.open_h5(path)
    try:
        with safety.h5_errors(path, "its root attributes"):
            attrs = _check_root_attrs(path, {k: L._attr_json(v) for k, v in f.attrs.items()})
            safety.check_file(f, path)  # nothing outside the file, no cycles, sizes it can hold
            checks.check_root(f, path)
    except BaseException:
        f.close()
        raise
    return f, attrs


def _check_root_attrs(path: Path, attrs: dict[str, Any]) -> dict[str, Any]:
    if attrs.get(L.A_FORMAT) != L.FORMAT:
        raise NotAnArchiveError(
            f"{path} is an HDF5 file but not an lodbuilder archive (no format='lodbuilder' attribute)"
        )
    version = attrs.get(L.A_SCHEMA_VERSION)
    if not isinstance(version, int):
        raise NotAnArchiveError(
            f"{path} has no integer schema_version attribute; it is not a valid archive"
        )
    if version > L.SCHEMA_VERSION:
        raise SchemaVersionError(
            f"{path} uses archive schema version {version}, newer than the {L.SCHEMA_VERSION} this "
            "lodbuilder reads; upgrade lodbuilder"
        )
    return attrs


@safety.guarded(lambda self: self.path)
class Archive:
    """An open archive. Use as a context manager: ``with open_archive(p) as a: ...``."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._file: Any = None
        _check_path(self.path)
        self._file, self.attrs = _open_checked(self.path)
        self.schema_version = int(self.attrs[L.A_SCHEMA_VERSION])
        self.lodbuilder_version = str(self.attrs.get(L.A_VERSION, ""))

    @property
    def file(self) -> Any:
        return self._file

    @property
    def scans(self) -> list[str]:
        """Scan names, sorted."""
        return sorted(self._file[L.G_SCANS]) if L.G_SCANS in self._file else []

    def scan(self, name: str | None = None) -> ScanView:
        """The scan called ``name``; ``None`` is allowed when the archive holds exactly one scan."""
        names = self.scans
        if name is None:
            if len(names) == 1:
                name = names[0]
            elif not names:
                raise ScanNotFoundError(f"archive {self.path} holds no scans")
            else:
                raise ScanNotFoundError(
                    f"archive {self.path} holds {len(names)} scans; choose one with --scan "
                    f"(one of {', '.join(names[:10])}{', ...' if len(names) > 10 else ''})"
                )
        if name not in names:
            raise ScanNotFoundError(
                f"archive {self.path} has no scan {name!r}; it holds {', '.join(names[:10]) or 'none'}"
            )
        return ScanView(self, name)

    __getitem__ = scan

    def __iter__(self):
        return (self.scan(n) for n in self.scans)

    def __len__(self) -> int:
        return len(self.scans)

    def index(self) -> list[dict[str, Any]]:
        """One dict per scan: name, n_points, bounds_min, bounds_max (from /index)."""
        ig = self._file.get(L.G_INDEX)
        if ig is None:
            return []
        names = [b.decode("utf-8", "replace") for b in ig[L.I_NAME][:]]
        counts = ig[L.I_N_POINTS][:]
        lo, hi = ig[L.I_BOUNDS_MIN][:], ig[L.I_BOUNDS_MAX][:]
        return [
            {"name": n, "n_points": int(c), "bounds_min": a.tolist(), "bounds_max": b.tolist()}
            for n, c, a, b in zip(names, counts, lo, hi, strict=True)
        ]

    def close(self) -> None:
        if self._file is not None:
            self._file.close()

    def __enter__(self) -> Archive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<Archive {self.path} scans={self.scans}>"


def open_archive(path: str | os.PathLike[str]) -> Archive:
    """Open an archive for reading (a context manager)."""
    return Archive(path)


@safety.guarded(lambda self: self.archive.path)
class ScanView:
    """Read access to one scan of an archive. Arrays are in the stored (farthest point) order."""

    def __init__(self, archive: Archive, name: str) -> None:
        self.archive = archive
        self.name = name
        self._g = archive.file[L.G_SCANS][name]
        m = self._meta = checks.check_scan_group(self._g, archive.path, name)
        self.n_points, self.n_ordered, self.encoding = m.n_points, m.n_ordered, m.encoding
        self.bounds = (m.bounds_min, m.bounds_max)
        self._step = m.step
        self._rindex: np.ndarray | None = None
        self._radius: np.ndarray | None = None
        self._offset, self._scale = m.offset, m.scale

    def __repr__(self) -> str:
        return f"<ScanView {self.name!r} n_points={self.n_points}>"

    # -- raw reads ---------------------------------------------------------------------------
    def _read(self, ds: Any, sel: Any = slice(None)) -> np.ndarray:
        arr = checks.read(self._meta, ds, sel)
        rows = checks.rows_of(sel, ds.shape[0]) if ds.ndim else None
        if rows is not None:  # what a query reads is checked as it is read
            rel = ds.name[len(self._g.name) + 1 :]
            checks.check_rows(self._meta, rel, arr, rows[0], self._raw_rows)
        return arr

    def _raw_rows(self, rel: str, lo: int, hi: int) -> np.ndarray:
        return self._g[rel][lo:hi]

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
                    f"scan {self.name!r} has no attribute {key!r}; it has {', '.join(grp) or 'none'}"
                )
            out[key] = self._read(grp[key], sel)
        return out

    def importance(self, name: str) -> np.ndarray:
        """(N,) float32 importance map ``name`` in stored order."""
        grp = self._g[L.G_IMPORTANCE]
        if name not in grp:
            raise InputError(
                f"scan {self.name!r} has no importance map {name!r}; it has {', '.join(grp) or 'none'}"
            )
        return self._read(grp[name])

    def importance_parameters(self, name: str) -> dict[str, Any]:
        return checks.json_attr(self._meta, self._g[L.G_IMPORTANCE][name].attrs, L.M_PARAMETERS)

    def ordering_parameters(self, name: str) -> dict[str, Any]:
        return checks.json_attr(self._meta, self._ordering_group(name).attrs, L.M_PARAMETERS)

    def _ordering_group(self, name: str) -> Any:
        grp = self._g[L.G_ORDERINGS] if L.G_ORDERINGS in self._g else {}
        if name not in grp:
            raise InputError(
                f"scan {self.name!r} has no ordering {name!r}; it has "
                f"{', '.join(['uniform'] + list(grp))}"
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
        checks.check_rho_prefix(self._meta, max(1, k), rho, self._rows)
        return max(1, k)

    def _bound(self, k: int) -> float:
        """Covering bound of the prefix of length k: radius[k], 0 for the whole ordering."""
        if k >= self.n_ordered:
            return 0.0
        return float(self._read(self._g[L.D_RADIUS], slice(k, k + 1))[0])

    def resolve_size(self, rho: Any = None, size: Any = None, fraction: Any = None) -> int:
        given = [x is not None for x in (rho, size, fraction)]
        if sum(given) != 1:
            raise InputError("give exactly one of rho, size or fraction")
        if rho is not None:
            return self.size_for_rho(rho)
        if size is not None:
            return check_size(size, self.n_ordered)
        f = check_fraction(fraction)
        return min(self.n_ordered, max(1, int(math.floor(f * self.n_ordered + 0.5))))

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
            rho=float(radius[k]) if k < self.n_ordered else 0.0,
            size=k,
            scan=self.name,
        )

    def _ordering_level(
        self, name: str, rho: Any, size: Any, fraction: Any, attributes: Any
    ) -> Level:
        og = self._ordering_group(name)
        rad_ds = og[L.D_RADIUS]
        kmax = rad_ds.shape[0]
        given = [x is not None for x in (rho, size, fraction)]
        if sum(given) != 1:
            raise InputError("give exactly one of rho, size or fraction")
        if rho is not None:
            rho = check_positive(rho, "rho", allow_none=False)
            rad = self._read(rad_ds)
            k = max(1, int(np.searchsorted(-rad, -rho, side="left")))
        elif size is not None:
            k = check_size(size, kmax)
        else:
            f = check_fraction(fraction)
            k = min(kmax, max(1, int(math.floor(f * kmax + 0.5))))
        pos = self._read(og[L.D_ORDER], slice(0, k))
        bound = 0.0 if k >= kmax else float(self._read(rad_ds, slice(k, k + 1))[0])
        return self._gather(pos, self._read(rad_ds, slice(0, k)), bound, attributes, ordering=name)

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
        )

    def refine_box(
        self, box: Any, rho_inner: Any, rho_outer: Any, *, attributes: Any = True
    ) -> Level:
        """Finer level inside ``box`` ((2, 3) or 6 numbers): see :mod:`lodbuilder.archive.levels`.

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
        pts = self.points(k_in)
        extra = k_out + np.flatnonzero(in_box(pts[k_out:], b, r_in))
        pos = np.concatenate([np.arange(k_out, dtype=np.int64), extra])
        region = {"box": b.tolist(), "rho_inner": r_in, "rho_outer": r_out}
        return self._gather(pos, None, self._bound(k_out), attributes, region=region)

    def refine_viewpoint(
        self, viewpoint: Any, rho0: Any, slope: Any, rho_max: Any = None, *, attributes: Any = True
    ) -> Level:
        """Level whose density falls with distance from ``viewpoint``:
        ``rho(x) = min(rho0 + slope * |x - viewpoint|, rho_max)``; every input point ``p`` is within
        ``rho(p)`` of a kept point."""
        v, r0, s, rmax = check_viewpoint(viewpoint, rho0, slope, rho_max)
        k_fine = self.size_for_rho(r0 / (1.0 + s))
        k_coarse = self.size_for_rho(rmax) if rmax is not None else 1
        k_coarse = min(k_coarse, k_fine)
        pts = self.points(k_fine)
        rad = self._read(self._g[L.D_RADIUS], slice(0, k_fine))
        keep = viewpoint_keep(pts, rad, v, r0, s, rmax)
        keep[:k_coarse] = True
        pos = np.flatnonzero(keep).astype(np.int64)
        region = {"viewpoint": v.tolist(), "rho0": r0, "slope": s, "rho_max": rmax}
        lo, hi = self.bounds
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        far = float(np.sqrt(((corners - v) ** 2).sum(axis=1)).max())
        bound = r0 + s * far if rmax is None else min(rmax, r0 + s * far)
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
