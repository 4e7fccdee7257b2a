"""LAS / LAZ / COPC reader and writer, built on laspy (``pip install lodbuilder[las]``).

Reading keeps every point dimension (standard ones and extra bytes) as an attribute, with laspy's
dtypes (bit fields as uint8, extra bytes scaled when the file says so); coordinates are the scaled
doubles. ``metadata`` keeps what is needed to write the same format back: LAS version, point format
id, scales, offsets, the CRS (WKT string and the raw LASF_Projection VLRs), the extra-byte
definitions, system identifier and generating software; ``crs_wkt`` holds the CRS as WKT (the WKT
VLR as written, else the GeoTIFF keys through pyproj).

Writing goes through :func:`las_layout`, the one mapping from points + attributes + metadata to
what laspy writes (the COPC exporter uses it too); see its docstring for every rule. In short:
nothing is dropped; a value that does not fit its standard LAS field exactly is written to an
extra-bytes dimension in its own dtype (and the standard field gets a scaled copy for viewers);
8-bit colours are scaled x257; the coordinate scale comes from the source LAS or from the point
spacing; every change is logged as a warning and listed in :attr:`LasLayout.notes`.
"""

from __future__ import annotations

import base64
import contextlib
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError, MissingDependencyError
from ._files import exc_line
from .base import Scan
from .crs import KEY_SOURCE, KEY_WKT, normalise_wkt, pyproj_wkt, set_crs

log = logging.getLogger(__name__)

#: description prefix of an extra-bytes dimension that holds the exact values of a standard field
EXACT_PREFIX = "lodbuilder exact "
_COLOURS = ("red", "green", "blue", "nir")
_GEOTIFF_IDS = (34735, 34736, 34737)
_WKT_ID = 2112
_EXTRA_TYPES = {"u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8", "f4", "f8"}
#: a standard field that the other point-format family holds under another name and unit:
#: field -> (its twin, factor from the twin's unit to the field's, how)
_TWINS = {
    "scan_angle": ("scan_angle_rank", 1 / 0.006, "degrees to 0.006-degree units"),  # formats 6-10
    "scan_angle_rank": ("scan_angle", 0.006, "0.006-degree units to degrees"),  # formats 0-5
}


def _laspy(path: Path | str) -> Any:
    from .._optional import require

    return require("laspy", f"{path}: LAS/LAZ")


def _check_laz_backend(laspy: Any, path: Path) -> None:
    if path.suffix.lower() == ".laz" and not laspy.LazBackend.detect_available():
        from .._optional import missing_message

        raise MissingDependencyError(missing_message("lazrs", f"{path}: LAZ"))


@contextlib.contextmanager
def _quiet_laspy() -> Iterator[None]:
    """laspy logs an ERROR line before raising on a damaged file; the raised error is reported
    as one line by the caller, so the log line would only repeat it."""
    lg = logging.getLogger("laspy")
    old = lg.level
    lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        lg.setLevel(old)


# ---------------------------------------------------------------------------------------- reader

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


def _check_points_layout(path: Path, head: bytes, size: int) -> None:
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


def _check_vlr_counts(path: Path) -> None:
    """Refuse VLR counts the file cannot hold: laspy reads that many VLRs from the stream, past
    its end, and a damaged count (billions) keeps it busy forever."""
    import struct

    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(255)
    if len(head) < 104 or head[:4] != b"LASF":
        return  # laspy says what is wrong
    header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
    _check_points_layout(path, head, size)
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
    laspy = _laspy(path)
    _check_laz_backend(laspy, path)
    try:
        _check_vlr_counts(path)
        if path.suffix.lower() == ".laz":
            _check_chunk_table(laspy, path)
        with _quiet_laspy():
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



# ------------------------------------------------------------------------------ the mapping

@dataclass
class ExtraDim:
    """One extra-bytes dimension: ``type`` is a numpy type string (``"f4"``, ``"3f8"``...)."""

    name: str
    type: str
    description: str = ""
    scales: list[float] | None = None
    offsets: list[float] | None = None
    no_data: list[int | float | str] | None = None


@dataclass
class LasLayout:
    """Everything laspy needs to write a set of points: see :func:`las_layout`.

    ``dimensions`` maps each LAS dimension name (standard or extra) to the values to assign, in
    write order; ``vlrs`` are raw LASF_Projection VLRs copied from a LAS source (``user_id``,
    ``record_id``, ``description``, ``data`` bytes); ``crs_wkt`` is written as a WKT VLR when
    ``write_wkt_vlr``; ``notes`` lists every change made to the data, one line each."""

    version: str
    point_format: int
    scales: np.ndarray
    offsets: np.ndarray
    crs_wkt: str | None = None
    write_wkt_vlr: bool = False
    wkt_bit: bool = False
    vlrs: list[dict[str, Any]] = field(default_factory=list)
    extra_dims: list[ExtraDim] = field(default_factory=list)
    dimensions: dict[str, np.ndarray] = field(default_factory=dict)
    system_identifier: str = ""
    notes: list[str] = field(default_factory=list)

    def header(self) -> Any:
        """A ``laspy.LasHeader`` with version, point format, scales, offsets, extra dimensions,
        CRS VLRs and the global-encoding WKT bit set."""
        laspy = _laspy("LAS output")
        header = laspy.LasHeader(point_format=int(self.point_format), version=self.version)
        header.scales = self.scales
        header.offsets = self.offsets
        for d in self.extra_dims:
            kw: dict[str, Any] = {"name": d.name, "type": d.type, "description": d.description}
            if d.scales is not None:
                kw.update(scales=np.asarray(d.scales), offsets=np.asarray(d.offsets))
            if d.no_data is not None:
                kw.update(no_data=np.asarray([float(v) if isinstance(v, str) else v for v in d.no_data]))
            header.add_extra_dim(laspy.ExtraBytesParams(**kw))
        for v in self.vlrs:
            header.vlrs.append(laspy.VLR(user_id=v["user_id"], record_id=int(v["record_id"]),
                                         description=v.get("description", ""), record_data=v["data"]))
        if self.write_wkt_vlr and self.crs_wkt:
            header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(self.crs_wkt))
        if self.wkt_bit:
            header.global_encoding.wkt = True
        if self.system_identifier:
            header.system_identifier = self.system_identifier[:32]
        header.generating_software = "lodbuilder"
        return header

    def las_data(self, points: np.ndarray) -> Any:
        """A ``laspy.LasData`` holding ``points`` and every dimension, ready to write."""
        laspy = _laspy("LAS output")
        las = laspy.LasData(self.header())
        las.x = points[:, 0]
        las.y = points[:, 1]
        las.z = points[:, 2]
        for name, arr in self.dimensions.items():
            try:
                las[name] = arr
            except (ValueError, OverflowError, TypeError) as exc:
                raise InputError(f"attribute {name!r} does not fit LAS dimension {name!r} ({exc_line(exc)}); rename or rescale it") from None
        return las


def _standard_dims(fmt: int) -> dict[str, tuple[float, float, bool]]:
    """Standard dimension -> (min, max, integer) of what it holds exactly (X/Y/Z left out)."""
    laspy = _laspy("LAS output")
    out: dict[str, tuple[float, float, bool]] = {}
    for d in laspy.PointFormat(fmt).dimensions:
        if not d.is_standard or d.name in ("X", "Y", "Z"):
            continue
        if d.kind.name == "BitField" or d.dtype is None:
            out[d.name] = (0, 2 ** int(d.num_bits) - 1, True)
        elif np.dtype(d.dtype).kind == "f":
            out[d.name] = (-math.inf, math.inf, False)
        else:
            info = np.iinfo(np.dtype(d.dtype))
            out[d.name] = (info.min, info.max, True)
    return out


def _fits(values: np.ndarray, lo: float, hi: float, integer: bool) -> bool:
    a = np.asarray(values)
    if a.ndim != 1:
        return False
    if a.size == 0:
        return True
    if a.dtype == np.bool_:
        return True
    if not integer:
        return a.dtype.kind in "iuf" and (a.dtype.kind != "f" or a.dtype.itemsize <= 8)
    if a.dtype.kind in "iu":
        return bool(a.min() >= lo and a.max() <= hi)
    if a.dtype.kind == "f":
        return bool(np.all(np.isfinite(a)) and np.all(a == np.round(a)) and a.min() >= lo and a.max() <= hi)
    return False


def _scaled_rendition(name: str, a: np.ndarray, hi: float) -> tuple[np.ndarray, str]:
    """A copy of ``a`` for a standard integer field [0, hi] (for viewers), and how it was made."""
    v = np.asarray(a, dtype=np.float64)
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        return np.zeros(v.shape, dtype=np.float64), "all values NaN: left 0"
    lo_v, hi_v = float(finite.min()), float(finite.max())
    if name in _COLOURS and lo_v >= 0 and hi_v <= 1:
        how, out = "x 65535", v * 65535
    elif name in _COLOURS and lo_v >= 0 and hi_v <= 255:
        how, out = "x 257", v * 257
    else:
        lo = min(0.0, lo_v)
        span = hi_v - lo
        out = (v - lo) / span * hi if span > 0 else np.zeros_like(v)
        how = f"mapped [{lo:g}, {hi_v:g}] -> [0, {hi:g}]"
    return np.clip(np.rint(np.nan_to_num(out)), 0, hi), how


def _extra_type(name: str, a: np.ndarray, notes: list[str]) -> tuple[np.ndarray, str]:
    if a.dtype == np.bool_:
        return a.astype(np.uint8), "u1"
    if a.dtype.kind == "f" and a.dtype.itemsize < 4:
        return a.astype(np.float32), "f4"
    key = a.dtype.str.lstrip("<>=|")
    if key not in _EXTRA_TYPES:
        if a.dtype.kind == "f":  # float128
            notes.append(f"{name}: {a.dtype} written as float64 extra bytes")
            return a.astype(np.float64), "f8"
        raise InputError(f"attribute {name!r} has dtype {a.dtype}, which LAS cannot store; convert it to numbers")
    return np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("=")), key


def _spacing(points: np.ndarray) -> float:
    """A cheap estimate of the point spacing: sqrt(area / N) over the two largest extents."""
    n = points.shape[0]
    ext = np.sort(np.ptp(points, axis=0))[::-1] if n else np.zeros(3)
    area = float(ext[0] * ext[1]) if ext[1] > 0 else float(ext[0]) ** 2
    if n < 2 or area <= 0:
        return float(ext[0]) if ext[0] > 0 else 1.0
    return math.sqrt(area / n)


def choose_quantization(points: np.ndarray, spacing: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(scales, offsets) for points without a LAS source: the power of ten at or below
    spacing / 100 (``spacing`` estimated from the bounding box when not given), made coarser only
    when the coordinates would not fit in int32; offsets at the floor of the minimum (in units of
    1000 x scale). Quantisation error <= scale / 2 per coordinate."""
    s = spacing if spacing and math.isfinite(spacing) and spacing > 0 else _spacing(points)
    scale = 10.0 ** math.floor(math.log10(s / 100.0))
    lo = points.min(axis=0) if points.size else np.zeros(3)
    while True:
        unit = scale * 1000.0
        offsets = np.floor(lo / unit) * unit
        if not points.size or np.all(np.abs(np.rint((points - offsets) / scale)) < 2**31 - 1):
            return np.full(3, scale), offsets
        scale *= 10.0


def exact_decimal_quantization(points: np.ndarray, finest: int = 9) -> tuple[np.ndarray, np.ndarray] | None:
    """(scales, offsets) at the coarsest power of ten 10^-k (k = 0..``finest``) that reproduces every
    coordinate (decoded as laspy does: X * scale + offset) up to float64 rounding (4 ulp), or None.
    Text scans with fixed decimals and E57 files of scaled integers are on such a grid."""
    if not points.size:
        return None
    lo = points.min(axis=0)
    for k in range(finest + 1):
        scale = 10.0 ** -k
        unit = scale * 1000.0
        offsets = np.floor(lo / unit) * unit
        q = np.rint((points - offsets) / scale)
        if not np.all(np.abs(q) < 2**31 - 1):
            return None
        tol = 4 * np.finfo(np.float64).eps * np.maximum(np.abs(points), np.abs(offsets))
        if np.all(np.abs(q * scale + offsets - points) <= tol):
            return np.full(3, scale), offsets
    return None


def _source_quantization_fits(points: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> bool:
    if scales.shape != (3,) or offsets.shape != (3,) or not np.all(scales > 0):
        return False
    q = np.rint((points - offsets) / scales)
    return bool(np.all(np.abs(q) < 2**31 - 1))


def las_layout(
    points: np.ndarray,
    attributes: dict[str, np.ndarray],
    metadata: dict[str, Any] | None = None,
    *,
    point_format: int | None = None,
    version: str | None = None,
) -> LasLayout:
    """Map points + attributes + metadata to what laspy writes, losing nothing without saying so.

    Args:
        points: (N, 3) float64 coordinates.
        attributes: per-point arrays ((N,) or (N, k)).
        metadata: a scan's metadata (``Scan.metadata`` / ``ScanView.format_metadata``): the
            ``las_*`` keys of a LAS source, ``crs_wkt``, and optionally ``point_spacing``.
        point_format, version: a point format (and LAS version) to write instead of the rule below,
            e.g. 6/7/8 and "1.4" for COPC; dimensions of the source that the format lacks become
            extra bytes like any other attribute.

    Rules:
        * **Version and point format.** A LAS source's own (``las_version``/``las_point_format``);
          otherwise LAS 1.4 with point format 6, 7 when red/green/blue are all given, 8 with nir.
        * **Coordinates.** A LAS source's scale and offset when the points fit them in int32 (they
          then come back exactly); else the coarsest power of ten 10^-k (k <= 9) on which every
          coordinate lies exactly (:func:`exact_decimal_quantization`: text with fixed decimals,
          E57 scaled integers); else :func:`choose_quantization`: the power of ten at or below
          spacing / 100 (``metadata["point_spacing"]`` or an estimate), error <= scale / 2 (noted).
        * **Standard fields** (intensity, classification, gps_time, red...) take an attribute of
          the same name when every value fits the field exactly (integers in range; any number for
          gps_time). uint8 colours (red/green/blue/nir) are scaled x 257 into the 16-bit fields
          (255 -> 65535; read back, ``value // 257`` is the source value).
        * **Values that do not fit** a standard field (a float intensity, a negative or too large
          integer) keep their exact values in an extra-bytes dimension ``<name>_<dtype>`` (e.g.
          ``intensity_float32``) whose description is ``"lodbuilder exact <name>"`` (this reader
          restores the attribute under its own name), and the standard field gets a scaled copy for
          viewers: colours in [0, 1] x 65535, colours in [0, 255] x 257, anything else mapped
          linearly from [min(0, min), max] to the field's range.
        * **Other attributes** become extra-bytes dimensions in their own dtype ((N, 2) and (N, 3)
          as array dimensions; wider ones as ``name_0``, ``name_1``...; bool as uint8); a LAS
          source's scaled extra bytes keep their scale and offset. Names longer than 32 bytes are
          cut (noted). A source's extra-bytes description and no-data value are kept where the
          values keep the source's type.
        * **Twin fields.** A change of point-format family (a format 3 source written as 7 for
          COPC) leaves a standard field empty whose values the source holds under another name:
          ``scan_angle`` (formats 6-10, int16 in 0.006 degrees) is filled from ``scan_angle_rank``
          (formats 0-5, int8 degrees) rounded, and the other way round (clipped to int8); the
          source field keeps its exact values in extra bytes like any other attribute (noted).
        * **CRS.** ``crs_wkt`` as a WKT VLR; the global-encoding WKT bit for point formats 6-10
          always (the specification requires it, CRS or not) and for LAS 1.4 files of formats 0-5
          whose source set it. A LAS source's own CRS
          VLRs are copied unchanged for point formats 0-5 (GeoTIFF keys included); for 6-10 only
          the WKT VLR is written. A CRS assigned with ``build --crs`` replaces the source's VLRs.

    Every change is in ``notes`` (one line each), which :func:`write` logs as warnings.
    """
    meta = metadata or {}
    notes: list[str] = []
    n = points.shape[0]
    names = set(attributes)
    from_las = meta.get("las_point_format") is not None
    if point_format is not None:
        fmt = int(point_format)
        version = str(version or ("1.4" if fmt >= 6 else meta.get("las_version") or "1.2"))
    elif from_las:
        fmt, version = int(meta["las_point_format"]), str(version or meta.get("las_version") or "1.4")
    else:
        fmt, version = 6, str(version or "1.4")
        if {"red", "green", "blue"} <= names:
            fmt = 8 if "nir" in names else 7

    scales = np.asarray(meta.get("las_scales") or [], dtype=np.float64)
    offsets = np.asarray(meta.get("las_offsets") or [], dtype=np.float64)
    if not _source_quantization_fits(points, scales, offsets):
        if scales.shape == (3,):
            notes.append("coordinates do not fit the source LAS scale/offset in int32; new ones chosen")
        grid = exact_decimal_quantization(points)
        if grid is not None:
            scales, offsets = grid
        else:
            scales, offsets = choose_quantization(points, meta.get("point_spacing"))
            notes.append(f"coordinates quantised to scale {scales[0]:g} (error <= {scales[0] / 2:g}) with offset "
                         f"{', '.join(f'{o:g}' for o in offsets)}")

    standard = _standard_dims(fmt)
    extra_defs = {d["name"]: d for d in meta.get("las_extra_dims") or []}
    layout = LasLayout(version=version, point_format=fmt, scales=scales, offsets=offsets,
                       system_identifier=str(meta.get("las_system_identifier") or ""))
    used = set(standard)
    for name, arr in attributes.items():
        a = np.asarray(arr)
        if a.shape[:1] != (n,):
            raise InputError(f"attribute {name!r} has shape {a.shape}; expected first dimension {n}")
        if name in standard:
            lo, hi, integer = standard[name]
            if name in _COLOURS and a.dtype == np.uint8:
                layout.dimensions[name] = a.astype(np.uint16) * np.uint16(257)
                notes.append(f"{name}: 8-bit values scaled x 257 into the 16-bit LAS field")
                continue
            if _fits(a, lo, hi, integer):
                layout.dimensions[name] = a
                continue
            exact = f"{name}_{a.dtype.name}"[:32]
            vals, typ = _extra_type(exact, a, notes)
            layout.extra_dims.append(ExtraDim(exact, typ, (EXACT_PREFIX + name)[:32]))
            layout.dimensions[exact] = vals
            used.add(exact)
            if integer and a.ndim == 1 and math.isfinite(hi) and a.dtype.kind in "iuf":
                scaled, how = _scaled_rendition(name, a, hi)
                layout.dimensions[name] = scaled
                notes.append(f"{name}: {a.dtype} values do not fit the LAS field; exact values in extra bytes "
                             f"{exact!r}, the standard field holds a scaled copy ({how})")
            else:
                notes.append(f"{name}: values do not fit the LAS field; exact values in extra bytes {exact!r}, "
                             "the standard field is left 0")
            continue
        _add_extra(layout, name, a, extra_defs, used, notes)

    _fill_twins(layout, attributes, standard, notes)
    _layout_crs(layout, meta, from_las, notes)
    if fmt >= 6:  # LAS 1.4: point formats 6-10 require the WKT bit, with or without a CRS
        layout.wkt_bit = True
    layout.notes = notes
    return layout


def _add_extra(layout: LasLayout, name: str, a: np.ndarray, extra_defs: dict[str, Any],
               used: set[str], notes: list[str]) -> None:
    if a.dtype.kind not in "iufb":
        raise InputError(f"attribute {name!r} has dtype {a.dtype}, which LAS cannot store; convert it to numbers")
    if a.ndim > 2 or (a.ndim == 2 and a.shape[1] > 3):
        flat = a.reshape(a.shape[0], -1)
        notes.append(f"{name}: {flat.shape[1]} values per point written as {name}_0 .. {name}_{flat.shape[1] - 1}")
        for j in range(flat.shape[1]):
            _add_extra(layout, f"{name}_{j}", flat[:, j], extra_defs, used, notes)
        return
    las_name = name[:32]
    if las_name != name:
        notes.append(f"attribute name {name!r} cut to 32 bytes: {las_name!r}")
    if las_name in used:
        raise InputError(f"attribute {name!r} clashes with LAS dimension {las_name!r}; rename it")
    used.add(las_name)
    d = extra_defs.get(name)
    k = a.shape[1] if a.ndim == 2 else 1
    if d is not None and d.get("scales") is not None and a.dtype.kind == "f" and not str(d["type"])[0].isdigit():
        layout.extra_dims.append(ExtraDim(las_name, str(d["type"]), str(d.get("description", "")),
                                          list(d["scales"]), list(d["offsets"]), d.get("no_data")))
        layout.dimensions[las_name] = a
        return
    vals, typ = _extra_type(name, a, notes)
    if a.dtype == np.bool_:
        notes.append(f"{name}: bool written as uint8 extra bytes")
    typ = f"{k}{typ}" if k > 1 else typ
    # the source's no-data value, where the values keep the source's type
    keep = d is not None and d.get("no_data") is not None and str(d["type"]) == typ
    layout.extra_dims.append(ExtraDim(las_name, typ, str((d or {}).get("description", ""))[:32],
                                      no_data=d.get("no_data") if keep and d is not None else None))
    layout.dimensions[las_name] = vals


def _fill_twins(layout: LasLayout, attributes: dict[str, np.ndarray],
                standard: dict[str, tuple[float, float, bool]], notes: list[str]) -> None:
    """Fill a standard field of the layout's format from its twin attribute (see ``_TWINS``)."""
    for name, (twin, factor, how) in _TWINS.items():
        if name not in standard or name in attributes or twin not in attributes:
            continue
        a = np.asarray(attributes[twin])
        if a.ndim != 1 or a.dtype.kind not in "iuf":
            continue
        lo, hi, _ = standard[name]
        v = np.rint(np.nan_to_num(a.astype(np.float64) * factor))
        clipped = int(np.count_nonzero((v < lo) | (v > hi)))
        layout.dimensions[name] = np.clip(v, lo, hi).astype(np.int64)
        what = f"{how}, rounded" + (f"; {clipped} value(s) clipped to [{lo:g}, {hi:g}]" if clipped else "")
        notes.append(f"{name}: filled from {twin} ({what}); {twin} keeps its exact values in extra bytes")


def _layout_crs(layout: LasLayout, meta: dict[str, Any], from_las: bool, notes: list[str]) -> None:
    wkt = meta.get(KEY_WKT)
    layout.crs_wkt = wkt
    raw = [dict(v, data=base64.b64decode(v["data_b64"])) for v in meta.get("las_crs_vlrs") or []]
    own = from_las and meta.get(KEY_SOURCE) != "assigned"
    new_fmt = layout.point_format >= 6
    if own and not new_fmt:
        layout.vlrs = raw  # the source's CRS VLRs, byte for byte
        layout.wkt_bit = bool(meta.get("las_wkt_bit")) and layout.version >= "1.4"
        if wkt and not any(int(v["record_id"]) == _WKT_ID for v in raw) and not any(
            int(v["record_id"]) in _GEOTIFF_IDS for v in raw
        ):
            layout.write_wkt_vlr = True
        return
    if wkt:
        layout.write_wkt_vlr = True
        layout.wkt_bit = new_fmt or layout.version >= "1.4"
        if not new_fmt and layout.version < "1.4":
            geo = _geotiff_vlrs(wkt)
            layout.vlrs = geo
            if not geo:
                notes.append("CRS written as a WKT VLR only: LAS < 1.4 readers may expect GeoTIFF keys")
        return
    geo_raw = [v for v in raw if int(v["record_id"]) in _GEOTIFF_IDS]
    if geo_raw:  # GeoTIFF keys that could not be turned into WKT (no pyproj): keep them
        layout.vlrs = geo_raw
        if new_fmt:
            notes.append("CRS copied as GeoTIFF keys: point formats 6-10 should carry WKT "
                         "(install pyproj to convert: pip install 'lodbuilder[crs]')")


def _geotiff_vlrs(wkt: str) -> list[dict[str, Any]]:
    """GeoTIFF key VLRs for a CRS with an EPSG code (laspy + pyproj), or [] when not possible."""
    try:
        import pyproj
        from laspy.vlrs.geotiff import create_geotiff_projection_vlrs
    except ImportError:
        return []
    try:
        vlrs = create_geotiff_projection_vlrs(pyproj.CRS.from_wkt(wkt))
    except Exception:
        return []
    out = []
    for v in vlrs:
        out.append({"user_id": v.user_id, "record_id": int(v.record_id), "description": str(v.description),
                    "data": bytes(v.record_data_bytes())})
    return out


def check_output(path: Path) -> None:
    """Refuse, before any work, a LAS/LAZ output this installation cannot write (no laspy, or
    no LAZ backend for .laz); see ``registry.writer_for``."""
    _check_laz_backend(_laspy(path), path)


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], metadata: dict[str, Any] | None) -> list[str]:
    """Write through :func:`las_layout` (``check_output`` has run); returns its notes (what was
    changed)."""
    compress = path.suffix.lower() == ".laz"
    layout = las_layout(points, attributes, metadata)
    las = layout.las_data(points)
    with open(path, "wb") as f:
        las.write(f, do_compress=compress)
    return layout.notes
