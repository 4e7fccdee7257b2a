"""The one mapping from points + attributes + metadata to what laspy writes (LAS, LAZ and COPC):
point format, fields and extra bytes, colours, coordinate scale, CRS; every change noted.

The rules of :func:`las_layout`:

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
"""

from __future__ import annotations

import base64
import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...errors import InputError
from .._files import exc_line
from ..crs import KEY_SOURCE, KEY_WKT
from .common import EXACT_PREFIX, laspy_module

log = logging.getLogger(__name__)


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
        laspy = laspy_module("LAS output")
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
        laspy = laspy_module("LAS output")
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
    laspy = laspy_module("LAS output")
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

    The rules (version and point format, coordinates, standard fields, values that do not fit,
    other attributes, twin fields, CRS) are in this module's docstring.

    Every change is in ``notes`` (one line each), which :func:`write` logs as warnings.
    """
    meta = metadata or {}
    notes: list[str] = []
    n = points.shape[0]
    from_las = meta.get("las_point_format") is not None
    fmt, version = _format_and_version(point_format, version, meta, set(attributes))
    scales, offsets = _coordinate_grid(points, meta, notes)
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
            _add_standard(layout, name, a, standard[name], used, notes)
        else:
            _add_extra(layout, name, a, extra_defs, used, notes)

    _fill_twins(layout, attributes, standard, notes)
    _layout_crs(layout, meta, from_las, notes)
    if fmt >= 6:  # LAS 1.4: point formats 6-10 require the WKT bit, with or without a CRS
        layout.wkt_bit = True
    layout.notes = notes
    return layout


def _format_and_version(point_format: int | None, version: str | None, meta: dict[str, Any],
                        names: set[str]) -> tuple[int, str]:
    """The point format and LAS version to write: the ones asked, else a LAS source's, else 1.4
    with format 6 (7 with red/green/blue, 8 with nir too)."""
    if point_format is not None:
        fmt = int(point_format)
        return fmt, str(version or ("1.4" if fmt >= 6 else meta.get("las_version") or "1.2"))
    if meta.get("las_point_format") is not None:
        return int(meta["las_point_format"]), str(version or meta.get("las_version") or "1.4")
    if {"red", "green", "blue"} <= names:
        return (8 if "nir" in names else 7), str(version or "1.4")
    return 6, str(version or "1.4")


def _coordinate_grid(points: np.ndarray, meta: dict[str, Any], notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(scales, offsets): the source's when the points fit them, else an exact decimal grid, else
    :func:`choose_quantization` (noted)."""
    scales = np.asarray(meta.get("las_scales") or [], dtype=np.float64)
    offsets = np.asarray(meta.get("las_offsets") or [], dtype=np.float64)
    if _source_quantization_fits(points, scales, offsets):
        return scales, offsets
    if scales.shape == (3,):
        notes.append("coordinates do not fit the source LAS scale/offset in int32; new ones chosen")
    grid = exact_decimal_quantization(points)
    if grid is not None:
        return grid
    scales, offsets = choose_quantization(points, meta.get("point_spacing"))
    notes.append(f"coordinates quantised to scale {scales[0]:g} (error <= {scales[0] / 2:g}) with offset "
                 f"{', '.join(f'{o:g}' for o in offsets)}")
    return scales, offsets


def _add_standard(layout: LasLayout, name: str, a: np.ndarray, limits: tuple[float, float, bool],
                  used: set[str], notes: list[str]) -> None:
    """Attribute ``name`` into its standard field (x 257 for 8-bit colours) when it fits; else its
    exact values into extra bytes and a scaled copy (or 0) into the field (noted)."""
    lo, hi, integer = limits
    if name in _COLOURS and a.dtype == np.uint8:
        layout.dimensions[name] = a.astype(np.uint16) * np.uint16(257)
        notes.append(f"{name}: 8-bit values scaled x 257 into the 16-bit LAS field")
        return
    if _fits(a, lo, hi, integer):
        layout.dimensions[name] = a
        return
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
