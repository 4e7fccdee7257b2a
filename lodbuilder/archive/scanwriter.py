"""Streaming writer of one scan: rows in stored (prefix) order, block by block, into one file.

:class:`ScanWriter` is the one place where a scan's datasets are written: ``update_archive`` and
``write_archive`` use it for in-memory scans, tiled and out-of-core builds call it directly with
blocks of rows. The file it writes is a complete archive holding that one scan (a *part*): open it
with :func:`lodbuilder.open_archive`, or add it to a bigger archive with
:func:`lodbuilder.archive.writer.register_parts` (O(its size), atomic).

Layout choices made here (see :mod:`lodbuilder.archive.layout`): HDF5 paged aggregation with a
page sized from the expected file size; every per-point dataset chunked by the same number of rows
R; rows written one *row group* at a time (the chunks of rows [iR, (i+1)R) of points, source_index,
radius, parent, every attribute and importance map next to each other), with HDF5's chunk cache
off so chunks reach the file in that order. A level (a prefix) is then one contiguous byte range.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ArchiveError, InputError
from ..sampling.spacing import axis_max, axis_min
from . import files as F
from . import layout as L
from .chunks import (
    Spec,
    check_points,
    check_rows,
    create_datasets,
    encode_exactly,
    spec_bytes,
    spec_of,
)
from .index import write_index
from .layout import IndexRow

log = logging.getLogger(__name__)

#: per-row datasets written in every row group, in this order (then attributes, importance maps)
_CORE = (L.D_POINTS, L.D_SOURCE_INDEX, L.D_RADIUS, L.D_PARENT)


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


@dataclass(frozen=True)
class PartInfo:
    """What :meth:`ScanWriter.finish` wrote: the file, the scan name, its sizes and bounds."""

    path: Path
    name: str
    n_points: int
    n_ordered: int
    bounds_min: tuple[float, float, float]
    bounds_max: tuple[float, float, float]
    nbytes: int


def new_file(
    path: Path, expected_bytes: int, created: str | None = None, max_chunk_bytes: int = 0
) -> Any:
    """Create the archive file ``path`` (a temporary) with root attributes, paged aggregation and
    HDF5's chunk cache off (chunks reach the file in the order they are written)."""
    import h5py

    f = h5py.File(
        path,
        "w",
        libver=L.LIBVER,
        fs_strategy="page",
        fs_page_size=L.page_size(expected_bytes, max_chunk_bytes),
        rdcc_nbytes=0,
    )
    f.attrs[L.A_FORMAT] = L.text(L.FORMAT)
    f.attrs[L.A_SCHEMA_VERSION] = np.int64(L.SCHEMA_VERSION)
    f.attrs[L.A_VERSION] = L.text(__version__)
    f.attrs[L.A_CREATED] = L.text(created or utc_now())
    f.attrs[L.A_MODIFIED] = L.text(utc_now())
    f.create_group(L.G_SCANS)
    return f


def close_quietly(f: Any) -> None:
    """Close an h5py file after a failure without raising (HDF5 may refuse the first time)."""
    for _ in range(3):
        try:
            if not f.id.valid:
                return
            f.close()
            return
        except Exception:  # noqa: BLE001 - the original error is what the caller reports
            continue


class ScanWriter:
    """Write one scan, in stored (prefix) order, block by block, into a self-contained file.

    The rows are the scan's points in farthest-point order: row ``i`` is the ``i``-th point of the
    ordering (points left out of the ordering, if any, come last with radius 0 and parent -1).
    Only the current row group (a few thousand rows) is held in memory, so a tiled build of 20M
    points can stream its merged ordering straight into the file::

        from lodbuilder.archive.scanwriter import ScanWriter
        from lodbuilder.archive.writer import register_parts

        with ScanWriter("site.part.h5", "site", n_points=20_000_000, metadata=las_metadata) as w:
            for b in merged_blocks():                  # any block sizes, in stored order
                w.write(b.points, b.source_index, b.radius, b.parent,
                        attributes={"intensity": b.intensity, "classification": b.cls})
            info = w.finish(seeds=seed_indices, build={...}, provenance={...})
        register_parts("survey.h5", [info.path])        # atomic, O(this scan); then delete it

    Arguments: ``path`` the file to write (written to a temporary beside it and renamed when
    :meth:`finish` succeeds; nothing is left behind on failure), ``name`` the scan name,
    ``n_points`` the number of rows that will be written (all input points), ``metadata`` the
    reader's format metadata (stored as ``format_metadata``; a LAS-like ``scale``/``offset`` or
    ``las_scales``/``las_offsets`` lets integer coordinates be stored exactly), ``encoding`` the
    coordinate storage (``"float32"``, ``"float64"``, ``"int32"``, ``"int64"``; by default the
    smallest lossless one for the first row group: pass it when later blocks may need more, e.g.
    ``"float64"``; a block that the chosen encoding would change is refused, never rounded).

    Each :meth:`write` is checked as it arrives (shapes, finite points, radii non-increasing and
    never NaN, parents earlier, source indices distinct and in range), so a part file always
    satisfies the archive's invariants. The process that writes a part need not be the one that
    registers it (a worker can write, the parent registers).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        name: str,
        n_points: int,
        *,
        metadata: Mapping[str, Any] | None = None,
        encoding: str | None = None,
    ) -> None:
        self.path = Path(path)
        self.name = L.check_name(name)
        if isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)) or n_points < 1:
            raise InputError(f"n_points must be a whole number >= 1, got {n_points!r}")
        if encoding is not None and encoding not in L.ENCODINGS:
            raise InputError(
                f"encoding must be one of {', '.join(L.ENCODINGS)} or None, got {encoding!r}"
            )
        self.n = int(n_points)
        self.metadata = dict(metadata or {})
        self._enc = encoding
        self._offset, self._scale = L.metadata_scale(self.metadata)
        if encoding in ("int32", "int64") and self._scale is None:
            raise InputError(
                f"encoding {encoding!r} needs a scale and offset in metadata ('scale'/'offset' or "
                "'las_scales'/'las_offsets')"
            )
        F.check_writable_dir(self.path, "part")
        self.rows = L.row_group_rows(self.n)
        self._tmp: Path | None = None
        self._f: Any = None
        self._g: Any = None
        self._ds: dict[str, Any] = {}
        self._pending: list[dict[str, np.ndarray]] = []
        self._n_pending = 0
        self._written = 0  # rows handed to write()
        self._flushed = 0  # rows in the file
        self._attr_spec: dict[str, tuple[np.dtype, tuple[int, ...]]] | None = None
        self._imp_names: list[str] | None = None
        self._seen = np.zeros(self.n, dtype=bool)
        self._last_radius = np.inf
        self._last_tail = -1  # last row with radius != 0 or parent != -1
        self._rindex: list[np.ndarray] = []
        self._lo = np.full(3, np.inf)
        self._hi = np.full(3, -np.inf)
        self._done = False
        self._margin = 0

    # -- context manager: a failure removes the temporary ----------------------------------------
    def __enter__(self) -> ScanWriter:
        return self

    def __exit__(self, exc_type: Any, *exc: object) -> None:
        if not self._done:
            self.abort()

    def abort(self) -> None:
        """Stop writing and remove the temporary file (the target path is never touched)."""
        self._done = True
        if self._f is not None:
            close_quietly(self._f)
            self._f = None
        if self._tmp is not None:
            F.unlink_quietly(self._tmp)

    # -- rows ------------------------------------------------------------------------------------
    def write(
        self,
        points: Any,
        source_index: Any,
        radius: Any,
        parent: Any,
        attributes: Mapping[str, Any] | None = None,
        importance: Mapping[str, Any] | None = None,
    ) -> None:
        """Append the next rows (any number, in stored order).

        ``points`` (m, 3) coordinates, ``source_index`` (m,) input indices, ``radius`` (m,)
        insertion radii, ``parent`` (m,) stored positions of the parents (-1 for roots),
        ``attributes`` the per-point attributes (the same names and dtypes in every block),
        ``importance`` per-point importance maps in stored order (their parameters go to
        :meth:`finish`)."""
        if self._done:
            raise ArchiveError(f"ScanWriter of scan {self.name!r} is finished or aborted")
        block = self._check_block(points, source_index, radius, parent, attributes, importance)
        m = block[L.D_RADIUS].shape[0]
        if m == 0:
            return
        self._written += m
        self._pending.append(block)
        self._n_pending += m
        try:
            while self._n_pending >= self.rows:
                self._flush_group(self.rows)
        except BaseException:
            self.abort()
            raise

    def _check_block(self, points, source_index, radius, parent, attributes, importance):
        where = f"scan {self.name!r}"
        pts = np.asarray(points, dtype=np.float64)
        m = pts.shape[0] if pts.ndim == 2 else -1
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"points of {where} must have shape (m, 3), got {pts.shape}")
        lo = self._written
        if lo + m > self.n:
            raise InputError(
                f"{where}: {lo + m} rows written but the ScanWriter was opened for "
                f"n_points={self.n}"
            )
        arrays: dict[str, np.ndarray] = {}
        for key, arr, kind in (
            (L.D_SOURCE_INDEX, source_index, "i"),
            (L.D_RADIUS, radius, "f"),
            (L.D_PARENT, parent, "i"),
        ):
            a = np.asarray(arr)
            if a.shape != (m,) or (kind == "i" and a.dtype.kind not in "iu"):
                raise InputError(
                    f"{key} of {where} must be {'integers' if kind == 'i' else 'numbers'} of "
                    f"shape ({m},), got {a.dtype} {a.shape}"
                )
            arrays[key] = a.astype(np.int64 if kind == "i" else np.float64, copy=False)
        check_points(pts, where, lo)
        src, rad, par = arrays[L.D_SOURCE_INDEX], arrays[L.D_RADIUS], arrays[L.D_PARENT]
        self._check_order(src, rad, par, lo, where)
        self._seen[src] = True
        if m:
            self._last_radius = float(rad[-1])
            tail = np.flatnonzero((rad != 0) | (par != -1))
            if tail.size:
                self._last_tail = lo + int(tail[-1])
        arrays[L.D_POINTS] = pts
        self._check_extras(arrays, attributes, m, where, "attribute", lo)
        self._check_extras(arrays, importance, m, where, "importance map", lo)
        return arrays

    def _check_order(self, src: np.ndarray, rad: np.ndarray, par: np.ndarray, lo: int, where: str) -> None:
        """A block's source indices (in range, each input point once), radii (non-increasing, >= 0)
        and parents (earlier rows or -1), from stored row ``lo`` on."""
        check_rows(src, rad, par, self.n, lo, self._last_radius, where)
        if src.size and self._seen[src].any():
            raise InputError(f"source_index of {where} repeats an input index; each point goes once")

    def _check_extras(self, arrays, extras, m, where, what, lo) -> None:
        extras = dict(extras or {})
        group = L.G_ATTRIBUTES if what == "attribute" else L.G_IMPORTANCE
        if what == "attribute":
            if self._attr_spec is None:
                self._attr_spec = {}
                for key, arr in extras.items():
                    L.check_name(key, "attribute name")
                    a = np.asarray(arr)
                    if a.dtype.kind not in "biuf":
                        raise InputError(
                            f"attribute {key!r} of {where} has dtype {a.dtype}; store numbers "
                            "(bool, int, float)"
                        )
                    self._attr_spec[key] = (a.dtype, a.shape[1:])
            spec = self._attr_spec
        else:
            if self._imp_names is None:
                self._imp_names = [L.check_name(k, "importance map name") for k in extras]
            spec = {k: (np.dtype(np.float32), ()) for k in self._imp_names}
        if set(extras) != set(spec):
            raise InputError(
                f"the {what}s of {where} at stored row {lo} are {sorted(extras)}, the first "
                f"block had {sorted(spec)}; give the same names in every block"
            )
        for key, (dtype, tail) in spec.items():
            a = np.asarray(extras[key])
            if a.shape != (m, *tail):
                raise InputError(
                    f"{what} {key!r} of {where} has shape {a.shape}, expected {(m, *tail)}"
                )
            if what == "attribute" and a.dtype != dtype:
                raise InputError(
                    f"attribute {key!r} of {where} is {a.dtype} at stored row {lo}, {dtype} in "
                    "the first block; give one dtype"
                )
            if what != "attribute" and not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
                raise InputError(f"importance map {key!r} of {where} must hold numbers")
            arrays[f"{group}/{key}"] = a.astype(dtype, copy=False)

    # -- HDF5 ------------------------------------------------------------------------------------
    def _take(self, k: int) -> dict[str, np.ndarray]:
        """The next k pending rows as one block."""
        out: dict[str, list[np.ndarray]] = {}
        need = k
        while need:
            head = self._pending[0]
            m = head[L.D_RADIUS].shape[0]
            take = min(m, need)
            for key, a in head.items():
                out.setdefault(key, []).append(a[:take])
            if take == m:
                self._pending.pop(0)
            else:
                self._pending[0] = {key: a[take:] for key, a in head.items()}
            need -= take
        self._n_pending -= k
        return {key: v[0] if len(v) == 1 else np.concatenate(v) for key, v in out.items()}

    def _row_bytes(self, block: dict[str, np.ndarray]) -> int:
        enc_bytes = np.dtype(self._enc or "float64").itemsize * 3
        other = sum(a[:1].nbytes for key, a in block.items() if key != L.D_POINTS)
        return enc_bytes + other

    def _open(self, block: dict[str, np.ndarray]) -> None:
        pts = block[L.D_POINTS]
        if self._enc is None:
            _, self._enc, off, sc = L.encode_points(pts, self.metadata)
            if off is not None:
                self._offset, self._scale = off, sc
        self._create(spec_of({k: self._encode(a, 0) if k == L.D_POINTS else a for k, a in block.items()}))

    def _create(self, spec: Spec) -> None:
        """Create the file and the scan's datasets (``spec``: see :mod:`.chunks`), no rows yet."""
        row_bytes, chunk = spec_bytes(spec, self.rows)
        expected = self.n * row_bytes
        page = L.page_size(expected, chunk)
        self._margin = 16 * page + (64 << 10)  # metadata, partial pages
        self._tmp = F.tmp_name(self.path)
        self._tmp.touch()
        # the whole file's raw bytes (uncompressed) plus metadata, before HDF5 writes anything
        F.reserve(self._tmp, int(expected * 1.1) + self._margin, f"scan {self.name!r}")
        self._f = new_file(self._tmp, expected, max_chunk_bytes=chunk)
        g = self._f[L.G_SCANS].create_group(self.name)
        self._g = g
        g.create_group(L.G_ATTRIBUTES)
        g.create_group(L.G_IMPORTANCE)
        g.create_group(L.G_ORDERINGS)
        self._ds = create_datasets(g, self.n, self.rows, spec)
        if self._offset is not None and self._enc in ("int32", "int64"):
            self._ds[L.D_POINTS].attrs[L.P_OFFSET] = self._offset
            self._ds[L.D_POINTS].attrs[L.P_SCALE] = self._scale

    def _encode(self, pts: np.ndarray, lo: int) -> np.ndarray:
        assert self._enc is not None
        return encode_exactly(pts, self._enc, self._offset, self._scale, f"scan {self.name!r}", lo)

    def _flush_group(self, k: int) -> None:
        block = self._take(k)
        if self._f is None:
            self._open(block)
        lo, hi = self._flushed, self._flushed + k
        assert self._tmp is not None
        F.reserve(self._tmp, int(k * self._row_bytes(block) * 1.1) + self._margin, f"scan {self.name!r}")
        pts = block[L.D_POINTS]
        self._lo = np.minimum(self._lo, axis_min(pts))
        self._hi = np.maximum(self._hi, axis_max(pts))
        rad = block[L.D_RADIUS]
        first = -(-lo // L.RADIUS_INDEX_STEP) * L.RADIUS_INDEX_STEP
        self._rindex.append(rad[first - lo :: L.RADIUS_INDEX_STEP].copy())
        try:
            for key, ds in self._ds.items():
                data = self._encode(pts, lo) if key == L.D_POINTS else block[key]
                _write_rows(ds, lo, data)
        except OSError as exc:
            raise F.disk_error(exc, self.path) from None
        self._flushed = hi

    # -- the end -----------------------------------------------------------------------------------
    def finish(
        self,
        *,
        n_ordered: int | None = None,
        seeds: Any = None,
        build: Mapping[str, Any] | None = None,
        provenance: Mapping[str, Any] | None = None,
        format_metadata: Mapping[str, Any] | None = None,
        importance_parameters: Mapping[str, Mapping[str, Any]] | None = None,
        orderings: Mapping[str, tuple[Any, Any, Any, Mapping[str, Any] | None]] | None = None,
        stop_radius: float = 0.0,
    ) -> PartInfo:
        """Write what is known at the end and move the file into place; returns a PartInfo.

        ``n_ordered`` (default: all rows) is how many leading rows the ordering covers (the rest
        must have radius 0 and parent -1); ``seeds`` the input indices that started the
        ordering; ``build`` and ``provenance`` JSON-able dicts (provenance gets
        lodbuilder_version and created_utc); ``format_metadata`` defaults to the ``metadata``
        given at the start; ``importance_parameters`` the parameters of each importance map;
        ``orderings`` extra orderings ``name -> (positions, radius, parent, parameters)`` with
        positions into the stored rows; ``stop_radius`` the covering bound of the whole ordered
        prefix (0 for a complete ordering; where a build stopped by size or rho left off)."""
        if self._done:
            raise ArchiveError(f"ScanWriter of scan {self.name!r} is finished or aborted")
        try:
            info = self._finish(
                n_ordered, seeds, build, provenance, format_metadata, importance_parameters,
                orderings, stop_radius,
            )
        except BaseException:
            self.abort()
            raise
        self._done = True
        return info

    def _checked_finish(self, n_ordered: Any, stop: Any, seeds: Any, imp_params: Any,
                        where: str) -> tuple[int, float, np.ndarray, dict[str, Any]]:
        """The ordered count, the stop radius, the seeds and the importance maps' parameters of
        :meth:`finish`, checked."""
        k = self.n if n_ordered is None else int(n_ordered)
        if not 1 <= k <= self.n:
            raise InputError(f"n_ordered of {where} must be in [1, {self.n}], got {n_ordered!r}")
        if self._last_tail >= k:
            raise InputError(
                f"{where}: stored row {self._last_tail} is beyond n_ordered={k} but has a radius "
                "or a parent; rows after the ordering must have radius 0 and parent -1"
            )
        stop = float(stop)
        if not stop >= 0.0:  # also NaN
            raise InputError(f"stop_radius of {where} must be a number >= 0 (or inf), got {stop!r}")
        seeds_arr = np.asarray([] if seeds is None else seeds, dtype=np.int64).reshape(-1)
        if seeds_arr.size and (seeds_arr.min() < 0 or seeds_arr.max() >= self.n):
            raise InputError(f"seeds of {where} must be input indices in [0, {self.n})")
        imp_params = dict(imp_params or {})
        unknown = sorted(set(imp_params) - set(self._imp_names or []))
        if unknown:
            raise InputError(f"importance_parameters name maps {unknown} that were not written")
        return k, stop, seeds_arr, imp_params

    def _finish(self, n_ordered, seeds, build, provenance, format_metadata, imp_params, orderings, stop):
        where = f"scan {self.name!r}"
        if self._written != self.n:
            raise InputError(
                f"{where}: {self._written} rows written but the ScanWriter was opened for "
                f"n_points={self.n}"
            )
        if self._n_pending:
            self._flush_group(self._n_pending)
        k, stop, seeds_arr, imp_params = self._checked_finish(n_ordered, stop, seeds, imp_params, where)
        g, f = self._g, self._f
        assert g is not None and f is not None and self._tmp is not None
        meta_text = {
            L.S_BUILD: L.to_json(dict(build or {})),
            L.S_PROVENANCE: L.to_json(
                {"lodbuilder_version": __version__, "created_utc": utc_now(), **(provenance or {})}
            ),
            L.S_FORMAT_METADATA: L.to_json(
                dict(self.metadata if format_metadata is None else format_metadata)
            ),
        }
        extra = sum(len(t) for t in meta_text.values())
        orderings = dict(orderings or {})
        extra += sum(np.asarray(o[0]).size * 24 for o in orderings.values())
        F.reserve(self._tmp, 2 * extra + self._margin, f"scan {self.name!r}")
        try:
            self._write_ends(g, k, stop, seeds_arr, imp_params, orderings, meta_text)
            row = IndexRow(self.name, self.n, tuple(self._lo), tuple(self._hi))
            write_index(f, [row])
            f.flush()
            f.close()
        except OSError as exc:
            raise F.disk_error(exc, self.path) from None
        self._f = None
        F.release(self._tmp)
        F.publish(self._tmp, self.path)
        return PartInfo(
            path=self.path,
            name=self.name,
            n_points=self.n,
            n_ordered=k,
            bounds_min=tuple(float(x) for x in self._lo),
            bounds_max=tuple(float(x) for x in self._hi),
            nbytes=self.path.stat().st_size,
        )

    def _write_ends(self, g: Any, k: int, stop: float, seeds_arr: np.ndarray, imp_params: dict[str, Any],
                    orderings: dict[str, Any], meta_text: dict[str, str]) -> None:
        """What :meth:`finish` knows: the radius index, the seeds, the importance maps' parameters,
        the extra orderings and the scan's attributes."""
        assert self._enc is not None  # (set by the first row group)
        L.create_dataset(g, L.D_RADIUS_INDEX, np.concatenate(self._rindex))
        L.create_dataset(g, L.D_SEEDS, seeds_arr)
        for key, params in imp_params.items():
            g[L.G_IMPORTANCE][key].attrs[L.M_PARAMETERS] = L.text(L.to_json(dict(params or {})))
        for key in self._imp_names or []:
            if L.M_PARAMETERS not in g[L.G_IMPORTANCE][key].attrs:
                g[L.G_IMPORTANCE][key].attrs[L.M_PARAMETERS] = L.text(L.to_json({}))
        for oname, (pos, rad, par, params) in orderings.items():
            write_ordering(g, oname, pos, rad, par, params)
        a = g.attrs
        a[L.S_N_POINTS] = np.int64(self.n)
        a[L.S_N_ORDERED] = np.int64(k)
        a[L.S_ENCODING] = L.text(self._enc)
        a[L.S_BOUNDS_MIN] = self._lo
        a[L.S_BOUNDS_MAX] = self._hi
        a[L.S_RADIUS_STEP] = np.int64(L.RADIUS_INDEX_STEP)
        a[L.S_STOP_RADIUS] = np.float64(stop)
        for key, text in meta_text.items():
            a[key] = L.text(text)


def _write_rows(ds: Any, lo: int, data: np.ndarray) -> None:
    """``ds[lo:lo + len(data)] = data`` through h5py's low-level API (the high-level selection
    machinery costs about 0.2 ms a call, and a scan is written in thousands of calls)."""
    from h5py import h5s

    data = np.ascontiguousarray(data)
    fspace = ds.id.get_space()
    fspace.select_hyperslab((lo,) + (0,) * (data.ndim - 1), data.shape)
    ds.id.write(h5s.create_simple(data.shape), fspace, data)


def write_ordering(
    g: Any, name: str, positions: Any, radius: Any, parent: Any, params: Mapping[str, Any] | None
) -> None:
    """Store an extra ordering (positions into the stored rows of scan group ``g``), checked."""
    L.check_name(name, "ordering name")
    n = int(g[L.D_SOURCE_INDEX].shape[0])
    pos = np.asarray(positions, dtype=np.int64).reshape(-1)
    rad = np.asarray(radius, dtype=np.float64).reshape(-1)
    par = np.asarray(parent, dtype=np.int64).reshape(-1)
    where = f"ordering {name!r} of scan {g.name.rsplit('/', 1)[-1]!r}"
    if not (pos.shape == rad.shape == par.shape) or pos.size == 0:
        raise InputError(f"{where}: order, radius and parent must be non-empty and of one length")
    if pos.min() < 0 or pos.max() >= n or np.unique(pos).size != pos.size:
        raise InputError(f"{where}: order must hold distinct stored positions in [0, {n})")
    if np.isnan(rad).any() or (rad[1:] > rad[:-1]).any():
        raise InputError(f"{where}: radius must be non-increasing and never NaN")
    if ((par >= np.arange(par.size)) | (par < -1)).any():
        raise InputError(f"{where}: parents must be earlier positions in the ordering or -1")
    grp = g.require_group(L.G_ORDERINGS)
    with contextlib.suppress(KeyError):
        del grp[name]
    og = grp.create_group(name)
    L.create_dataset(og, L.D_ORDER, pos)
    L.create_dataset(og, L.D_RADIUS, rad)
    L.create_dataset(og, L.D_PARENT, par)
    og.attrs[L.M_PARAMETERS] = L.text(L.to_json(dict(params or {})))
    og.attrs[L.S_N_ORDERED] = np.int64(pos.size)
