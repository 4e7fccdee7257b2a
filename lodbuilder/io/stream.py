"""Streaming readers: a scan read in chunks of points, never whole.

The tiled (out-of-core) build reads its input through :func:`open_stream`. Which formats stream:

* **LAS / LAZ / COPC** (``.las``, ``.laz``, ``.copc.laz``): laspy's chunk iterator
  (``laspy.open(...).chunk_iterator``), LAZ decompressed chunk by chunk;
* **binary PLY** (little or big endian) whose vertices have no list property and follow only
  fixed-size elements: the vertex rows are read straight from the file, chunk by chunk;
* **NPY** (``.npy``: an (N, 3) array or a structured array with x, y, z): a read-only memory map,
  copied chunk by chunk.

Every other input (ASCII PLY, PLY with list properties, E57, XYZ/CSV/TXT/PTS, NPZ) does **not**
stream: :func:`open_stream` reads it whole with :func:`lodbuilder.io.read_scans` and hands it out in
chunks (``PointStream.streams`` is False), so it must fit in memory once.

A chunk gives exactly what :func:`lodbuilder.io.read_scan` gives for the same rows: float64
coordinates and every other field as an attribute in the file's dtype, and the stream's
``metadata`` equals the reader's (a test checks both per format).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, LodbuilderError, ScanFileError
from ._files import library_panic
from .base import Scan

log = logging.getLogger(__name__)

#: default rows per chunk
CHUNK = 1 << 20


@dataclass
class Chunk:
    """Rows ``start .. start + len(points)`` of a stream."""

    start: int
    points: np.ndarray
    attributes: dict[str, np.ndarray]

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass
class PointStream:
    """A scan opened for reading in chunks.

    ``n_points`` and ``metadata`` are known before any point is read; ``fields`` maps every
    attribute name to its (dtype, per-point shape); ``streams`` says whether the rows come from the
    file chunk by chunk (True) or from a scan read whole (False)."""

    path: Path
    name: str
    reader: str
    n_points: int
    metadata: dict[str, Any]
    fields: dict[str, tuple[np.dtype, tuple[int, ...]]]
    streams: bool
    _iter: Any = field(default=None, repr=False)

    def chunks(self, size: int = CHUNK, start: int = 0, stop: int | None = None) -> Iterator[Chunk]:
        """The rows ``start .. stop`` (default: all) in file order, ``size`` at a time (the last
        chunk may be shorter); a chunk's ``start`` is its first row in the whole file. LAS/LAZ,
        PLY and NPY seek to ``start`` (a LAZ file through its chunk table)."""
        stop = self.n_points if stop is None else min(int(stop), self.n_points)
        yield from self._iter(max(1, int(size)), max(0, int(start)), stop)


def streams(path: str | os.PathLike[str]) -> bool:
    """True when :func:`open_stream` reads ``path`` chunk by chunk (see the module docstring)."""
    try:
        return peek_stream(path) is not None
    except LodbuilderError:
        return False


def open_stream(path: str | os.PathLike[str], *, scan_index: int | None = None, crs: str | None = None,
                crs_override: bool = False) -> PointStream:
    """Open a scan file for chunked reading; ``scan_index`` picks one scan of a multi-scan E57.
    A format that does not stream is read whole here (see the module docstring). ``crs`` and
    ``crs_override`` as for :func:`lodbuilder.io.read_scans`."""
    from ._files import check_input_file

    p = check_input_file(path)
    s = _streaming(p) if scan_index is None else None
    if s is None:
        return _whole_stream(p, scan_index, crs, crs_override)
    _finish_metadata(s, crs, crs_override)
    return s


def _finish_metadata(s: PointStream, crs: str | None, crs_override: bool) -> None:
    """What :func:`lodbuilder.io.read_scans` adds to every reader's metadata: the CRS key, and
    the CRS given by the caller."""
    from .crs import KEY_WKT, assign_crs

    s.metadata.setdefault(KEY_WKT, None)
    if crs is not None:
        assign_crs(s.metadata, crs, override=crs_override, what=str(s.path))


def peek_stream(path: str | os.PathLike[str]) -> PointStream | None:
    """The stream of ``path`` when its format streams (reading only its header), else None."""
    from ._files import check_input_file

    return _streaming(check_input_file(path))


def declared_crs(path: str | os.PathLike[str]) -> str | None:
    """The CRS a scan file declares (WKT or None) without reading its points: the LAS/LAZ or PLY
    header, an E57's root ``coordinateMetadata``, an NPZ's metadata, else the ``.prj`` sidecar."""
    from .crs import KEY_WKT, read_sidecar
    from .registry import reader_for

    stream = peek_stream(path)
    if stream is not None:
        return stream.metadata.get(KEY_WKT)
    peek = getattr(reader_for(path)[1], "declared_crs", None)
    return peek(Path(path)) if peek is not None else read_sidecar(path)


def _streaming(p: Path) -> PointStream | None:
    from .registry import reader_for

    fmt, _ = reader_for(p)
    if fmt == "las":
        return _las_stream(p)
    if fmt == "npy" and p.suffix.lower() == ".npy":
        return _npy_stream(p)
    if fmt == "ply":
        return _ply_stream(p)
    return None


# ------------------------------------------------------------------------------------ in memory

def _scan_fields(scan: Scan) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    return {k: (np.asarray(v).dtype, tuple(np.asarray(v).shape[1:])) for k, v in scan.attributes.items()}


def scan_stream(scan: Scan, path: Path | None = None) -> PointStream:
    """A stream over an in-memory scan (its rows handed out in chunks)."""

    def it(size: int, start: int, stop: int) -> Iterator[Chunk]:
        for lo in range(start, stop, size):
            hi = min(stop, lo + size)
            yield Chunk(lo, scan.points[lo:hi], {k: np.asarray(v)[lo:hi] for k, v in scan.attributes.items()})

    return PointStream(path or Path(scan.source or scan.name), scan.name, scan.reader, len(scan),
                       dict(scan.metadata), _scan_fields(scan), False, it)


def _whole_stream(p: Path, scan_index: int | None, crs: str | None = None, crs_override: bool = False) -> PointStream:
    from .api import read_scan, read_scans

    if scan_index is None:
        scan = read_scan(p, crs=crs, crs_override=crs_override)
    else:
        scan = read_scans(p, crs=crs, crs_override=crs_override)[scan_index]
    return scan_stream(scan, p)


# ------------------------------------------------------------------------------------ LAS/LAZ

def _foreign_error(p: Path, exc: BaseException) -> FormatError:
    """A parser library's own error, worded as :func:`lodbuilder.io.read_scans` words it."""
    from ._files import exc_line

    return FormatError(f"{p}: cannot be read as LAS ({exc_line(exc)}); check or re-export the file")


def _las_error(p: Path, exc: BaseException) -> FormatError:
    msg = " ".join(str(exc).split())
    return FormatError(f"{p}: not a readable LAS/LAZ file ({msg}); check or re-export it")


def _las_stream(p: Path) -> PointStream:
    from .las.common import laspy_module, quiet_laspy

    laspy = laspy_module(p)
    n, meta, rename, dims, probe = _las_header(laspy, p)
    if n == 0:
        raise FormatError(f"{p}: holds no points; a scan needs at least one point")
    names = {d: rename.get(d, d) for d in dims}
    # read() keeps the standard field's place in its dict when an exact copy replaces it
    order = [d for d in dims if d not in rename] + [d for d in dims if d in rename]
    fields: dict[str, tuple[np.dtype, tuple[int, ...]]] = {}
    if probe is not None:
        for d in order:
            a = np.asarray(probe[d])
            fields[names[d]] = (a.dtype, tuple(a.shape[1:]))
    name = p.name[: -len(".copc.laz")] if p.name.lower().endswith(".copc.laz") else p.stem

    def it(size: int, first: int, stop: int) -> Iterator[Chunk]:
        start = first
        try:
            with quiet_laspy(), laspy.open(str(p)) as reader:
                if first:
                    reader.seek(first)
                while start < stop:
                    rec = reader.read_points(min(size, stop - start))
                    m = len(rec)
                    if m == 0:
                        break
                    pts = np.empty((m, 3), dtype=np.float64)
                    pts[:, 0] = rec.x
                    pts[:, 1] = rec.y
                    pts[:, 2] = rec.z
                    attrs = {names[d]: np.ascontiguousarray(np.asarray(rec[d])) for d in order}
                    _check_finite(p, pts, start)
                    yield Chunk(start, pts, attrs)
                    start += m
        except laspy.errors.LaspyException as exc:
            raise _las_error(p, exc) from None
        except LodbuilderError:
            raise
        except BaseException as exc:
            if not isinstance(exc, Exception) and not library_panic(exc):
                raise
            raise _foreign_error(p, exc) from None
        if start != stop:
            raise FormatError(f"{p}: the header declares {n} points but the file holds {start}; re-export it")

    return PointStream(p, name, "las", n, meta, fields, True, it)


def _las_header(laspy: Any, p: Path) -> tuple[int, dict[str, Any], dict[str, str], list[str], Any]:
    """A LAS/LAZ file's point count, metadata, renamed fields, dimensions and first point, after the
    checks that refuse a damaged file; one line for every failure."""
    from .las.common import check_laz_backend, quiet_laspy
    from .las.read import check_chunk_table, check_vlr_counts, las_metadata

    check_laz_backend(laspy, p)
    try:
        check_vlr_counts(p)
        if p.suffix.lower() == ".laz":
            check_chunk_table(laspy, p)
        with quiet_laspy(), laspy.open(str(p)) as reader:
            hdr = reader.header
            n = int(hdr.point_count)
            meta, rename = las_metadata(hdr, hdr.point_format, p)
            dims = [d for d in hdr.point_format.dimension_names if d not in ("X", "Y", "Z")]
            probe = reader.read_points(1) if n else None
    except laspy.errors.LaspyException as exc:
        raise _las_error(p, exc) from None
    except OSError as exc:
        raise ScanFileError(f"{p}: cannot be read ({' '.join(str(exc).split())}); check the file") from None
    except LodbuilderError:
        raise
    except BaseException as exc:  # lazrs' own errors (or panics) on a damaged file: the reader's message
        if not isinstance(exc, Exception) and not library_panic(exc):
            raise
        raise _foreign_error(p, exc) from None
    return n, meta, rename, dims, probe


def _check_finite(p: Path, pts: np.ndarray, start: int) -> None:
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        raise FormatError(
            f"{p}: {int(bad.sum())} point(s) in rows {start}..{start + len(pts) - 1} have NaN or inf coordinates "
            f"(first at index {start + int(np.argmax(bad))}); remove them from the file before building"
        )


# ------------------------------------------------------------------------------------ PLY

def _ply_stream(p: Path) -> PointStream | None:
    """Binary PLY with fixed-size vertex rows after fixed-size elements; None otherwise."""
    from .ply import XYZ, check_size, has_lists, header_metadata, parse_header

    size = p.stat().st_size
    notes: list[str] = []
    with open(p, "rb") as f:
        header = parse_header(f, p, notes)
        body_start = f.tell()
    if header.text:
        return None
    names = [e.name for e in header.elements]
    if "vertex" not in names:
        return None  # the reader's own error
    vi = names.index("vertex")
    vertex = header.elements[vi]
    before = header.elements[:vi]
    if has_lists(vertex) or any(has_lists(e) for e in before):
        return None
    props = [q.name for q in vertex.properties]
    if any(c not in props for c in XYZ):
        return None  # the reader's own error
    order = header.byte_order
    dtype = vertex.dtype(order)
    count = int(vertex.count)
    if count == 0:
        return None
    offset = body_start + sum(int(e.count) * e.dtype(order).itemsize for e in before)
    check_size(p, count, dtype.itemsize * count, size - offset)
    native = vertex.dtype("=")
    fields: dict[str, tuple[np.dtype, tuple[int, ...]]] = {n: (native[n], ()) for n in native.names if n not in XYZ}

    def it(rows: int, first: int, stop: int) -> Iterator[Chunk]:
        with open(p, "rb") as f:
            f.seek(offset + first * dtype.itemsize)
            start = first
            while start < stop:
                m = min(rows, stop - start)
                data = np.fromfile(f, dtype=dtype, count=m)
                if data.shape[0] != m:
                    raise FormatError(f"{p}: PLY body is truncated: read {start + data.shape[0]} of {count} "
                                      "vertices; re-export the file")
                data = data.astype(native, copy=False)
                pts = np.empty((m, 3), dtype=np.float64)
                for j, c in enumerate(XYZ):
                    pts[:, j] = data[c]
                _check_finite(p, pts, start)
                attrs = {n: np.ascontiguousarray(data[n]) for n in fields}
                yield Chunk(start, pts, attrs)
                start += m

    return PointStream(p, p.stem, "ply", count, header_metadata(header, vertex, notes), fields, True, it)


# ------------------------------------------------------------------------------------ NPY

def _npy_stream(p: Path) -> PointStream | None:
    try:
        arr = np.load(p, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError):
        return None  # the reader's own error
    xyz = ("x", "y", "z")
    if arr.dtype.names:
        if any(c not in arr.dtype.names for c in xyz) or arr.ndim != 1:
            return None
        fields = {n: (arr.dtype[n].base, arr.dtype[n].shape) for n in arr.dtype.names if n not in xyz}
        layout = "structured" if fields else "plain"
    elif arr.ndim == 2 and arr.shape[1] == 3 and arr.dtype.kind in "iuf":
        fields, layout = {}, "plain"
    else:
        return None
    n = int(arr.shape[0])
    if n == 0:
        return None
    del arr

    def it(size: int, start: int, stop: int) -> Iterator[Chunk]:
        a = np.load(p, mmap_mode="r", allow_pickle=False)
        try:
            for lo in range(start, stop, size):
                hi = min(stop, lo + size)
                block = np.array(a[lo:hi])  # a copy: the map is dropped chunk by chunk
                if block.dtype.names:
                    pts = np.stack([np.asarray(block[c], dtype=np.float64) for c in xyz], axis=1)
                    attrs = {k: np.ascontiguousarray(block[k]) for k in fields}
                else:
                    pts, attrs = np.asarray(block, dtype=np.float64), {}
                _check_finite(p, pts, lo)
                yield Chunk(lo, pts, attrs)
        finally:
            with contextlib.suppress(AttributeError):
                a._mmap.close()

    from .crs import read_sidecar, set_crs

    meta: dict[str, Any] = {"npy_layout": layout}
    set_crs(meta, read_sidecar(p), "file")  # as lodbuilder.io.npy.read: a .prj sidecar
    return PointStream(p, p.stem, "npy", n, meta, fields, True, it)
