"""PLY reader and writer (ascii and binary), built on plyfile.

Reading parses the header with plyfile, checks the declared vertex count against the file size
*before* allocating anything, and reads only the ``vertex`` element: elements after it (faces,
``tristrips``, ``range_grid``, ...) are never read. Every vertex property except x/y/z becomes an
attribute in its file dtype (native byte order); coordinates become float64.
"""

from __future__ import annotations

import io
import itertools
import json
import logging
import warnings
from collections.abc import Generator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from ._files import exc_line
from .base import Scan

log = logging.getLogger(__name__)

XYZ = ("x", "y", "z")
#: a header comment carrying the CRS as WKT on one line (``crs_json`` + a JSON string when the
#: WKT has non-ASCII characters, which PLY headers cannot hold)
CRS_COMMENT = "crs "
CRS_JSON_COMMENT = "crs_json "


def crs_comment(wkt: str) -> str:
    return CRS_COMMENT + wkt if wkt.isascii() else CRS_JSON_COMMENT + json.dumps(wkt)


def _comment_crs(comments: list[str]) -> str | None:
    for c in comments:
        if c.startswith(CRS_COMMENT):
            return c[len(CRS_COMMENT):]
        if c.startswith(CRS_JSON_COMMENT):
            try:
                value = json.loads(c[len(CRS_JSON_COMMENT):])
            except ValueError:
                return None
            return value if isinstance(value, str) else None
    return None


def _is_crs_comment(c: str) -> bool:
    return c.startswith((CRS_COMMENT, CRS_JSON_COMMENT))


#: longest header line read whole; longer comment/obj_info lines are cut to this many bytes
LINE_CAP = 4096
#: total bytes of comment/obj_info text kept from one header (the rest is dropped, with a note)
COMMENTS_CAP = 65536
#: most properties a header may declare (all elements): parsing 200,000 took minutes and 3.5 GB
MAX_PROPERTIES = 1024


def _header_bytes(f: Any, path: Path, notes: list[str]) -> bytes:
    """The header up to ``end_header`` with comment/obj_info text capped (:data:`LINE_CAP` bytes a
    line, :data:`COMMENTS_CAP` in all), read line by line with a bounded line length; ``f`` is
    left at the first body byte. A 50 MB comment is skipped in chunks instead of being parsed."""
    out: list[bytes] = []
    kept = 0
    dropped = 0
    properties = 0
    first = True
    while True:
        line = f.readline(LINE_CAP + 1)
        if not line:
            raise FormatError(f"{path}: not a valid PLY header (no end_header line); check that it is a PLY file")
        long_line = len(line) > LINE_CAP and not line.endswith(b"\n")
        if first:
            first = False
            if line.strip() != b"ply":
                raise FormatError(f"{path}: not a valid PLY header (the file does not start with 'ply'); "
                                  "check that it is a PLY file")
        word = line.split(None, 1)[0] if line.strip() else b""
        if word in (b"comment", b"obj_info"):
            total = len(line)
            if long_line:
                line = line[:LINE_CAP]
                while True:  # skip the rest of the line
                    chunk = f.readline(1 << 20)
                    total += len(chunk)
                    if not chunk or chunk.endswith(b"\n"):
                        break
            text = line.rstrip(b"\r\n")
            if kept + len(text) > COMMENTS_CAP:
                dropped += total
                continue
            if long_line:
                dropped += total - len(text)
            kept += len(text)
            out.append(text + b"\n")
            continue
        if long_line:
            raise FormatError(f"{path}: not a valid PLY header (a header line is longer than {LINE_CAP} bytes); "
                              "check that it is a PLY file")
        if word == b"property":
            properties += 1
            if properties > MAX_PROPERTIES:
                raise FormatError(
                    f"{path}: its PLY header declares more than {MAX_PROPERTIES:,} properties; "
                    f"lodbuilder reads at most {MAX_PROPERTIES:,} (a scan has x, y, z and a few "
                    "attributes): check that the header is not damaged"
                )
        out.append(line)
        if line.strip() == b"end_header":
            break
    if dropped:
        notes.append(f"PLY header comments cut: at most {LINE_CAP:,} bytes a line and {COMMENTS_CAP // 1024} KiB "
                     f"in all are kept; {dropped:,} bytes of comment text were not kept")
    return b"".join(out)


def parse_header(f: Any, path: Path, notes: list[str] | None = None) -> Any:
    from plyfile import PlyData, PlyParseError

    head = _header_bytes(f, path, notes if notes is not None else [])
    try:
        return PlyData._parse_header(io.BytesIO(head))
    except PlyParseError as exc:
        raise FormatError(f"{path}: not a valid PLY header ({exc_line(exc)}); check that it is a PLY file") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise FormatError(f"{path}: not a valid PLY header ({exc_line(exc)}); check that it is a PLY file") from None


def has_lists(element: Any) -> bool:
    from plyfile import PlyListProperty

    return any(isinstance(p, PlyListProperty) for p in element.properties)


def header_metadata(header: Any, vertex: Any, notes: list[str]) -> dict[str, Any]:
    from .crs import KEY_WKT, set_crs, to_wkt

    fmt = "ascii" if header.text else {"<": "binary_little_endian", ">": "binary_big_endian"}.get(
        header.byte_order, "binary_little_endian"
    )
    comments = [c for c in header.comments if not _is_crs_comment(c)]
    meta: dict[str, Any] = {
        "ply_format": fmt,
        "comments": comments,
        "obj_info": list(header.obj_info),
        "elements": {e.name: int(e.count) for e in header.elements},
        "vertex_properties": {p.name: str(np.dtype(p.val_dtype).str.lstrip("<>=|")) for p in vertex.properties},
    }
    crs = _comment_crs(header.comments)
    if crs:
        set_crs(meta, to_wkt(crs, what="PLY comment crs"), "file")
    else:
        meta[KEY_WKT] = None
    if notes:
        meta["read_notes"] = list(notes)
    return meta


def read(path: Path) -> list[Scan]:
    size = path.stat().st_size
    notes: list[str] = []
    with open(path, "rb") as f:
        header = parse_header(f, path, notes)
        body_start = f.tell()
        names = [e.name for e in header.elements]
        if "vertex" not in names:
            raise FormatError(f"{path}: PLY has no 'vertex' element (elements: {', '.join(names) or 'none'}); it holds no points")
        vi = names.index("vertex")
        vertex = header.elements[vi]
        prop_names = [p.name for p in vertex.properties]
        missing = [c for c in XYZ if c not in prop_names]
        if missing:
            raise FormatError(
                f"{path}: PLY vertices lack {'/'.join(missing)} (properties: {', '.join(prop_names) or 'none'}); "
                "lodbuilder needs x, y and z"
            )
        count = int(vertex.count)
        before = header.elements[:vi]
        last = vi == len(names) - 1
        if header.text:
            data = _read_ascii(f, path, size, body_start, before, vertex, count, last)
        else:
            data = _read_binary(path, size, body_start, header, vi)
        if data is None:  # a layout the fast paths do not handle: let plyfile read up to the vertices
            f.seek(body_start)
            data = _read_plyfile(f, path, header, vi)
    if not header.text:
        check_byte_order(path, data, header.byte_order)
    scan = _to_scan(path, data, notes)
    scan.metadata = header_metadata(header, vertex, notes)
    for n in notes:
        log.warning("%s: %s", path, n)
    return [scan]


_ORDER_NAMES = {"<": "binary_little_endian", ">": "binary_big_endian", "=": "binary_little_endian"}


def _bad_values(a: np.ndarray) -> int:
    with np.errstate(invalid="ignore", over="ignore"):
        m = np.abs(a.astype(np.float64))
        return int((~np.isfinite(m) | (m > 1e15) | ((m > 0) & (m < 1e-30))).sum())


#: the leading vertices whose coordinates :func:`check_byte_order` looks at
BYTE_ORDER_SAMPLE = 10_000


def check_byte_order(path: Path, data: np.ndarray, byte_order: str) -> None:
    """Refuse a binary PLY whose float coordinates read as garbage in the declared byte order but
    as ordinary numbers in the other one: its header names the wrong byte order."""
    fields = [c for c in XYZ if data.dtype[c].kind == "f"]
    if not fields or data.shape[0] == 0:
        return
    sample = data[: min(data.shape[0], BYTE_ORDER_SAMPLE)]
    bad = sum(_bad_values(sample[c]) for c in fields)
    if bad * 100 <= sample.shape[0] * len(fields):  # at most 1 % odd values: plausibly fine
        return
    swapped = sum(_bad_values(sample[c].byteswap()) for c in fields)
    if swapped == 0:
        declared = _ORDER_NAMES.get(byte_order, byte_order)
        other = "binary_big_endian" if declared == "binary_little_endian" else "binary_little_endian"
        raise FormatError(
            f"{path}: the header says {declared} but the vertex data is {other} ({bad} of "
            f"{sample.shape[0] * len(fields)} coordinates read as NaN, inf or absurd magnitudes, none the "
            f"other way); fix the header line to 'format {other} 1.0'"
        )


def _read_binary(path: Path, size: int, body_start: int, header: Any, vi: int) -> np.ndarray | None:
    """The vertices of a binary PLY whose rows have a fixed size: its chunked read
    (:func:`vertex_rows`) in one chunk; None for list properties (plyfile reads them)."""
    layout = binary_layout(path, size, body_start, header, vi)
    if layout is None:
        return None
    offset, dtype, count = layout
    blocks = [block for _, block in vertex_rows(path, offset, dtype, count, max(count, 1))]
    return blocks[0] if blocks else np.zeros(0, dtype=dtype.newbyteorder("="))


def binary_layout(path: Path, size: int, body_start: int, header: Any, vi: int) -> tuple[int, np.dtype, int] | None:
    """(byte offset, file dtype, count) of the vertex rows of binary PLY element ``vi``, after
    checking that the file holds them (and no more rows when the vertices come last); None when the
    vertices or an element before them have list properties (rows of varying size)."""
    vertex, before, byte_order = header.elements[vi], header.elements[:vi], header.byte_order
    count = int(vertex.count)
    dtype = vertex.dtype(byte_order)
    if has_lists(vertex):
        # lower bound: the scalar part of every vertex
        min_item = sum(np.dtype(p.val_dtype).itemsize if not hasattr(p, "len_dtype") else np.dtype(p.len_dtype).itemsize for p in vertex.properties)
        check_size(path, count, min_item * count, size - body_start)
        return None
    if any(has_lists(e) for e in before):
        check_size(path, count, dtype.itemsize * count, size - body_start)
        return None
    offset = body_start + sum(int(e.count) * e.dtype(byte_order).itemsize for e in before)
    need = dtype.itemsize * count
    check_size(path, count, need, size - offset)
    extra = size - offset - need
    if vi == len(header.elements) - 1 and dtype.itemsize and extra >= dtype.itemsize:  # (a trailing newline is fine)
        raise FormatError(
            f"{path}: PLY header declares {count} vertices but {extra:,} more bytes follow them "
            f"({extra // dtype.itemsize:,} more vertices): {_LONGER}"
        )
    return offset, dtype, count


def vertex_rows(path: Path, offset: int, dtype: np.dtype, count: int, rows: int, first: int = 0,
                stop: int | None = None) -> Generator[tuple[int, np.ndarray], None, None]:
    """The one read of fixed-size binary vertex rows: ``(first row, rows in native byte order)``,
    ``rows`` at a time from row ``first`` to ``stop`` (default: the last), straight from the file."""
    native = dtype.newbyteorder("=")
    stop = count if stop is None else stop
    with open(path, "rb") as f:
        f.seek(offset + first * dtype.itemsize)
        start = first
        while start < stop:
            m = min(rows, stop - start)
            data = np.fromfile(f, dtype=dtype, count=m)
            if data.shape[0] != m:  # the file shrank under us
                raise FormatError(f"{path}: PLY body is truncated: read {start + data.shape[0]} of {count} "
                                  "vertices; re-export the file")
            yield start, data.astype(native, copy=False)
            start += m


_LONGER = ("the vertex count is wrong or the file has trailing data; fix the 'element vertex' "
           "line or re-export the scan")


def check_size(path, count, need, avail):
    if need > avail:
        raise FormatError(
            f"{path}: PLY header declares {count} vertices (>= {need} bytes) but only {max(avail, 0)} bytes follow "
            "the header: the file is truncated or its vertex count is wrong; re-export the scan"
        )


def _read_ascii(f, path, size, body_start, before, vertex, count, last=False):
    nprops = len(vertex.properties)
    # every value takes at least one character and one separator
    check_size(path, count, 2 * nprops * count, size - body_start)
    if has_lists(vertex):
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
    if last and any(line.strip() for line in itertools.islice(f, 1000)):
        raise FormatError(
            f"{path}: PLY header declares {count} vertices but more vertex lines follow them: "
            f"{_LONGER}"
        )
    if count == 0:
        return np.zeros(0, dtype=vertex.dtype("="))
    try:
        table = np.loadtxt(io.BytesIO(b"".join(lines)), dtype=np.float64, ndmin=2, comments=None)
    except ValueError as exc:
        raise FormatError(f"{path}: malformed PLY vertex line ({exc_line(exc)}); re-export the scan") from None
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


def _read_plyfile(f: Any, path: Path, header: Any, vi: int) -> np.ndarray:
    """Read the elements up to the vertices with plyfile (list properties, ascii lists)."""
    from plyfile import PlyParseError

    stream = io.TextIOWrapper(f, "ascii") if header.text else f
    try:
        with warnings.catch_warnings():  # numpy's note on every empty ascii list ("no data")
            warnings.filterwarnings("ignore", message="loadtxt: input contained no data", category=UserWarning)
            for e in header.elements[: vi + 1]:
                e._read(stream, header.text, header.byte_order, False, known_list_len={})
        return np.asarray(header.elements[vi].data)
    except PlyParseError as exc:
        raise FormatError(f"{path}: malformed PLY body ({exc_line(exc)}); re-export the scan") from None
    except (ValueError, EOFError, MemoryError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: malformed PLY body ({exc_line(exc)}); re-export the scan") from None
    finally:
        if header.text:
            stream.detach()


def _list_column(name: str, col: np.ndarray, notes: list[str]) -> np.ndarray | None:
    """A list property as an (N, k) attribute when every vertex has k values (k >= 1); None
    (skipped, with a note) when the lengths differ or every list is empty."""
    lengths = np.fromiter((len(v) for v in col), dtype=np.int64, count=col.shape[0])
    k = int(lengths[0]) if lengths.size else 0
    if lengths.size and k > 0 and np.all(lengths == k):
        return np.ascontiguousarray(np.stack([np.asarray(v) for v in col]))
    if lengths.size:
        notes.append(f"list property {name!r} skipped: its lists have {int(lengths.min())} to "
                     f"{int(lengths.max())} values (only lists of one fixed, non-zero length are kept, "
                     "as an (N, k) attribute)")
    return None


def vertex_points(data: np.ndarray) -> np.ndarray:
    """The float64 (N, 3) coordinates of vertex rows."""
    pts = np.empty((data.shape[0], 3), dtype=np.float64)
    for j, c in enumerate(XYZ):
        pts[:, j] = data[c]
    return pts


def _to_scan(path: Path, data: np.ndarray, notes: list[str]) -> Scan:
    pts = vertex_points(data)
    attrs: dict[str, np.ndarray] = {}
    for name in data.dtype.names or ():
        if name in XYZ:
            continue
        col = data[name]
        if col.dtype == object:  # a list property
            arr = _list_column(name, col, notes)
            if arr is not None:
                attrs[name] = arr.astype(arr.dtype.newbyteorder("="), copy=False)
        else:
            attrs[name] = np.ascontiguousarray(col, dtype=col.dtype.newbyteorder("="))
    return Scan(points=pts, attributes=attrs, name=path.stem, source=str(path), reader="ply")


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


def coord_dtype(points: np.ndarray, metadata: dict[str, Any] | None) -> np.dtype:
    """float32 when the source stored float32 and the values survive the round trip, else float64."""
    props = (metadata or {}).get("vertex_properties") or {}
    if props.get("x") == "f4" and points.size:
        p32 = points.astype(np.float32)
        if np.array_equal(p32.astype(np.float64), points):
            return np.dtype("f4")
    return np.dtype("f8")


def columns(attributes: dict[str, np.ndarray], notes: list[str] | None = None) -> list[tuple[str, np.ndarray]]:
    """Flatten attributes to 1-D columns: an (N, k) attribute becomes ``name_0`` ... ``name_{k-1}``
    (noted in ``notes`` when given)."""
    out: list[tuple[str, np.ndarray]] = []
    for name, arr in attributes.items():
        a = np.asarray(arr)
        if a.ndim == 1:
            out.append((name, a))
        else:
            flat = a.reshape(a.shape[0], -1)
            out.extend((f"{name}_{j}", flat[:, j]) for j in range(flat.shape[1]))
            if notes is not None:
                notes.append(f"{name}: {flat.shape[1]} values per point written as {name}_0 .. {name}_{flat.shape[1] - 1}")
    return out


#: PLY property order after x, y, z: normals, colours, then the rest in their given order
STANDARD_ORDER = ("nx", "ny", "nz", "red", "green", "blue", "alpha")
_COLOUR_NAMES = ("red", "green", "blue", "alpha")


def ordered_columns(attributes: dict[str, np.ndarray], notes: list[str] | None = None) -> list[tuple[str, np.ndarray]]:
    """:func:`columns` with nx ny nz, red green blue alpha first (those present), then the rest."""
    cols = columns(attributes, notes)
    rank = {n: i for i, n in enumerate(STANDARD_ORDER)}
    first = sorted((c for c in cols if c[0] in rank), key=lambda c: rank[c[0]])
    return first + [c for c in cols if c[0] not in rank]


def _ply_name_ok(name: str) -> bool:
    return bool(name) and all(33 <= ord(c) <= 126 for c in name)


def ply_names(cols: list[tuple[str, Any]], notes: list[str]) -> list[tuple[str, Any]]:
    """``cols`` with every name PLY cannot hold (spaces, characters outside printable ASCII, an
    empty name) renamed: each such character becomes ``_`` and a name already taken gets ``_2``,
    ``_3``... (noted)."""
    taken = set(XYZ) | {n for n, _ in cols if _ply_name_ok(n)}
    out = []
    for name, a in cols:
        if _ply_name_ok(name):
            out.append((name, a))
            continue
        base = "".join(c if 33 <= ord(c) <= 126 else "_" for c in name) or "attribute"
        new, k = base, 1
        while new in taken:
            k += 1
            new = f"{base}_{k}"
        taken.add(new)
        notes.append(f"attribute {name!r} written as {new!r}: PLY property names are printable "
                     "ASCII without spaces")
        out.append((new, a))
    return out


def colour_column(name: str, a: np.ndarray, depth: int, notes: list[str]) -> np.ndarray:
    """A colour column as uchar (``depth`` 8) or ushort (16). 8-bit -> 16-bit multiplies by 257;
    16-bit values all <= 255 (8-bit colours in 16-bit fields, common in LAS) cast unchanged;
    other 16-bit values divide by 257 (rounded, noted). Non-integer colours are left alone."""
    if a.dtype.kind not in "iub":
        return a
    hi = int(a.max()) if a.size else 0
    lo = int(a.min()) if a.size else 0
    if depth == 16:
        if a.dtype.itemsize == 1 and a.dtype.kind in "ub":
            notes.append(f"{name}: 8-bit values scaled x 257 to 16 bit")
            return a.astype(np.uint16) * np.uint16(257)
        if lo >= 0 and hi <= 65535:
            return a.astype(np.uint16)
        return a
    if lo >= 0 and hi <= 255:
        return a.astype(np.uint8)
    if lo >= 0 and hi <= 65535:
        notes.append(f"{name}: 16-bit values divided by 257 to uchar (use colour depth 16 to keep them)")
        return np.rint(a.astype(np.float64) / 257.0).astype(np.uint8)
    return a


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], metadata: dict[str, Any] | None) -> list[str]:
    """Binary little-endian PLY: x y z, nx ny nz, red green blue alpha, then the other attributes;
    colours uchar by default (``metadata["write_colour_depth"] = 16`` keeps 16 bit); the CRS as a
    ``comment crs <WKT>`` line. Returns the notes of what was changed."""
    from plyfile import PlyData, PlyElement

    meta = metadata or {}
    notes: list[str] = []
    depth = int(meta.get("write_colour_depth") or 8)
    cdt = coord_dtype(points, metadata)
    cols = [(n, colour_column(n, np.asarray(a), depth, notes) if n in _COLOUR_NAMES else a)
            for n, a in ordered_columns(attributes, notes)]
    cols = ply_names(cols, notes)
    fields = [(c, cdt) for c in XYZ] + [(n, _ply_dtype(a, n)) for n, a in cols]
    data = np.empty(points.shape[0], dtype=fields)
    for j, c in enumerate(XYZ):
        data[c] = points[:, j]
    for n, a in cols:
        data[n] = a
        if np.asarray(a).dtype.kind == "i" and data.dtype[n].kind == "f" and np.asarray(a).dtype.itemsize == 8:
            notes.append(f"{n}: int64 values beyond 32 bits written as float64 (PLY has no 64-bit integers)")
    comments = ["written by lodbuilder"]
    for c in meta.get("comments", []) or []:
        if isinstance(c, str) and "\n" not in c and c not in comments and not _is_crs_comment(c) and c.isascii():
            comments.append(c)
    wkt = meta.get("crs_wkt")
    if wkt:
        comments.append(crs_comment(str(wkt)))
    el = PlyElement.describe(data, "vertex")
    with open(path, "wb") as f:
        PlyData([el], text=False, byte_order="<", comments=comments).write(f)
    return notes
