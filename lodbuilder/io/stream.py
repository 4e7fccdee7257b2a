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

Each streaming format has one reading path, in its own module, that both this module and
:func:`lodbuilder.io.read_scan` use (laspy's chunk iterator pattern): ``las.read.las_rows``,
``ply.vertex_rows`` and ``npy.npy_rows`` yield the rows in chunks; a whole read is that read in one
chunk. So a chunk gives exactly what :func:`lodbuilder.io.read_scan` gives for the same rows:
float64 coordinates and every other field as an attribute in the file's dtype, and the stream's
``metadata`` equals the reader's (a test checks both per format). Coordinates that are NaN or inf
are refused per chunk here (naming its rows) and per scan by the whole read.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import EmptyScanError, FormatError, LodbuilderError
from .base import Scan, file_stem

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

def _las_stream(p: Path) -> PointStream:
    from .las.common import laspy_module
    from .las.read import las_header, las_rows

    laspy = laspy_module(p)
    header = las_header(laspy, p)
    n = header.n_points
    if n == 0:
        raise EmptyScanError(f"{p}: holds no points; a scan needs at least one point")
    fields = header.fields
    name = file_stem(p)

    def it(size: int, first: int, stop: int) -> Iterator[Chunk]:
        for start, pts, attrs in las_rows(laspy, p, header, size, first, stop):
            _check_finite(p, pts, start)
            yield Chunk(start, pts, attrs)

    return PointStream(p, name, "las", n, header.metadata, fields, True, it)


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
    from .ply import (
        BYTE_ORDER_SAMPLE,
        XYZ,
        binary_layout,
        check_byte_order,
        header_metadata,
        parse_header,
        vertex_points,
        vertex_rows,
    )

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
    if any(c not in [q.name for q in vertex.properties] for c in XYZ) or int(vertex.count) == 0:
        return None  # the reader's own error
    layout = binary_layout(p, size, body_start, header, vi)
    if layout is None:
        return None
    offset, dtype, count = layout
    sample = vertex_rows(p, offset, dtype, count, BYTE_ORDER_SAMPLE)
    check_byte_order(p, next(sample)[1], header.byte_order)  # on the rows the whole read checks
    sample.close()
    native = dtype.newbyteorder("=")
    fields: dict[str, tuple[np.dtype, tuple[int, ...]]] = {n: (native[n], ()) for n in native.names or () if n not in XYZ}

    def it(rows: int, first: int, stop: int) -> Iterator[Chunk]:
        for start, data in vertex_rows(p, offset, dtype, count, rows, first, stop):
            pts = vertex_points(data)
            _check_finite(p, pts, start)
            yield Chunk(start, pts, {n: np.ascontiguousarray(data[n]) for n in fields})

    return PointStream(p, p.stem, "ply", count, header_metadata(header, vertex, notes), fields, True, it)


# ------------------------------------------------------------------------------------ NPY

def _npy_stream(p: Path) -> PointStream | None:
    from .crs import read_sidecar, set_crs
    from .npy import npy_layout, npy_rows

    layout = npy_layout(p)
    if layout is None:
        return None  # the reader's own error, or a layout read whole

    def it(size: int, first: int, stop: int) -> Iterator[Chunk]:
        for start, pts, attrs in npy_rows(p, layout, size, first, stop):
            _check_finite(p, pts, start)
            yield Chunk(start, pts, attrs)

    meta: dict[str, Any] = {"npy_layout": "structured" if layout.fields else "plain"}
    set_crs(meta, read_sidecar(p), "file")  # as lodbuilder.io.npy.read: a .prj sidecar
    return PointStream(p, p.stem, "npy", layout.n, meta, layout.fields, True, it)
