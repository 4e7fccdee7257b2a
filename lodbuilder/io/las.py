"""LAS / LAZ / COPC reader and writer, built on laspy (``pip install lodbuilder[las]``).

Reading keeps every point dimension (standard ones and extra bytes) as an attribute, with laspy's
dtypes (bit fields as uint8, extra bytes scaled when the file says so); coordinates are the scaled
doubles. ``metadata`` keeps what is needed to write the same format back: LAS version, point format
id, scales, offsets, the CRS (WKT string and the raw LASF_Projection VLRs), the extra-byte
definitions, system identifier and generating software.

Writing uses the metadata of a LAS source when present (same version, point format, scale, offset
and CRS VLRs); attributes that are not dimensions of that point format become extra bytes. Without
LAS metadata it writes LAS 1.4, point format 7 when red/green/blue are given else 6, an offset at
the floor of the minimum and the power-of-ten scale that keeps the coordinates in int32.
"""

from __future__ import annotations

import base64
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError, MissingDependencyError
from .base import Scan

log = logging.getLogger(__name__)

_HINT = "pip install lodbuilder[las]"


def _laspy(path: Path) -> Any:
    try:
        import laspy
    except ImportError:
        raise MissingDependencyError(f"{path}: LAS/LAZ files need laspy with lazrs; {_HINT}") from None
    return laspy


def _check_laz_backend(laspy: Any, path: Path) -> None:
    if path.suffix.lower() == ".laz" and not laspy.LazBackend.detect_available():
        raise MissingDependencyError(f"{path}: LAZ files need a LAZ backend (lazrs); {_HINT}")


def _check_vlr_counts(path: Path) -> None:
    """Refuse VLR counts the file cannot hold: laspy reads that many VLRs from the stream, past
    its end, and a damaged count (billions) keeps it busy forever."""
    import struct

    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(247)
    if len(head) < 104 or head[:4] != b"LASF":
        return  # laspy says what is wrong
    header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
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


def _check_chunk_table(laspy: Any, path: Path) -> None:
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
    if not start + 8 <= at <= size - 8 or len(raw) != 8:
        return  # no chunk table where it should be: lazrs reads the chunks in sequence
    n_chunks = struct.unpack("<II", raw)[1]
    lazvlr = lazrs.LazVlr(vlr.record_data)
    count = int(header.point_count)
    most = count if lazvlr.uses_variable_size_chunks() else -(-count // max(1, lazvlr.chunk_size()))
    if n_chunks > max(1, min(most, size - start)):
        raise FormatError(
            f"{path}: the LAZ chunk table declares {n_chunks} chunks for {count} points in "
            f"{size} bytes; the file is damaged"
        )


def read(path: Path) -> list[Scan]:
    laspy = _laspy(path)
    _check_laz_backend(laspy, path)
    try:
        _check_vlr_counts(path)
        if path.suffix.lower() == ".laz":
            _check_chunk_table(laspy, path)
        las = laspy.read(str(path))
    except laspy.errors.LaspyException as exc:
        msg = " ".join(str(exc).split())
        raise FormatError(f"{path}: not a readable LAS/LAZ file ({msg}); check or re-export it") from None
    hdr = las.header
    pts = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1).astype(np.float64)
    attrs: dict[str, np.ndarray] = {}
    for dim in las.point_format.dimension_names:
        if dim in ("X", "Y", "Z"):
            continue
        attrs[dim] = np.ascontiguousarray(np.asarray(las[dim]))
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
    for d in las.point_format.extra_dimensions:
        extra.append({
            "name": d.name,
            "type": np.dtype(d.dtype).str.lstrip("<>=|") if d.num_elements == 1 else f"{d.num_elements}{np.dtype(d.dtype).base.str.lstrip('<>=|')}",
            "description": str(d.description or ""),
            "scales": None if d.scales is None else [float(s) for s in np.atleast_1d(d.scales)],
            "offsets": None if d.offsets is None else [float(s) for s in np.atleast_1d(d.offsets)],
        })
    meta = {
        "las_version": str(hdr.version),
        "las_point_format": int(hdr.point_format.id),
        "las_scales": [float(s) for s in hdr.scales],
        "las_offsets": [float(s) for s in hdr.offsets],
        "las_crs_wkt": wkt,
        "las_crs_vlrs": crs_vlrs,
        "las_extra_dims": extra,
        "las_system_identifier": str(hdr.system_identifier),
        "las_generating_software": str(hdr.generating_software),
        "las_compressed": path.suffix.lower() == ".laz",
    }
    return [Scan(points=pts, attributes=attrs, name=path.stem.split(".")[0] if path.name.lower().endswith(".copc.laz") else path.stem,
                 source=str(path), reader="las", metadata=meta)]


def _default_quantization(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    lo = points.min(axis=0) if points.size else np.zeros(3)
    offsets = np.floor(lo)
    span = float(np.max(np.abs(points - offsets))) if points.size else 1.0
    scale = 10.0 ** math.ceil(math.log10(max(span, 1e-300) / 2.0e9))
    return np.full(3, scale), offsets


def _fits(points: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> bool:
    q = np.round((points - offsets) / scales)
    return bool(np.all(np.abs(q) < 2**31 - 1))


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], metadata: dict[str, Any] | None) -> None:
    laspy = _laspy(path)
    compress = path.suffix.lower() == ".laz"
    if compress:
        _check_laz_backend(laspy, path)
    meta = metadata or {}
    names = set(attributes)
    fmt = meta.get("las_point_format")
    version = meta.get("las_version")
    if fmt is None:
        fmt, version = (7 if {"red", "green", "blue"} <= names else 6), "1.4"
    header = laspy.LasHeader(point_format=int(fmt), version=version)
    scales = np.asarray(meta.get("las_scales") or [], dtype=np.float64)
    offsets = np.asarray(meta.get("las_offsets") or [], dtype=np.float64)
    if scales.shape != (3,) or offsets.shape != (3,) or not _fits(points, scales, offsets):
        if scales.shape == (3,):
            log.warning("%s: coordinates do not fit the source scale/offset; choosing new ones", path)
        scales, offsets = _default_quantization(points)
    header.scales = scales
    header.offsets = offsets
    vlrs = meta.get("las_crs_vlrs") or []
    for v in vlrs:
        header.vlrs.append(laspy.VLR(user_id=v["user_id"], record_id=int(v["record_id"]),
                                     description=v.get("description", ""),
                                     record_data=base64.b64decode(v["data_b64"])))
    if meta.get("las_crs_wkt") and not any(int(v["record_id"]) == 2112 for v in vlrs):
        header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(meta["las_crs_wkt"]))
    if meta.get("las_system_identifier"):
        header.system_identifier = meta["las_system_identifier"][:32]
    header.generating_software = "lodbuilder"
    standard = set(header.point_format.standard_dimension_names) - {"X", "Y", "Z"}
    from .ply import columns

    cols = columns(attributes)
    extra_defs = {d["name"]: d for d in meta.get("las_extra_dims") or []}
    for name, arr in cols:
        if name in standard:
            continue
        if arr.dtype.kind not in "iufb":
            raise InputError(f"attribute {name!r} has dtype {arr.dtype}, which LAS cannot store; convert it to numbers")
        d = extra_defs.get(name)
        if d is not None and d.get("scales") is not None and arr.dtype.kind == "f" and not d["type"][0].isdigit():
            params = laspy.ExtraBytesParams(name=name, type=d["type"], description=d.get("description", ""),
                                            scales=np.asarray(d["scales"]), offsets=np.asarray(d["offsets"]))
        else:
            dt = np.dtype("u1") if arr.dtype == np.bool_ else arr.dtype.newbyteorder("=")
            params = laspy.ExtraBytesParams(name=name, type=dt, description=(d or {}).get("description", ""))
        header.add_extra_dim(params)
    las = laspy.LasData(header)
    las.x = points[:, 0]
    las.y = points[:, 1]
    las.z = points[:, 2]
    for name, arr in cols:
        try:
            las[name] = arr
        except (ValueError, OverflowError, TypeError) as exc:
            msg = " ".join(str(exc).split())
            raise InputError(f"attribute {name!r} does not fit LAS dimension {name!r} ({msg}); rename or rescale it") from None
    with open(path, "wb") as f:
        las.write(f, do_compress=compress)
