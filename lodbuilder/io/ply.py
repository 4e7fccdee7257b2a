"""PLY reader and writer (ascii and binary), built on plyfile.

Reading parses the header with plyfile, checks the declared vertex count against the file size
*before* allocating anything, and reads only the ``vertex`` element: elements after it (faces,
``tristrips``, ``range_grid``, ...) are never read. Every vertex property except x/y/z becomes an
attribute in its file dtype (native byte order); coordinates become float64.
"""

from __future__ import annotations

import io
import itertools
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from .base import Scan

log = logging.getLogger(__name__)

_XYZ = ("x", "y", "z")


def _parse_header(f: Any, path: Path) -> Any:
    from plyfile import PlyData, PlyParseError

    try:
        return PlyData._parse_header(f)
    except PlyParseError as exc:
        raise FormatError(f"{path}: not a valid PLY header ({_one_line(exc)}); check that it is a PLY file") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise FormatError(f"{path}: not a valid PLY header ({_one_line(exc)}); check that it is a PLY file") from None


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def _has_lists(element: Any) -> bool:
    from plyfile import PlyListProperty

    return any(isinstance(p, PlyListProperty) for p in element.properties)


def _metadata(header: Any, vertex: Any) -> dict[str, Any]:
    fmt = "ascii" if header.text else {"<": "binary_little_endian", ">": "binary_big_endian"}.get(
        header.byte_order, "binary_little_endian"
    )
    return {
        "ply_format": fmt,
        "comments": list(header.comments),
        "obj_info": list(header.obj_info),
        "elements": {e.name: int(e.count) for e in header.elements},
        "vertex_properties": {p.name: str(np.dtype(p.val_dtype).str.lstrip("<>=|")) for p in vertex.properties},
    }


def read(path: Path) -> list[Scan]:
    size = path.stat().st_size
    with open(path, "rb") as f:
        header = _parse_header(f, path)
        body_start = f.tell()
        names = [e.name for e in header.elements]
        if "vertex" not in names:
            raise FormatError(f"{path}: PLY has no 'vertex' element (elements: {', '.join(names) or 'none'}); it holds no points")
        vi = names.index("vertex")
        vertex = header.elements[vi]
        prop_names = [p.name for p in vertex.properties]
        missing = [c for c in _XYZ if c not in prop_names]
        if missing:
            raise FormatError(
                f"{path}: PLY vertices lack {'/'.join(missing)} (properties: {', '.join(prop_names) or 'none'}); "
                "lodbuilder needs x, y and z"
            )
        count = int(vertex.count)
        before = header.elements[:vi]
        if header.text:
            data = _read_ascii(f, path, size, body_start, before, vertex, count)
        else:
            data = _read_binary(f, path, size, body_start, before, vertex, count, header.byte_order)
    if data is None:  # a layout the fast paths do not handle: let plyfile read everything
        data = _read_plyfile(path)
    return [_to_scan(path, data, _metadata(header, vertex))]


def _read_binary(f, path, size, body_start, before, vertex, count, byte_order):
    dtype = vertex.dtype(byte_order)
    if _has_lists(vertex):
        # lower bound: the scalar part of every vertex
        min_item = sum(np.dtype(p.val_dtype).itemsize if not hasattr(p, "len_dtype") else np.dtype(p.len_dtype).itemsize for p in vertex.properties)
        _check_size(path, count, min_item * count, size - body_start)
        return None
    if any(_has_lists(e) for e in before):
        _check_size(path, count, dtype.itemsize * count, size - body_start)
        return None
    offset = body_start + sum(int(e.count) * e.dtype(byte_order).itemsize for e in before)
    need = dtype.itemsize * count
    _check_size(path, count, need, size - offset)
    f.seek(offset)
    data = np.fromfile(f, dtype=dtype, count=count)
    if data.shape[0] != count:  # the file shrank under us
        raise FormatError(f"{path}: PLY body is truncated: read {data.shape[0]} of {count} vertices; re-export the file")
    return data.astype(vertex.dtype("="), copy=False)


def _check_size(path, count, need, avail):
    if need > avail:
        raise FormatError(
            f"{path}: PLY header declares {count} vertices (>= {need} bytes) but only {max(avail, 0)} bytes follow "
            "the header: the file is truncated or its vertex count is wrong; re-export the scan"
        )


def _read_ascii(f, path, size, body_start, before, vertex, count):
    nprops = len(vertex.properties)
    # every value takes at least one character and one separator
    _check_size(path, count, 2 * nprops * count, size - body_start)
    if _has_lists(vertex):
        return None
    for e in before:  # ascii PLY: one line per element instance
        skipped = sum(1 for _ in itertools.islice(f, int(e.count)))
        if skipped < e.count:
            raise FormatError(f"{path}: PLY body is truncated inside element '{e.name}'; re-export the scan")
    lines = list(itertools.islice(f, count))
    if len(lines) < count:
        raise FormatError(
            f"{path}: PLY header declares {count} vertices but the file holds only {len(lines)} vertex lines: "
            "the file is truncated or its vertex count is wrong; re-export the scan"
        )
    if count == 0:
        return np.zeros(0, dtype=vertex.dtype("="))
    try:
        table = np.loadtxt(io.BytesIO(b"".join(lines)), dtype=np.float64, ndmin=2, comments=None)
    except ValueError as exc:
        raise FormatError(f"{path}: malformed PLY vertex line ({_one_line(exc)}); re-export the scan") from None
    if table.shape != (count, nprops):
        raise FormatError(
            f"{path}: PLY vertex lines hold {table.shape[1]} values each, the header declares {nprops}; re-export the scan"
        )
    out = np.empty(count, dtype=vertex.dtype("="))
    for j, p in enumerate(vertex.properties):
        out[p.name] = _fit(path, p.name, table[:, j], out.dtype[p.name])
    return out


def _fit(path: Path, name: str, col: np.ndarray, dt: np.dtype) -> np.ndarray:
    """``col`` cast to the property's type; a value the type cannot hold (a float beyond float32,
    a fraction, negative or too large a number for an integer type) is an error, never a silent
    inf or wrapped integer."""
    with np.errstate(over="ignore", invalid="ignore"):
        cast = col.astype(dt)
    if dt.kind == "f":
        bad = np.isfinite(col) & ~np.isfinite(cast)
    else:
        info = np.iinfo(dt)
        bad = ~((col >= info.min) & (col <= info.max) & (col == np.floor(col)))
    if bad.any():
        i = int(np.argmax(bad))
        raise FormatError(
            f"{path}: PLY vertex {i} has {name} = {float(col[i])!r}, which its type {dt.name} cannot "
            "hold; re-export the scan"
        )
    return cast


def _read_plyfile(path: Path) -> np.ndarray:
    from plyfile import PlyData, PlyParseError

    try:
        ply = PlyData.read(str(path), mmap=False)
        return np.asarray(ply["vertex"].data)
    except PlyParseError as exc:
        raise FormatError(f"{path}: malformed PLY body ({_one_line(exc)}); re-export the scan") from None
    except (ValueError, EOFError, MemoryError) as exc:
        raise FormatError(f"{path}: malformed PLY body ({_one_line(exc)}); re-export the scan") from None


def _to_scan(path: Path, data: np.ndarray, metadata: dict[str, Any]) -> Scan:
    pts = np.empty((data.shape[0], 3), dtype=np.float64)
    for j, c in enumerate(_XYZ):
        pts[:, j] = data[c]
    attrs: dict[str, np.ndarray] = {}
    for name in data.dtype.names or ():
        if name in _XYZ:
            continue
        col = data[name]
        if col.dtype == object:  # a list property: keep as an object array of per-vertex arrays
            attrs[name] = col.copy()
        else:
            attrs[name] = np.ascontiguousarray(col, dtype=col.dtype.newbyteorder("="))
    return Scan(points=pts, attributes=attrs, name=path.stem, source=str(path), reader="ply", metadata=metadata)


# ---------------------------------------------------------------------------------------- writer

_PLY_TYPES = {"i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8"}


def _ply_dtype(arr: np.ndarray, name: str) -> np.dtype:
    dt = arr.dtype
    if dt == np.bool_:
        return np.dtype("u1")
    key = dt.str.lstrip("<>=|")
    if key in _PLY_TYPES:
        return np.dtype(key)
    if dt.kind in "iu":  # 64-bit integers: PLY has no 64-bit integer type
        lo, hi = (int(arr.min()), int(arr.max())) if arr.size else (0, 0)
        for cand in ("u4", "i4") if lo >= 0 else ("i4",):
            info = np.iinfo(cand)
            if info.min <= lo and hi <= info.max:
                return np.dtype(cand)
        return np.dtype("f8")
    if dt.kind == "f":
        return np.dtype("f8")
    from ..errors import InputError

    raise InputError(f"attribute {name!r} has dtype {dt}, which PLY cannot store; convert it to a number type")


def _coord_dtype(points: np.ndarray, metadata: dict[str, Any] | None) -> np.dtype:
    """float32 when the source stored float32 and the values survive the round trip, else float64."""
    props = (metadata or {}).get("vertex_properties") or {}
    if props.get("x") == "f4" and points.size:
        p32 = points.astype(np.float32)
        if np.array_equal(p32.astype(np.float64), points):
            return np.dtype("f4")
    return np.dtype("f8")


def columns(attributes: dict[str, np.ndarray]) -> list[tuple[str, np.ndarray]]:
    """Flatten attributes to 1-D columns: an (N, k) attribute becomes ``name_0`` ... ``name_{k-1}``."""
    out: list[tuple[str, np.ndarray]] = []
    for name, arr in attributes.items():
        a = np.asarray(arr)
        if a.ndim == 1:
            out.append((name, a))
        else:
            flat = a.reshape(a.shape[0], -1)
            out.extend((f"{name}_{j}", flat[:, j]) for j in range(flat.shape[1]))
    return out


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], metadata: dict[str, Any] | None) -> None:
    from plyfile import PlyData, PlyElement

    cdt = _coord_dtype(points, metadata)
    cols = columns(attributes)
    fields = [(c, cdt) for c in _XYZ] + [(n, _ply_dtype(a, n)) for n, a in cols]
    data = np.empty(points.shape[0], dtype=fields)
    for j, c in enumerate(_XYZ):
        data[c] = points[:, j]
    for n, a in cols:
        data[n] = a
    comments = ["written by lodbuilder"]
    for c in (metadata or {}).get("comments", []) or []:
        if isinstance(c, str) and "\n" not in c and c not in comments:
            comments.append(c)
    el = PlyElement.describe(data, "vertex")
    with open(path, "wb") as f:
        PlyData([el], text=False, byte_order="<", comments=comments).write(f)
