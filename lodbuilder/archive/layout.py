"""The archive layout: every group, dataset and attribute name, in one place.

The writer, the reader, the validator and the JSON Schema (:mod:`lodbuilder.archive.schema`) all
take their names from here. An archive is the HDF5 file the user names (``NAME.h5``) and, once it
holds more than one scan, the directory ``NAME.h5.scans/`` beside it with one *part* file per scan::

    /                          attrs: format="lodbuilder", schema_version, lodbuilder_version,
                                      created_utc, modified_utc
    /index/                    attrs: n_scans; one row per scan, in name order:
        name                   (S,) fixed-length UTF-8 scan names
        n_points               (S,) int64
        bounds_min, bounds_max (S, 3) float64
        part                   (S,) fixed-length ASCII: the part file in NAME.h5.scans/ holding the
                                    scan, or "" when the scan is stored in this file (/scans/<name>)
        part_bytes             (S,) int64: size of that part file (0 for a scan stored here)
    /scans/<name>/             attrs: n_points, n_ordered, coordinate_encoding, bounds_min,
                                      bounds_max, radius_index_step, build (JSON),
                                      provenance (JSON), format_metadata (JSON), stop_radius
        points                 (N, 3) float64 | float32 | int32 | int64 (+ attrs offset, scale)
        source_index           (N,) int64: input index of each stored point
        radius                 (N,) float64: insertion radii, non-increasing; inf for seeds
        parent                 (N,) int64: stored position of the parent, -1 for roots
        radius_index           (ceil(N / step),) float64: radius[::step], to find a rho level
                                                   without reading the whole radius array
        seeds                  (S,) int64: input indices that started the ordering
        attributes/<prop>      (N,) or (N, k), the input's dtype, same order as points
        importance/<map>       (N,) float32, attrs: parameters (JSON)
        orderings/<name>/      attrs: parameters (JSON), n_ordered
            order              (K,) int64: positions into the stored points
            radius             (K,) float64
            parent             (K,) int64: position in this ordering, -1 for roots

A part file is itself an archive holding its scan under /scans/<name> (so one part, or a
single-scan archive, is self-contained). The stored order *is* the default (uniform) farthest
point ordering, so a level is a prefix. Stored points beyond ``n_ordered`` (points left out of the
ordering, e.g. outliers) come last with radius 0 and parent -1.

``stop_radius`` is the covering bound of the whole ordered prefix: 0 when every point the ordering
was built on is ordered, else (a build stopped by ``size`` or ``rho``) the distance of the next
candidate when it stopped, an upper bound of the distance from every unordered point (outliers
excepted: they are left out of the ordering by design) to the ordered ones. Archives written
before it existed lack it: a reader takes 0 when ``n_ordered == n_points`` and inf (no bound
known) otherwise (:func:`stop_radius_of`).

Storage: files are written with HDF5 paged aggregation (all metadata in the first page(s)); the
per-point datasets of a scan share one chunk length and are written in *row groups* (the chunks of
rows [i R, (i+1) R) of points, source_index, radius, parent and every attribute next to each other),
so the prefix of a scan, a level, is one contiguous byte range. Every dataset is chunked along its
first axis and carries a fletcher32 checksum; compression (shuffle + gzip) is used where it pays.
"""

from __future__ import annotations

import json
import math
import re
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError

FORMAT = "lodbuilder"
SCHEMA_VERSION = 2

# root
A_FORMAT = "format"
A_SCHEMA_VERSION = "schema_version"
A_VERSION = "lodbuilder_version"
A_CREATED = "created_utc"
A_MODIFIED = "modified_utc"

# groups
G_SCANS = "scans"
G_INDEX = "index"
G_ATTRIBUTES = "attributes"
G_IMPORTANCE = "importance"
G_ORDERINGS = "orderings"

# index datasets
I_NAME = "name"
I_N_POINTS = "n_points"
I_BOUNDS_MIN = "bounds_min"
I_BOUNDS_MAX = "bounds_max"
I_PART = "part"
I_PART_BYTES = "part_bytes"
A_N_SCANS = "n_scans"

# parts: NAME.h5.scans/<stem>-<16 hex digits>.h5, written by lodbuilder only
PARTS_SUFFIX = ".scans"
PART_NAME = re.compile(r"[A-Za-z0-9_]{0,48}-[0-9a-f]{16}\.h5")

# scan datasets
D_POINTS = "points"
D_SOURCE_INDEX = "source_index"
D_RADIUS = "radius"
D_PARENT = "parent"
D_RADIUS_INDEX = "radius_index"
D_SEEDS = "seeds"
D_ORDER = "order"

# scan attributes
S_N_POINTS = "n_points"
S_N_ORDERED = "n_ordered"
S_ENCODING = "coordinate_encoding"
S_BOUNDS_MIN = "bounds_min"
S_BOUNDS_MAX = "bounds_max"
S_RADIUS_STEP = "radius_index_step"
S_BUILD = "build"
S_PROVENANCE = "provenance"
S_FORMAT_METADATA = "format_metadata"
S_STOP_RADIUS = "stop_radius"
P_OFFSET = "offset"
P_SCALE = "scale"
M_PARAMETERS = "parameters"

ENCODINGS = ("float64", "float32", "int32", "int64")
RADIUS_INDEX_STEP = 1024
CHUNK_ROWS = 65536
# row groups: the per-point datasets of a scan share one chunk length, between these bounds and
# with at most ROW_GROUPS_MAX chunks per dataset (a small chunk index, all in the first page)
ROW_GROUP_MIN = 8192
ROW_GROUPS_MAX = 1024
# paged aggregation (see page_size)
PAGE_MIN = 4096
PAGE_BIG_MIN = 1 << 16
PAGE_MAX = 1 << 20
SMALL_FILE_PAGES = 32
GZIP_LEVEL = 1  # (level 4: 1.1 % smaller per-point datasets of an airborne survey, their deflate 1.3-1.4 x slower)
# small datasets (index columns, radius_index, seeds) up to this size are stored compact
COMPACT_MAX = 16384
COMPRESS_BELOW = 0.6
LIBVER = ("v110", "latest")

_FORBIDDEN_NAME_CHARS = set("/\\\x00")


def stop_radius_of(value: Any, n_points: int, n_ordered: int) -> float:
    """The ``stop_radius`` attribute's value (``None`` when absent), as a float: a missing one is
    0 for a complete ordering and inf (no bound known) for a partial one."""
    if value is None:
        return 0.0 if n_ordered >= n_points else math.inf
    return float(np.asarray(value, dtype=np.float64).reshape(-1)[0])


def check_name(name: Any, what: str = "scan name") -> str:
    """Return ``name`` if it is usable as an HDF5 member name (no path separators)."""
    if not isinstance(name, str) or not name or not name.strip():
        raise InputError(f"{what} must be a non-empty string, got {name!r}")
    bad = sorted(_FORBIDDEN_NAME_CHARS & set(name))
    if bad or name in (".", "..") or name.startswith(".") or len(name.encode()) > 255:
        raise InputError(
            f"{what} {name!r} is not allowed: use at most 255 bytes, no '/', '\\' or NUL, "
            "and do not start with '.'"
        )
    return name


@dataclass(frozen=True)
class IndexRow:
    """One row of an archive's /index: a scan, its size and bounds, and where its data is."""

    name: str
    n_points: int
    bounds_min: tuple[float, ...]
    bounds_max: tuple[float, ...]
    part: str = ""  # file name in NAME.h5.scans/, "" when the scan is in the index file itself
    part_bytes: int = 0


def part_file_name(scan: str, token: str) -> str:
    """File name of a new part holding ``scan`` (``token``: 16 hex digits)."""
    stem = re.sub(r"[^A-Za-z0-9_]", "_", scan)[:48]
    name = f"{stem}-{token}.h5"
    assert PART_NAME.fullmatch(name), name
    return name


def parts_dir_name(archive_name: str) -> str:
    """The directory beside ``archive_name`` that holds its parts: ``NAME.h5.scans``."""
    return archive_name + PARTS_SUFFIX


def to_json(value: Any) -> str:
    """JSON text of ``value`` (sorted keys) by lodbuilder's one convention (:mod:`lodbuilder._json`:
    NumPy values converted, non-finite floats as strings)."""
    from .._json import dumps

    return dumps(value, sort_keys=True)


def from_json(text: Any) -> Any:
    if isinstance(text, bytes):
        text = text.decode()
    if text is None or text == "":
        return {}
    return json.loads(text)


# ---------------------------------------------------------------------------------------------
# coordinates


def choose_encoding(encodings: set[str]) -> str:
    """One coordinate encoding for every block of a scan written in blocks: the one all chunks share, else the widest."""
    if len(encodings) == 1:
        return next(iter(encodings))
    if encodings <= {"int32", "int64"}:
        return "int64"
    return "float64"


def encode_points(points: np.ndarray, metadata: dict[str, Any] | None = None):
    """Choose the smallest lossless storage of ``points``.

    Returns ``(stored_array, encoding, offset, scale)``: float32 when every coordinate is exactly a
    float32 (e.g. PLY float properties), integers with offset and scale when the metadata gives a
    LAS-like ``scale``/``offset`` (or ``las_scales``/``las_offsets``) that reproduces every coordinate exactly, float64 otherwise.
    Decoding (:func:`decode_points`) returns exactly the input.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    stored = encode_as(pts, "float32")
    if stored is not None:
        return stored, "float32", None, None
    offset, scale = metadata_scale(metadata)
    if scale is not None:
        for enc in ("int32", "int64"):
            stored = encode_as(pts, enc, offset, scale)
            if stored is not None:
                return stored, enc, offset, scale
    return pts, "float64", None, None


def metadata_scale(metadata: dict[str, Any] | None) -> tuple[Any, Any]:
    """``(offset, scale)`` (3-vectors) from LAS-like metadata, or ``(None, None)``."""
    meta = metadata or {}
    scale = meta.get("scale", meta.get("las_scales"))
    offset = meta.get("offset", meta.get("las_offsets"))
    if scale is None or offset is None:
        return None, None
    try:
        scale = np.asarray(scale, dtype=np.float64).reshape(3)
        offset = np.asarray(offset, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        return None, None
    if not (np.all(scale > 0) and np.all(np.isfinite(scale)) and np.all(np.isfinite(offset))):
        return None, None
    return offset, scale


def encode_as(
    points: np.ndarray, encoding: str, offset: Any = None, scale: Any = None
) -> np.ndarray | None:
    """``points`` stored in ``encoding``, or None when that encoding would lose a coordinate."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if encoding == "float64":
        return pts
    if encoding == "float32":
        f32 = pts.astype(np.float32)
        return f32 if np.array_equal(f32.astype(np.float64), pts) else None
    if encoding in ("int32", "int64") and scale is not None and offset is not None:
        with np.errstate(invalid="ignore", over="ignore"):
            q = np.rint((pts - offset) / scale)
        limit = 2**31 - 1 if encoding == "int32" else 2**62
        if not np.all(np.abs(q) < limit):  # also false for NaN
            return None
        ints = q.astype(encoding)
        return ints if np.array_equal(decode_points(ints, encoding, offset, scale), pts) else None
    return None


def decode_points(
    stored: np.ndarray, encoding: str, offset: Any = None, scale: Any = None
) -> np.ndarray:
    """(K, 3) float64 coordinates from the stored array."""
    if encoding in ("int32", "int64"):
        out = stored.astype(np.float64)
        out *= np.asarray(scale, dtype=np.float64)
        out += np.asarray(offset, dtype=np.float64)
        return out
    return np.asarray(stored, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# dataset creation


def chunk_shape(shape: tuple[int, ...], itemsize: int) -> tuple[int, ...]:
    """Chunks along the first axis of at most about 1 MiB and CHUNK_ROWS rows, balanced so that
    the last chunk is nearly full (HDF5 allocates whole chunks)."""
    row_bytes = itemsize * int(np.prod(shape[1:], dtype=np.int64)) if len(shape) > 1 else itemsize
    target = max(1, min(CHUNK_ROWS, (1 << 20) // max(1, row_bytes)))
    n = int(shape[0])
    if n <= 0:
        return (target,) + tuple(shape[1:])
    n_chunks = -(-n // target)
    rows = -(-n // n_chunks)
    return (rows,) + tuple(shape[1:])


def row_group_rows(n_points: int) -> int:
    """Rows per chunk of every per-point dataset of a scan of ``n_points`` (one row group).

    Small enough that a 10k-point level reads at most about twice its bytes, large enough to keep
    at most ROW_GROUPS_MAX chunks per dataset (a chunk index that stays in the first file page);
    balanced so the last row group is nearly full."""
    n = max(1, int(n_points))
    target = max(ROW_GROUP_MIN, -(-n // ROW_GROUPS_MAX))
    n_groups = -(-n // target)
    return -(-n // n_groups)


def page_size(expected_bytes: int, max_chunk_bytes: int = 0) -> int:
    """HDF5 file-space page for a file of about ``expected_bytes`` whose largest chunk is about
    ``max_chunk_bytes``.

    A page of at least twice the largest chunk (a power of two in [PAGE_BIG_MIN, PAGE_MAX]) lets
    chunks pack into pages in the order they are written and leaves room in the first page for
    all the metadata (a remote reader gets it in one request): 1.7 % over the chunk bytes on a
    1M-point scan. A file smaller than SMALL_FILE_PAGES such pages gets PAGE_MIN pages instead,
    because each page kind wastes up to a page (measured on a 20k-point scan: 10 % with 4 KiB
    pages, 32 % with 64 KiB pages; DESIGN.md: 4 MiB pages added 18 % to a small file)."""
    want = max(PAGE_BIG_MIN, 2 * int(max_chunk_bytes))
    big = int(min(PAGE_MAX, 1 << max(0, (want - 1).bit_length())))
    return big if int(expected_bytes) >= SMALL_FILE_PAGES * big else PAGE_MIN


def compression_pays(data: np.ndarray) -> bool:
    """True when shuffle + gzip shrinks a sample of ``data`` below COMPRESS_BELOW of its size.

    Decompression costs about 1.5 ms per 100k values on the slice path, so compression is kept
    for data it halves (source_index, radius, parent, smooth attributes) and skipped for data it
    barely shrinks (noisy float coordinates and normals)."""
    if data.size == 0:
        return False
    flat = np.ascontiguousarray(data).reshape(data.shape[0], -1)
    sample = flat[: min(flat.shape[0], 16384)]
    raw = np.ascontiguousarray(sample).view(np.uint8).reshape(sample.shape[0], -1)
    item = data.dtype.itemsize
    # byte shuffle: group byte j of every element together, like HDF5's shuffle filter
    shuffled = raw.reshape(-1, item).T.tobytes() if item > 1 else raw.tobytes()
    if not shuffled:
        return False
    return len(zlib.compress(shuffled, 1)) < COMPRESS_BELOW * len(shuffled)


def text(value: str) -> np.bytes_:
    """A string attribute stored as fixed-length UTF-8 bytes: inside the object header (with its
    checksum, in the file's metadata pages), not in a separate heap that a remote reader would
    have to fetch on its own. Readers decode it with :func:`_attr_json` / :func:`from_json`."""
    return np.bytes_(value.encode("utf-8") or b" ")


def create_dataset(group: Any, name: str, data: np.ndarray, attrs: dict[str, Any] | None = None):
    """Create a small dataset: compact (stored in its object header, covered by the header's
    checksum) up to COMPACT_MAX bytes, else chunked and checksummed, compressed where it pays."""
    import h5py

    data = np.ascontiguousarray(data)
    kw: dict[str, Any]
    if 0 < data.nbytes <= COMPACT_MAX:
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_layout(h5py.h5d.COMPACT)
        kw = {"dcpl": dcpl}
    else:
        kw = {"chunks": chunk_shape(data.shape, data.dtype.itemsize), "fletcher32": True}
        if data.shape[0] > 0 and compression_pays(data):
            kw.update(compression="gzip", compression_opts=GZIP_LEVEL, shuffle=True)
        if data.shape[0] == 0:
            kw["maxshape"] = (None,) + tuple(data.shape[1:])
    ds = group.create_dataset(name, data=data, **kw)
    for key, value in (attrs or {}).items():
        ds.attrs[key] = value
    return ds


# ---------------------------------------------------------------------------------------------
# describing an HDF5 tree as JSON (validated against the schema)


def _attr_json(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray):
        return [_attr_json(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, list):
        return [_attr_json(v) for v in value]
    return value


def _layout_name(ds: Any) -> str:
    import h5py

    layout = ds.id.get_create_plist().get_layout()
    return {h5py.h5d.COMPACT: "compact", h5py.h5d.CONTIGUOUS: "contiguous",
            h5py.h5d.CHUNKED: "chunked"}.get(layout, "virtual")


def describe(node: Any) -> dict[str, Any]:
    """A JSON document of an open h5py File/Group: groups, datasets (dtype, shape, chunks,
    filters) and attributes, recursively. This is what ``schemas/archive.schema.json`` describes."""
    import h5py

    out: dict[str, Any] = {
        "kind": "group",
        "attrs": {k: _attr_json(v) for k, v in node.attrs.items()},
        "members": {},
    }
    for key in node:
        obj = node.get(key, getlink=False)
        if isinstance(obj, h5py.Group):
            out["members"][key] = describe(obj)
        elif isinstance(obj, h5py.Dataset):
            out["members"][key] = {
                "kind": "dataset",
                "dtype": obj.dtype.str[1:] if obj.dtype.kind == "S" else str(obj.dtype),
                "shape": list(obj.shape),
                "layout": _layout_name(obj),
                "chunks": list(obj.chunks) if obj.chunks else None,
                "compression": obj.compression,
                "fletcher32": bool(obj.fletcher32),
                "attrs": {k: _attr_json(v) for k, v in obj.attrs.items()},
            }
        else:  # pragma: no cover - links to nowhere, committed datatypes
            out["members"][key] = {"kind": "other"}
    return out
