"""Reading LAS/LAZ/COPC files: the checks that refuse a damaged file before laspy reads it, and the
metadata that lets a scan be written back in its own format."""

from __future__ import annotations

import base64
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import FormatError
from .._files import exc_line
from ..base import Scan
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


def check_chunk_table(laspy: Any, path: Path) -> None:
    """Refuse a LAZ chunk table that declares more chunks than the file can hold: lazrs
    allocates it whole and aborts the process (SIGABRT) when the allocation fails."""
    import struct

    import lazrs

    size = path.stat().st_size
    with open(path, "rb") as f:
        header = laspy.LasHeader.read_from(f)
        vlr = next((v for v in header.vlrs if type(v).__name__ == "LasZipVlr"), None)
        if vlr is None:
            return  # laspy says what is missing
        start = int(header.offset_to_point_data)
        f.seek(start)
        raw = f.read(8)
        at = struct.unpack("<q", raw)[0] if len(raw) == 8 else -2
        if at == -1:  # written at the end: the last 8 bytes say where
            f.seek(max(0, size - 8))
            raw = f.read(8)
            at = struct.unpack("<q", raw)[0] if len(raw) == 8 else -2
        f.seek(max(0, at))
        raw = f.read(8)
    lazvlr = lazrs.LazVlr(vlr.record_data)
    count = int(header.point_count)
    point_size = int(header.point_format.size)
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
    laspy = laspy_module(path)
    check_laz_backend(laspy, path)
    try:
        check_vlr_counts(path)
        if path.suffix.lower() == ".laz":
            check_chunk_table(laspy, path)
        with quiet_laspy():
            las = laspy.read(str(path))
    except laspy.errors.LaspyException as exc:
        raise FormatError(f"{path}: not a readable LAS/LAZ file ({exc_line(exc)}); check or re-export it") from None
    hdr = las.header
    pts = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1).astype(np.float64)
    attrs: dict[str, np.ndarray] = {}
    for dim in las.point_format.dimension_names:
        if dim in ("X", "Y", "Z"):
            continue
        attrs[dim] = np.ascontiguousarray(np.asarray(las[dim]))
    meta, rename = las_metadata(hdr, las.point_format, path)
    for stored, original in rename.items():
        attrs[original] = attrs.pop(stored)
    name = path.stem.split(".")[0] if path.name.lower().endswith(".copc.laz") else path.stem
    return [Scan(points=pts, attributes=attrs, name=name, source=str(path), reader="las", metadata=meta)]


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
