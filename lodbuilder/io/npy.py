"""NumPy files.

``.npy`` holds either a plain (N, 3) array of coordinates, or a structured array (one record per
point) with fields ``x``, ``y``, ``z`` and any further fields as attributes. The writer produces the
plain form when there are no attributes and the structured form otherwise (coordinates float64).

``.npz`` holds named arrays: ``points`` (N, 3) (or ``x``, ``y``, ``z`` of shape (N,)); every other
array whose first dimension is N is an attribute, and a ``metadata`` 0-d string array holds JSON
metadata (its ``crs_wkt`` is the CRS). Pickled objects are never loaded. A ``.npy`` file carries
its CRS in a ``<file>.prj`` sidecar (WKT).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from ._files import exc_line
from .base import Rows, Scan, whole
from .crs import KEY_WKT, read_sidecar, set_crs, to_wkt

_XYZ = ("x", "y", "z")


def _load(path: Path) -> Any:
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as exc:
        raise FormatError(f"{path}: not a readable NumPy file ({exc_line(exc)}); save it with numpy.save / numpy.savez") from None
    except (EOFError, OSError) as exc:
        raise FormatError(f"{path}: truncated or damaged NumPy file ({exc_line(exc)}); save it again") from None


def _from_structured(path: Path, arr: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    names = arr.dtype.names or ()
    missing = [c for c in _XYZ if c not in names]
    if missing:
        raise FormatError(f"{path}: structured array lacks field(s) {'/'.join(missing)} (fields: {', '.join(names)}); "
                          "lodbuilder needs x, y and z")
    arr = arr.reshape(-1)
    pts = np.stack([np.asarray(arr[c], dtype=np.float64) for c in _XYZ], axis=1)
    attrs = {n: np.ascontiguousarray(arr[n]) for n in names if n not in _XYZ}
    return pts, attrs


def _metadata(entry: np.ndarray) -> dict[str, Any]:
    """An NPZ's ``metadata`` entry (a 0-d JSON string) as a dict ({} when it is anything else)."""
    if entry.ndim != 0:
        return {}
    try:
        loaded = json.loads(str(entry))
    except ValueError:
        return {}
    return loaded if isinstance(loaded, dict) else {}


def declared_crs(path: Path) -> str | None:
    """The CRS of a .npy (its ``.prj`` sidecar) or an .npz (its metadata), without its points."""
    if path.suffix.lower() == ".npy":
        return read_sidecar(path)
    with _load(path) as obj:
        meta = _metadata(obj["metadata"]) if "metadata" in obj.files else {}
    wkt = meta.get(KEY_WKT)
    return to_wkt(wkt, what=f"{path} metadata") if wkt else None


@dataclass
class NpyLayout:
    """Where the rows of a ``.npy`` file lie: from byte ``offset``, ``n`` rows of ``dtype``
    (``per_row`` values each: 3 for a plain (N, 3) array, 1 for a structured one), and the
    attribute fields (dtype, per-point shape)."""

    offset: int
    n: int
    dtype: np.dtype
    per_row: int
    fields: dict[str, tuple[np.dtype, tuple[int, ...]]]


def npy_layout(path: Path) -> NpyLayout | None:
    """The layout of a ``.npy`` file that :func:`npy_rows` reads (a C-order (N, 3) numeric array,
    or a 1-d structured array with x, y, z; N > 0; every row in the file), from its header; None
    for any other file (:func:`read` loads it whole, and says what is wrong with it)."""
    fmt = np.lib.format
    try:
        with open(path, "rb") as f:
            version = fmt.read_magic(f)
            if version not in ((1, 0), (2, 0)):
                return None
            read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, fortran, dtype = read_header(f)
            offset = f.tell()
    except (ValueError, OSError, EOFError):
        return None
    if fortran or dtype.hasobject or not shape or not shape[0]:
        return None
    if dtype.names:
        if any(c not in dtype.names for c in _XYZ) or len(shape) != 1:
            return None
        fields = {n: (dtype[n].base, dtype[n].shape) for n in dtype.names if n not in _XYZ}
        per_row = 1
    elif len(shape) == 2 and shape[1] == 3 and dtype.kind in "iuf":
        fields, per_row = {}, 3
    else:
        return None
    n = int(shape[0])
    if path.stat().st_size < offset + n * per_row * dtype.itemsize:
        return None  # truncated: numpy's own message
    return NpyLayout(offset, n, dtype, per_row, fields)


def npy_rows(path: Path, layout: NpyLayout, size: int, first: int = 0, stop: int | None = None) -> Iterator[Rows]:
    """The one read of a ``.npy`` file's rows (see :func:`npy_layout`): ``(first row, float64
    (m, 3) points, attributes)``, ``size`` rows at a time from row ``first`` to ``stop`` (default:
    the last), straight from the file."""
    stop = layout.n if stop is None else stop
    with open(path, "rb") as f:
        f.seek(layout.offset + first * layout.per_row * layout.dtype.itemsize)
        for lo in range(first, stop, size):
            m = min(stop, lo + size) - lo
            block = np.fromfile(f, dtype=layout.dtype, count=m * layout.per_row)
            if block.shape[0] != m * layout.per_row:  # the file shrank under us
                raise FormatError(f"{path}: truncated or damaged NumPy file (read {lo + block.shape[0] // layout.per_row} "
                                  f"of {layout.n} rows); save it again")
            if block.dtype.names:
                pts = np.stack([np.asarray(block[c], dtype=np.float64) for c in _XYZ], axis=1)
                attrs = {k: np.ascontiguousarray(block[k]) for k in layout.fields}
            else:
                pts, attrs = np.asarray(block.reshape(m, 3), dtype=np.float64), {}
            yield lo, pts, attrs


def read(path: Path) -> list[Scan]:
    """A ``.npy`` file that :func:`npy_rows` reads is its chunked read in one chunk; other files
    (``.npz``, arrays of other shapes, which do not stream) are loaded whole."""
    layout = npy_layout(path) if path.suffix.lower() == ".npy" else None
    if layout is not None:
        pts, attrs = whole(npy_rows(path, layout, layout.n))
        meta: dict[str, Any] = {"npy_layout": "structured" if layout.fields else "plain"}
        set_crs(meta, read_sidecar(path), "file")
        return [Scan(points=np.ascontiguousarray(pts), attributes=attrs, name=path.stem, source=str(path),
                     reader="npy", metadata=meta)]
    obj = _load(path)
    meta = {}
    if isinstance(obj, np.ndarray):
        if obj.dtype.names:
            pts, attrs = _from_structured(path, obj)
        else:
            if obj.ndim != 2 or obj.shape[1] != 3:
                raise FormatError(f"{path}: array has shape {obj.shape}; expected (N, 3) coordinates or a structured "
                                  "array with fields x, y, z")
            _check_numeric(path, obj)
            pts, attrs = np.asarray(obj, dtype=np.float64), {}
    else:
        with obj:
            files = {k: obj[k] for k in obj.files}
        if "metadata" in files and files["metadata"].ndim == 0:
            meta = _metadata(files.pop("metadata"))
        if "points" in files:
            p = files.pop("points")
            if p.ndim != 2 or p.shape[1] != 3:
                raise FormatError(f"{path}: 'points' has shape {p.shape}; expected (N, 3)")
            _check_numeric(path, p)
            pts = np.asarray(p, dtype=np.float64)
        elif all(c in files for c in _XYZ):
            pts = np.stack([np.asarray(files.pop(c), dtype=np.float64).reshape(-1) for c in _XYZ], axis=1)
        else:
            raise FormatError(f"{path}: archive holds no 'points' (N, 3) array nor x/y/z arrays "
                              f"(arrays: {', '.join(files) or 'none'}); save the coordinates as 'points'")
        n = pts.shape[0]
        attrs = {k: v for k, v in files.items() if v.ndim >= 1 and v.shape[0] == n}
    meta.setdefault("npy_layout", "structured" if attrs else "plain")
    if path.suffix.lower() == ".npy":
        set_crs(meta, read_sidecar(path), "file")
    elif meta.get(KEY_WKT):
        set_crs(meta, to_wkt(meta[KEY_WKT], what=f"{path} metadata"), "file")
    return [Scan(points=np.ascontiguousarray(pts), attributes=attrs, name=path.stem, source=str(path),
                 reader="npy", metadata=meta)]


def _check_numeric(path: Path, arr: np.ndarray) -> None:
    if arr.dtype.kind not in "iuf":
        raise FormatError(f"{path}: coordinates have dtype {arr.dtype}; expected numbers")


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], metadata: dict[str, Any] | None) -> list[str]:
    if path.suffix.lower() == ".npz":
        arrays: dict[str, Any] = {"points": points}
        arrays.update(attributes)
        if metadata:
            arrays["metadata"] = np.array(json.dumps(metadata, default=str))
        with open(path, "wb") as f:
            np.savez(f, **arrays)
        return []
    if not attributes:
        arr: np.ndarray = np.ascontiguousarray(points, dtype=np.float64)
    else:
        fields: list[Any] = [(c, "f8") for c in _XYZ]
        for n, a in attributes.items():
            a = np.asarray(a)
            fields.append((n, a.dtype, a.shape[1:]) if a.ndim > 1 else (n, a.dtype))
        arr = np.empty(points.shape[0], dtype=fields)
        for j, c in enumerate(_XYZ):
            arr[c] = points[:, j]
        for n, a in attributes.items():
            arr[n] = a
    with open(path, "wb") as f:
        np.save(f, arr, allow_pickle=False)
    return []
