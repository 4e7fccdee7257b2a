"""E57 reader, built on pye57 (``pip install lodbuilder[e57]``).

An E57 file may hold several scans (``data3D`` entries): :func:`read` returns one Scan per scan,
named after the file (one scan) or the scan's E57 ``name`` (several scans; made unique), with its pose (rotation
quaternion + translation, world = R p + t) applied. Spherical scans are converted to Cartesian.
Points whose ``cartesianInvalidState`` (or ``sphericalInvalidState``) is non-zero are dropped; the
count is logged and kept in ``metadata["invalid_dropped"]``. Every other point field becomes an
attribute; ``colorRed/Green/Blue`` are renamed ``red/green/blue`` like the other formats. The root
``coordinateMetadata`` string, when not empty, is the CRS (see :mod:`lodbuilder.io.crs`).

An E57 file does not stream: pye57 reads a scan's points whole (``read_scan_raw``), so this reader
is the one path, and :func:`lodbuilder.io.stream.open_stream` hands its scan out in chunks.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np

from .base import Scan
from .crs import set_crs, to_wkt

log = logging.getLogger(__name__)

_RENAME = {"colorRed": "red", "colorGreen": "green", "colorBlue": "blue"}
_COORDS = {"cartesianX", "cartesianY", "cartesianZ", "sphericalRange", "sphericalAzimuth", "sphericalElevation"}
_STATES = ("cartesianInvalidState", "sphericalInvalidState")


def _pye57(path: Path) -> Any:
    from .._optional import require

    return require("pye57", f"{path}: E57")


def _scan_name(header: Any, default: str) -> str:
    try:
        name = str(header.node["name"].value()).strip()
    except Exception:
        name = ""
    name = re.sub(r"[^\w.\-]+", "_", name).strip("._")
    return name or default


def _coordinate_metadata(e57: Any, path: Path) -> str | None:
    """The root ``coordinateMetadata`` string (the file's CRS, e.g. WKT) as WKT, or None."""
    try:
        text = e57.root["coordinateMetadata"].value()
    except Exception:  # absent (it is optional) or not a string
        return None
    return to_wkt(text, what=f"{path} coordinateMetadata")


def declared_crs(path: Path) -> str | None:
    """The file's CRS (its root ``coordinateMetadata``) without reading any scan."""
    e57 = _pye57(path).E57(str(path), mode="r")
    try:
        return _coordinate_metadata(e57, path)
    finally:
        e57.close()


def read(path: Path) -> list[Scan]:
    pye57 = _pye57(path)
    e57 = pye57.E57(str(path), mode="r")
    try:
        scans: list[Scan] = []
        used: set[str] = set()
        count = e57.scan_count
        wkt = _coordinate_metadata(e57, path)
        for i in range(count):
            scan = _read_one(e57, i, path, count, used)
            set_crs(scan.metadata, wkt, "file")
            scans.append(scan)
        return scans
    finally:
        e57.close()


def _read_one(e57: Any, index: int, path: Path, count: int, used: set[str]) -> Scan:
    header = e57.get_header(index)
    data = e57.read_scan_raw(index, ignore_unsupported_fields=True)
    n = int(header.point_count)
    valid = np.ones(n, dtype=bool)
    for st in _STATES:
        if st in data:
            valid &= np.asarray(data[st]) == 0
    if "cartesianX" in data:
        local = np.stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]], axis=1).astype(np.float64)
        system = "cartesian"
    else:
        r = np.asarray(data["sphericalRange"], dtype=np.float64)
        az = np.asarray(data["sphericalAzimuth"], dtype=np.float64)
        el = np.asarray(data["sphericalElevation"], dtype=np.float64)
        local = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
        system = "spherical"
    dropped = int(n - valid.sum())
    local = local[valid]
    rot = np.asarray(header.rotation_matrix, dtype=np.float64)
    trans = np.asarray(header.translation, dtype=np.float64).reshape(3)
    has_pose = bool(header.has_pose())
    pts = local @ rot.T + trans if has_pose else local
    attrs = {
        _RENAME.get(k, k): np.ascontiguousarray(np.asarray(v)[valid])
        for k, v in data.items()
        if k not in _COORDS and k not in _STATES
    }
    # a file with one scan is named like any other file (its stem); several scans keep their E57 names
    name = path.stem if count == 1 else _scan_name(header, f"{path.stem}_{index}")
    base, j = name, 1
    while name in used:
        j += 1
        name = f"{base}_{j}"
    used.add(name)
    if dropped:
        log.warning("%s: scan %s: dropped %d point(s) flagged invalid", path, name, dropped)
    meta = {
        "e57_scan_index": index,
        "e57_scan_count": count,
        "e57_scan_name": _scan_name(header, ""),
        "e57_coordinate_system": system,
        "e57_pose_rotation": [float(x) for x in np.asarray(header.rotation).reshape(-1)] if has_pose else [1.0, 0.0, 0.0, 0.0],
        "e57_pose_translation": [float(x) for x in trans] if has_pose else [0.0, 0.0, 0.0],
        "invalid_dropped": dropped,
    }
    return Scan(points=np.ascontiguousarray(pts), attributes=attrs, name=name, source=str(path), reader="e57", metadata=meta)
