"""Text point clouds: XYZ, PTS, CSV (and .txt).

One point per line; values separated by commas (when the first data line has a comma) or by
whitespace. A header line is recognised when any of its fields is not a number: it names the columns
(``x, y, z`` must be among them, case-insensitive; ``X``/``Y``/``Z`` and ``//X`` work too). Without a
header the columns are named by convention: 3 -> x y z; 4 -> + intensity; 6 -> + red green blue when
all three are integers in 0..255, else + nx ny nz; 7 -> + intensity red green blue (the Leica PTS
layout); otherwise ``col3``, ``col4``, ... A leading line holding a single integer (the PTS point
count) is skipped. Lines starting with ``#`` are comments; a ``# dtypes: f8,f8,f8,u1,...`` comment
(written by the writer) restores each column's dtype exactly; otherwise integer-valued columns named
red/green/blue become uint8 (or uint16 when > 255) and every other column stays float64.
"""

from __future__ import annotations

import itertools
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from .base import Scan

_NUM = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$|^[+-]?(nan|inf|infinity)$", re.IGNORECASE)


def _split(line: str, delim: str | None) -> list[str]:
    return [t.strip() for t in line.split(delim)] if delim else line.split()


def _is_num(tok: str) -> bool:
    return bool(_NUM.match(tok))


def read(path: Path) -> list[Scan]:
    with open(path, encoding="utf-8", errors="replace") as f:
        head = list(itertools.islice(f, 64))
    dtypes: list[str] | None = None
    skip = 0
    header: list[str] | None = None
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
            header = [t.lstrip("/").strip().strip('"') for t in toks]
            skip += 1
            continue
        if header is None and first_data is None and len(toks) == 1 and re.fullmatch(r"\d+", toks[0]):
            skip += 1  # PTS point count
            continue
        first_data = toks
        break
    if first_data is None:
        raise FormatError(f"{path}: no point lines found; a text scan needs lines of 'x y z ...'")
    try:
        table = np.loadtxt(path, dtype=np.float64, delimiter=delim, skiprows=skip, comments="#", ndmin=2)
    except ValueError as exc:
        msg = " ".join(str(exc).split())
        raise FormatError(f"{path}: malformed line in text scan ({msg}); every line needs the same number of values") from None
    ncol = table.shape[1]
    names = _column_names(path, header, ncol, table)
    lower = [n.lower() for n in names]
    try:
        ix = [lower.index(c) for c in ("x", "y", "z")]
    except ValueError:
        raise FormatError(f"{path}: text header has no x/y/z columns (columns: {', '.join(names)}); name them x, y, z") from None
    pts = np.ascontiguousarray(table[:, ix])
    attrs: dict[str, np.ndarray] = {}
    for j, n in enumerate(names):
        if j in ix:
            continue
        col = table[:, j]
        if dtypes is not None and len(dtypes) == ncol:
            try:
                attrs[n] = col.astype(np.dtype(dtypes[j]))
                continue
            except TypeError:
                pass
        if n.lower() in ("red", "green", "blue") and col.size and np.all(col == np.round(col)) and col.min() >= 0:
            attrs[n] = col.astype(np.uint8 if col.max() <= 255 else np.uint16)
        else:
            attrs[n] = col
    meta = {"columns": names, "delimiter": delim or " ", "header": header is not None}
    return [Scan(points=pts, attributes=attrs, name=path.stem, source=str(path), reader="text", metadata=meta)]


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


def _fmt(dt: np.dtype) -> str:
    return "%d" if dt.kind in "iub" else "%.17g"


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], metadata: dict[str, Any] | None) -> None:
    """A ``# dtypes:`` comment, a header line, then one point per line: commas for .csv, spaces otherwise.

    Floats are written with 17 significant digits, so float64 values survive the round trip exactly.
    """
    from .ply import columns

    cols = columns(attributes)
    names = ["x", "y", "z"] + [n for n, _ in cols]
    arrays = [points[:, 0], points[:, 1], points[:, 2]] + [np.asarray(a) for _, a in cols]
    dts = [np.dtype("i8") if a.dtype.kind in "iub" else np.dtype("f8") for a in arrays]
    sep = "," if path.suffix.lower() == ".csv" else " "
    fmt = sep.join(_fmt(d) for d in dts)
    n = points.shape[0]
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(f"# dtypes: {','.join(a.dtype.str.lstrip('<>=|') for a in arrays)}\n")
        f.write(sep.join(names) + "\n")
        step = 100_000
        for s in range(0, n, step):
            rows = np.empty(min(step, n - s), dtype=[(f"c{j}", d) for j, d in enumerate(dts)])
            for j, a in enumerate(arrays):
                rows[f"c{j}"] = a[s:s + step]
            np.savetxt(f, rows, fmt=fmt)
