"""Reading LAS/LAZ/COPC files: the checks that refuse a damaged file before laspy reads it, and the
metadata that lets a scan be written back in its own format."""

from __future__ import annotations

import base64
import logging
import math
from collections.abc import Generator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import FormatError, LodbuilderError, ScanFileError
from .._files import exc_line, library_panic
from ..base import Rows, Scan, file_stem, whole
from ..crs import normalise_wkt, pyproj_wkt, set_crs
from .common import EXACT_PREFIX, check_laz_backend, laspy_module, quiet_laspy

log = logging.getLogger(__name__)


def _file_crs(hdr: Any) -> str | None:
    for vlr in list(hdr.vlrs) + list(hdr.evlrs or []):
        if type(vlr).__name__ == "WktCoordinateSystemVlr" and normalise_wkt(vlr.string):
            return normalise_wkt(vlr.string)
    try:
        crs = hdr.parse_crs()
    except ImportError:  # GeoTIFF keys need pyproj: CRS unknown, the raw VLRs still travel
        return None
    except Exception as exc:
        log.warning("LAS CRS keys not understood (%s); CRS unknown", exc_line(exc))
        return None
    return None if crs is None else pyproj_wkt(crs)


def check_points_layout(path: Path, head: bytes, size: int) -> None:
    """Refuse a coordinate scale of 0 (or not finite: every point would get one coordinate) and a
    point-data offset inside the header or with the points running past the end of the file
    (laspy then reads no points, or fails with a NumPy message)."""
    import math
    import struct

    if len(head) < 179:
        return  # laspy says what is wrong
    header_size, offset = struct.unpack_from("<HI", head, 94)
    record, legacy = struct.unpack_from("<HI", head, 105)
    scales = struct.unpack_from("<3d", head, 131)
    if not all(math.isfinite(s) and s > 0 for s in scales):
        raise FormatError(
            f"{path}: the LAS header's coordinate scale is {', '.join(f'{s:g}' for s in scales)} "
            "(x, y, z); a scale must be a finite number above 0 (with 0 every point has the same "
            "coordinate): the file is damaged; re-export it"
        )
    if offset < header_size:
        raise FormatError(
            f"{path}: the LAS header says the points start at byte {offset}, inside the "
            f"{header_size}-byte header; the file is damaged"
        )
    count = legacy
    if head[25] >= 4 and len(head) >= 255 and not legacy:
        count = struct.unpack_from("<Q", head, 247)[0]
    compressed = bool(head[104] & 0x80)  # (LAZ: the point format's top bit)
    need = count * record if not compressed else 0
    if offset + need > size:
        raise FormatError(
            f"{path}: the LAS header declares {count} points of {record} bytes from byte {offset} "
            f"({need:,} bytes), but the file ends at byte {size}: its point-data offset or point "
            "count is wrong; the file is damaged"
        )


def check_vlr_counts(path: Path) -> None:
    """Refuse VLR counts the file cannot hold: laspy reads that many VLRs from the stream, past
    its end, and a damaged count (billions) keeps it busy forever."""
    import struct

    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(255)
    if len(head) < 104 or head[:4] != b"LASF":
        return  # laspy says what is wrong
    header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
    check_points_layout(path, head, size)
    room = max(0, min(offset, size) - header_size)
    if n_vlrs * 54 > room:  # a VLR header alone is 54 bytes
        raise FormatError(
            f"{path}: the LAS header declares {n_vlrs} VLRs but only {room} bytes lie between the "
            "header and the points; the file is damaged"
        )
    if head[25] >= 4 and len(head) >= 247:  # LAS 1.4: extended VLRs at the end
        start, n_evlrs = struct.unpack_from("<QI", head, 235)
        if n_evlrs and n_evlrs * 60 > max(0, size - start):
            raise FormatError(
                f"{path}: the LAS header declares {n_evlrs} extended VLRs at byte {start} of a "
                f"{size}-byte file; the file is damaged"
            )


#: the largest LAZ chunk (points x point size) accepted when it is also larger than the whole file's
#: points: writers use 50,000-point chunks (1-3 MB); lazrs allocates a chunk whole before reading it
CHUNK_BYTES_MAX = 256 * 2**20


def _laszip_record(f: Any, head: bytes) -> bytes | None:
    """The record data of the LasZip VLR (user id "laszip encoded", record 22204) of the open
    LAS file ``f`` whose first bytes are ``head``, from its VLR headers (54 bytes each: reserved,
    user id, record id, record length, description), None where it has none: what laspy's
    header read finds, without building a header (opening a survey tile 0.82 -> 0.57 ms)."""
    import struct

    if len(head) < 104 or head[:4] != b"LASF":
        return None
    pos, _, n_vlrs = struct.unpack_from("<HII", head, 94)
    for _ in range(n_vlrs):  # (check_vlr_counts has bounded the count)
        f.seek(pos)
        vlr = f.read(54)
        if len(vlr) < 54:
            return None
        rid, length = struct.unpack_from("<HH", vlr, 18)
        if vlr[2:18].rstrip(b"\0") == b"laszip encoded" and rid == 22204:
            return f.read(length)
        pos += 54 + length
    return None


def check_chunk_table(path: Path) -> None:
    """Refuse a LAZ chunk table that declares more chunks than the file can hold: lazrs
    allocates it whole and aborts the process (SIGABRT) when the allocation fails."""
    import struct

    import lazrs

    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(255)
        record = _laszip_record(f, head)
        if record is None:
            return  # laspy says what is missing
        start = struct.unpack_from("<I", head, 96)[0]
        f.seek(start)
        raw = f.read(8)
        at = struct.unpack("<q", raw)[0] if len(raw) == 8 else -2
        if at == -1:  # written at the end: the last 8 bytes say where
            f.seek(max(0, size - 8))
            raw = f.read(8)
            at = struct.unpack("<q", raw)[0] if len(raw) == 8 else -2
        f.seek(max(0, at))
        raw = f.read(8)
    lazvlr = lazrs.LazVlr(record)
    point_size, count = struct.unpack_from("<HI", head, 105)
    if head[25] >= 4 and len(head) >= 255:  # (LAS 1.4: the 64-bit count)
        count = struct.unpack_from("<Q", head, 247)[0]
    if not lazvlr.uses_variable_size_chunks():
        # lazrs' parallel decompressor allocates one whole chunk: a damaged chunk size aborts it too
        chunk_bytes = lazvlr.chunk_size() * point_size
        if chunk_bytes > max(CHUNK_BYTES_MAX, count * point_size):
            raise FormatError(
                f"{path}: the LAZ header declares chunks of {lazvlr.chunk_size()} points "
                f"({chunk_bytes / 2**30:.1f} GiB each) for {count} points; the file is damaged"
            )
    if not start + 8 <= at <= size - 8 or len(raw) != 8:
        return  # no chunk table where it should be: lazrs reads the chunks in sequence
    n_chunks = struct.unpack("<II", raw)[1]
    most = count if lazvlr.uses_variable_size_chunks() else -(-count // max(1, lazvlr.chunk_size()))
    if n_chunks > max(1, min(most, size - start)):
        raise FormatError(
            f"{path}: the LAZ chunk table declares {n_chunks} chunks for {count} points in "
            f"{size} bytes; the file is damaged"
        )


def read(path: Path) -> list[Scan]:
    """The whole file: its chunked read (:func:`las_rows`) in one chunk."""
    laspy = laspy_module(path)
    header = las_header(laspy, path)
    pts, attrs = whole(las_rows(laspy, path, header, max(header.n_points, 1)))
    return [Scan(points=pts, attributes=attrs, name=file_stem(path), source=str(path), reader="las", metadata=header.metadata)]


@dataclass
class LasHeader:
    """What :func:`las_header` learns before any point is read: the point count, the format
    metadata, the point dimensions to read in order (X/Y/Z left out; a standard field that an exact
    copy replaces after the others, as the whole read always had it) and the attribute name of each."""

    n_points: int
    metadata: dict[str, Any]
    order: list[str]
    names: dict[str, str]
    #: every attribute's (dtype, per-point shape) as the read gives it (from a one-point record
    #: made for the header, so that no point is decompressed to learn them)
    fields: dict[str, tuple[np.dtype, tuple[int, ...]]]


def las_header(laspy: Any, p: Path) -> LasHeader:
    """The header of a LAS/LAZ file, after the checks that refuse a damaged file; one line for
    every failure."""
    check_laz_backend(laspy, p)
    try:
        check_vlr_counts(p)
        if p.suffix.lower() == ".laz":
            check_chunk_table(p)
        with quiet_laspy(), laspy.open(str(p)) as reader:
            hdr = reader.header
            n = int(hdr.point_count)
            meta, rename = las_metadata(hdr, hdr.point_format, p)
            dims = [d for d in hdr.point_format.dimension_names if d not in ("X", "Y", "Z")]
            probe = laspy.ScaleAwarePointRecord.zeros(1, header=hdr)
            kinds = {d: np.asarray(probe[d]) for d in dims}
    except BaseException as exc:
        raise _las_failure(laspy, p, exc) from None
    order = [d for d in dims if d not in rename] + [d for d in dims if d in rename]
    names = {d: rename.get(d, d) for d in dims}
    return LasHeader(n, meta, order, names, {names[d]: (kinds[d].dtype, tuple(kinds[d].shape[1:])) for d in order})


def las_rows(laspy: Any, p: Path, header: LasHeader, size: int, first: int = 0,
             stop: int | None = None) -> Generator[Rows, None, None]:
    """The one read of a LAS/LAZ file's points: ``(start, float64 (m, 3) points, attributes)``,
    ``size`` rows at a time from row ``first`` to ``stop`` (default: the end; laspy seeks, a LAZ
    file through its chunk table, and decompresses chunk by chunk).
    Coordinates are not checked for NaN/inf here: the whole read and the stream each say where."""
    stop = header.n_points if stop is None else stop
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
                attrs = {header.names[d]: np.ascontiguousarray(np.asarray(rec[d])) for d in header.order}
                yield start, pts, attrs
                start += m
    except GeneratorExit:
        raise
    except BaseException as exc:
        raise _las_failure(laspy, p, exc) from None
    if start != stop:
        raise FormatError(
            f"{p}: the header declares {header.n_points} points but the file holds {start}; re-export it"
        )


def _las_failure(laspy: Any, p: Path, exc: BaseException) -> BaseException:
    """The error to raise for ``exc`` met while reading ``p``: laspy's and the parser libraries'
    own errors (lazrs' panics included) worded as one line; lodbuilder's own errors and
    interruptions unchanged."""
    if isinstance(exc, LodbuilderError) or not isinstance(exc, Exception) and not library_panic(exc):
        return exc
    if isinstance(exc, laspy.errors.LaspyException):
        return FormatError(f"{p}: not a readable LAS/LAZ file ({exc_line(exc)}); check or re-export it")
    if isinstance(exc, MemoryError):
        return FormatError(f"{p}: too large to load into memory; split the scan or use a machine with more memory")
    if isinstance(exc, OSError):
        return ScanFileError(f"{p}: cannot be read ({exc_line(exc)}); check the file")
    return FormatError(f"{p}: cannot be read as LAS ({exc_line(exc)}); check or re-export the file")


def _extra_no_data(hdr: Any) -> dict[str, list[int | float | str]]:
    """The no-data values of the extra-bytes dimensions that declare one (option bit 0), by
    name, as JSON can hold them: integers as int, finite floats as float, nan/inf as a string
    that float() reads back."""
    out: dict[str, list[int | float | str]] = {}
    for vlr in hdr.vlrs:
        if type(vlr).__name__ != "ExtraBytesVlr":
            continue
        for eb in vlr.extra_bytes_structs:
            values = eb.no_data
            if values is None:
                continue
            name = eb.name.rstrip(b"\0").decode("ascii", "replace")
            out[name] = [int(v) if np.asarray(v).dtype.kind in "iu" else
                         (float(v) if math.isfinite(float(v)) else str(float(v)))
                         for v in np.atleast_1d(values)]
    return out


def las_metadata(hdr: Any, point_format: Any, path: Path) -> tuple[dict[str, Any], dict[str, str]]:
    """The format metadata of a LAS/LAZ file from its header, and the renaming of the extra
    dimensions lodbuilder wrote for exact standard fields: the same as :func:`lodbuilder.io.las.read`
    and the streaming reader (:mod:`lodbuilder.io.stream`) store."""
    wkt = None
    crs_vlrs = []
    for vlr in list(hdr.vlrs) + list(hdr.evlrs or []):
        if type(vlr).__name__ == "WktCoordinateSystemVlr":
            wkt = vlr.string
        if getattr(vlr, "user_id", "") == "LASF_Projection":
            data = vlr.record_data_bytes() if hasattr(vlr, "record_data_bytes") else vlr.record_data
            crs_vlrs.append({
                "user_id": vlr.user_id,
                "record_id": int(vlr.record_id),
                "description": str(vlr.description),
                "data_b64": base64.b64encode(bytes(data)).decode("ascii"),
            })
    extra = []
    rename: dict[str, str] = {}
    no_data = _extra_no_data(hdr)
    for d in point_format.extra_dimensions:
        desc = str(d.description or "")
        if desc.startswith(EXACT_PREFIX):
            rename[d.name] = desc[len(EXACT_PREFIX):]
            continue
        extra.append({
            "name": d.name,
            "type": np.dtype(d.dtype).str.lstrip("<>=|") if d.num_elements == 1
            else f"{d.num_elements}{np.dtype(d.dtype).base.str.lstrip('<>=|')}",
            "description": desc,
            "scales": None if d.scales is None else [float(s) for s in np.atleast_1d(d.scales)],
            "offsets": None if d.offsets is None else [float(s) for s in np.atleast_1d(d.offsets)],
            "no_data": no_data.get(d.name),
        })
    meta: dict[str, Any] = {
        "las_version": str(hdr.version),
        "las_point_format": int(hdr.point_format.id),
        "las_scales": [float(s) for s in hdr.scales],
        "las_offsets": [float(s) for s in hdr.offsets],
        "las_crs_wkt": wkt,
        "las_crs_vlrs": crs_vlrs,
        "las_wkt_bit": bool(hdr.global_encoding.wkt),
        "las_extra_dims": extra,
        "las_system_identifier": str(hdr.system_identifier),
        "las_generating_software": str(hdr.generating_software),
        "las_compressed": path.suffix.lower() == ".laz",
    }
    set_crs(meta, _file_crs(hdr), "file")
    return meta, rename
