"""The work directory of a tiled build: what the read phase learnt (:class:`Spill`) and the raw
files read back in chunks (the files and their records are listed in :mod:`.layout`).

Every pass reads these with explicit reads of bounded blocks (no memory maps left open), so the
resident memory of the process that runs it stays at one block.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import layout as WL
from .sums import SumFile, read_json, write_json  # noqa: F401 - the markers' helpers, re-exported

REC = WL.REC
BLOCK = 1 << 20  # rows per read/write block
SAMPLE = 400_000  # points kept for the spacing estimate


@dataclass
class Spill:
    """What the read pass learnt: size, bounds, attributes, a sample for the spacing."""

    n: int
    lo: np.ndarray
    hi: np.ndarray
    fields: dict[str, tuple[str, tuple[int, ...]]]
    sample: np.ndarray
    metadata: dict[str, Any]
    reader: str
    members: list[dict[str, Any]]
    encoding: str = "float64"
    files: dict[str, list[int]] | None = None  # size and CRC-32 of each file written
    blocks: list[list[int]] | None = None  # the read blocks: [input, first row, end row, first input index]
    rows: int = BLOCK  # rows per chunk of the raw blocks' readers and writers

    def to_json(self) -> dict[str, Any]:
        return {"n": self.n, "lo": self.lo.tolist(), "hi": self.hi.tolist(),
                "fields": {k: [d, list(s)] for k, (d, s) in self.fields.items()},
                "metadata": self.metadata, "reader": self.reader, "members": self.members,
                "encoding": self.encoding, "files": self.files or {}, "blocks": self.blocks or [], "rows": self.rows}

    @classmethod
    def from_json(cls, d: dict[str, Any], sample: np.ndarray) -> Spill:
        return cls(int(d["n"]), np.asarray(d["lo"]), np.asarray(d["hi"]),
                   {k: (v[0], tuple(v[1])) for k, v in d["fields"].items()}, sample, d["metadata"], d["reader"],
                   d.get("members") or [], d.get("encoding", "float64"), d.get("files"), d.get("blocks"),
                   int(d.get("rows", BLOCK)))


def blocks(path: Path, dtype: Any, count: int | None = None, rows: int | None = None,
           start: int = 0) -> Iterator[tuple[int, np.ndarray]]:
    """``(first row, rows)`` blocks of a raw file of records ``dtype``, read with plain reads."""
    rows = rows or BLOCK
    dt = np.dtype(dtype)
    if count is None:
        count = path.stat().st_size // dt.itemsize
    with open(path, "rb") as f:
        f.seek(start * dt.itemsize)
        lo = start
        while lo < count:
            m = min(rows, count - lo)
            a = np.fromfile(f, dtype=dt, count=m)
            if a.shape[0] != m:
                raise OSError(f"{path}: truncated ({lo + a.shape[0]} of {count} rows)")
            yield lo, a
            lo += m


def gather(path: Path, dtype: Any, shape: tuple[int, ...], idx: np.ndarray) -> np.ndarray:
    """Rows ``idx`` of a raw file (any order), read in sorted runs without a memory map."""
    dt = np.dtype(dtype)
    width = dt.itemsize * int(np.prod(shape)) if shape else dt.itemsize
    order = np.argsort(idx, kind="stable")
    srt = idx[order]
    out = np.empty((idx.shape[0], *shape), dtype=dt)
    flat = out.reshape(idx.shape[0], -1) if shape else out
    with open(path, "rb", buffering=0) as f:
        # contiguous runs of sorted indices are read in one call each; gaps are seeked over
        i = 0
        m = srt.shape[0]
        while i < m:
            j = i + 1
            while j < m and srt[j] - srt[j - 1] <= 64 and j - i < 65536:
                j += 1
            first, last = int(srt[i]), int(srt[j - 1])
            f.seek(first * width)
            raw = f.read((last - first + 1) * width)
            run = np.frombuffer(raw, dtype=dt).reshape(last - first + 1, -1) if shape else np.frombuffer(raw, dtype=dt)
            rows = srt[i:j] - first
            flat[order[i:j]] = run[rows] if shape else run[rows]
            i = j
    return out


def opaque_rows(a: np.ndarray) -> np.ndarray:
    """A structured array seen as opaque fixed-size rows: NumPy gathers and scatters those about
    ten times faster than structured records (field by field)."""
    return a.view(np.dtype((np.void, a.dtype.itemsize)))
