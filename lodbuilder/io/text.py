"""Text point clouds: XYZ, PTS, CSV (and .txt).

One point per line; values separated by commas (when the first data line has a comma) or by
whitespace. A header line is recognised when any of its fields is not a number: it names the columns
(``x, y, z`` must be among them, case-insensitive; ``X``/``Y``/``Z`` and ``//X`` work too). Without a
header the columns are named by convention: 3 -> x y z; 4 -> + intensity; 6 -> + red green blue when
all three are integers in 0..255, else + nx ny nz; 7 -> + intensity red green blue (the Leica PTS
layout); otherwise ``col3``, ``col4``, ... A leading line holding a single integer (the PTS point
count) is skipped. Lines starting with ``#`` are comments; a ``# dtypes: f8,f8,f8,u1,...`` comment
(written by lodbuilder before 0.2) restores each column's dtype; otherwise integer-valued columns
named red/green/blue become uint8 (or uint16 when > 255) and every other column stays float64.
The CRS is read from a ``<file>.prj`` sidecar (WKT) when there is one.

Text does not stream: the column layout and dtypes are decided from the whole file, so this
reader is the one path, and :func:`lodbuilder.io.stream.open_stream` hands its scan out in chunks.
"""

from __future__ import annotations

import itertools
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from ._files import exc_line
from .base import Scan
from .crs import read_sidecar, set_crs

_NUM = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$|^[+-]?(nan|inf|infinity)$", re.IGNORECASE)


def _split(line: str, delim: str | None) -> list[str]:
    return [t.strip() for t in line.split(delim)] if delim else line.split()


def _is_num(tok: str) -> bool:
    return bool(_NUM.match(tok))


def read(path: Path) -> list[Scan]:
    with open(path, encoding="utf-8", errors="replace") as f:
        head = list(itertools.islice(f, 64))
    dtypes, skip, header, header_line, delim, first_data = _layout(head)
    if first_data is None:
        raise FormatError(f"{path}: no point lines found; a text scan needs lines of 'x y z ...'")
    if header is not None:
        header = _header_fields(header_line, delim)
    try:
        table = np.loadtxt(path, dtype=np.float64, delimiter=delim, skiprows=skip, comments="#", ndmin=2)
    except ValueError as exc:
        raise FormatError(f"{path}: malformed line in text scan ({exc_line(exc)}); every line needs the same number of values") from None
    ncol = table.shape[1]
    names = _column_names(path, header, ncol, table)
    lower = [n.lower() for n in names]
    try:
        ix = [lower.index(c) for c in ("x", "y", "z")]
    except ValueError:
        raise FormatError(f"{path}: text header has no x/y/z columns (columns: {', '.join(names)}); name them x, y, z") from None
    pts = np.ascontiguousarray(table[:, ix])
    attrs = _attributes(table, names, ix, dtypes)
    meta: dict[str, Any] = {"columns": names, "delimiter": delim or " ", "header": header is not None}
    set_crs(meta, read_sidecar(path), "file")
    return [Scan(points=pts, attributes=attrs, name=path.stem, source=str(path), reader="text", metadata=meta)]


def _layout(head: list[str]) -> tuple[list[str] | None, int, list[str] | None, str, str | None,
                                      list[str] | None]:
    """From the first lines of a text scan: the dtypes comment, the lines to skip, whether there is a
    header (and its line), the delimiter and the first data line's values."""
    dtypes: list[str] | None = None
    skip = 0
    header: list[str] | None = None
    header_line = ""
    delim: str | None = None
    first_data: list[str] | None = None
    for line in head:
        s = line.strip()
        if not s:
            skip += 1
            continue
        if s.startswith("#"):
            m = re.match(r"#\s*dtypes:\s*(.*)$", s)
            if m:
                dtypes = [t.strip() for t in m.group(1).split(",")]
            skip += 1
            continue
        delim = "," if "," in s else (";" if ";" in s else None)
        toks = _split(s, delim)
        if header is None and first_data is None and not all(_is_num(t) for t in toks):
            header, header_line = [], s  # (its names are read with the data's delimiter below)
            skip += 1
            continue
        if header is None and first_data is None and len(toks) == 1 and re.fullmatch(r"\d+", toks[0]):
            skip += 1  # PTS point count
            continue
        first_data = toks
        break
    return dtypes, skip, header, header_line, delim, first_data


def _attributes(table: np.ndarray, names: list[str], ix: list[int], dtypes: list[str] | None) -> dict[str, np.ndarray]:
    """Every column but x, y, z, in the dtype the ``# dtypes:`` comment gives (colours as integers)."""
    attrs: dict[str, np.ndarray] = {}
    for j, n in enumerate(names):
        if j in ix:
            continue
        col = table[:, j]
        if dtypes is not None and len(dtypes) == table.shape[1]:
            try:
                attrs[n] = col.astype(np.dtype(dtypes[j]))
                continue
            except TypeError:
                pass
        if n.lower() in ("red", "green", "blue") and col.size and np.all(col == np.round(col)) and col.min() >= 0:
            attrs[n] = col.astype(np.uint8 if col.max() <= 255 else np.uint16)
        else:
            attrs[n] = col
    return attrs


def _column_names(path: Path, header: list[str] | None, ncol: int, table: np.ndarray) -> list[str]:
    if header is not None:
        if len(header) != ncol:
            raise FormatError(f"{path}: header names {len(header)} columns but lines hold {ncol} values; fix the header")
        return header
    base = ["x", "y", "z"]
    if ncol < 3:
        raise FormatError(f"{path}: lines hold {ncol} values; a text scan needs at least x y z")
    if ncol == 3:
        return base
    if ncol == 4:
        return base + ["intensity"]
    if ncol == 6:
        rgb = table[:, 3:6]
        if np.all(rgb == np.round(rgb)) and rgb.min() >= 0 and rgb.max() <= 255:
            return base + ["red", "green", "blue"]
        return base + ["nx", "ny", "nz"]
    if ncol == 7:
        return base + ["intensity", "red", "green", "blue"]
    return base + [f"col{j}" for j in range(3, ncol)]


def _text(a: np.ndarray) -> np.ndarray:
    """Each value as the shortest text that reads back to the same value of its dtype (integers
    as integers; float32 as float32, e.g. ``0.1`` not ``0.10000000149011612``)."""
    if a.dtype == np.bool_:
        return a.astype(np.uint8).astype(str)
    if a.dtype.kind in "iu":
        return a.astype(str)
    if a.dtype.kind == "f" and a.dtype.itemsize < 4:
        a = a.astype(np.float32)
    elif a.dtype.kind == "f" and a.dtype.itemsize > 8:
        a = a.astype(np.float64)
    return a.astype(str)  # numpy prints the shortest repr that round-trips (Dragon4, unique)


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], metadata: dict[str, Any] | None) -> list[str]:
    """One header line of names (``x,y,z,...``), then one point per line: commas for .csv, spaces
    otherwise, nothing before the header. Values keep their source precision: coordinates stored
    as float32 by the source (``metadata["vertex_properties"]``, as the PLY writer decides) and
    float32 attributes print as float32, float64 as float64, integers as integers. Text carries
    no dtypes: reading back gives float64 columns (and uint8 colours) whose values cast back to
    the source dtype exactly."""
    from .ply import columns, coord_dtype

    notes: list[str] = []
    cols = columns(attributes, notes)
    names = ["x", "y", "z"] + [_safe_name(n, notes) for n, _ in cols]
    cdt = coord_dtype(points, metadata)
    coords = points.astype(cdt, copy=False)
    arrays = [coords[:, 0], coords[:, 1], coords[:, 2]] + [np.asarray(a) for _, a in cols]
    sep = "," if path.suffix.lower() == ".csv" else " "
    n = points.shape[0]
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(sep.join(_quoted(name, sep) for name in names) + "\n")
        step = 100_000
        for s in range(0, n, step):
            texts = [_text(a[s:s + step]) for a in arrays]
            f.write("".join(sep.join(row) + "\n" for row in zip(*texts, strict=True)))
    return notes


#: first characters that make a spreadsheet read a cell as a formula (OWASP's CSV injection list)
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def _safe_name(name: str, notes: list[str]) -> str:
    """A column name a spreadsheet will not run: one starting like a formula gets a leading
    ``'`` (noted)."""
    if not name.startswith(FORMULA_START):
        return name
    notes.append(f"attribute {name!r} written as {chr(39) + name!r}: a name starting with = + - "
                 "or @ reads as a formula in spreadsheets")
    return "'" + name


def _quoted(name: str, sep: str) -> str:
    """``name`` as a header field (RFC 4180): in double quotes, its own quotes doubled, when it
    holds the separator, a quote, a line break or (space-separated files) white space."""
    if any(c in name for c in (sep, '"', "\n", "\r")) or (sep == " " and any(c.isspace() for c in name)):
        return '"' + name.replace('"', '""') + '"'
    return name


def _header_fields(line: str, delim: str | None) -> list[str]:
    """The names of a header line, quoted fields (RFC 4180) read as such."""
    import csv

    if delim:
        fields = next(csv.reader([line], delimiter=delim))
    else:
        fields = [f for f in next(csv.reader([line], delimiter=" ", skipinitialspace=True)) if f]
    return [f.strip().lstrip("/").strip() for f in fields]
