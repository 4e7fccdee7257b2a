"""The work directory of a tiled build: what the read phase learnt (:class:`Spill`) and the raw
files read back in chunks (the files and their records are listed in :mod:`.layout`; where they
are kept, a directory or an object store, in :mod:`.store`).

Every pass reads these with explicit reads of bounded blocks (no memory maps), so the resident
memory of the process that runs it stays at one block.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from . import layout as WL
from .store import LocalStore, Store, as_store
from .sums import read_json, write_json  # noqa: F401 - the markers' helpers, re-exported

REC = WL.REC
BLOCK = 1 << 20  # rows per read/write block
SAMPLE = 400_000  # points kept for the spacing estimate
RUN_BYTES = 1 << 26  # at most this many bytes in one read of gather()
MAX_RUN_ROWS = 65536  # and at most this many rows
WHOLE_BYTES = 1 << 22  # an object store's sorted object up to this size is read whole by sorted_slice()


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


def blocks(path: Path | tuple[Store, str], dtype: Any, count: int | None = None, rows: int | None = None,
           start: int = 0) -> Iterator[tuple[int, np.ndarray]]:
    """``(first row, rows)`` blocks of a raw file of records ``dtype`` (a path, or a store and an
    object's name), read with plain reads (an object store: ranged reads of a sequential file)."""
    store, name = _source(path)
    rows = rows or BLOCK
    dt = np.dtype(dtype)
    if count is None:
        size = store.size(name)
        if size is None:
            raise FileNotFoundError(f"{store.url}: {name} is missing")
        count = size // dt.itemsize
    with store.open(name) as f:
        f.seek(start * dt.itemsize)
        lo = start
        while lo < count:
            m = min(rows, count - lo)
            a = read_rows(f, dt, m)
            if a.shape[0] != m:
                raise OSError(f"{store.url}/{name}: truncated ({lo + a.shape[0]} of {count} rows)")
            yield lo, a
            lo += m


#: zstandard level of the work files that are only ever read whole or from their start (the raw
#: blocks' attributes, the write's bucket pieces). Level 1 halves them (records
#: of an airborne LAZ survey: 2.2 x smaller, at about 285 MB/s of one core to compress and 525 MB/s
#: to decompress; zlib's level 1 made them as small at 80 and 220 MB/s): the largest work files,
#: alive beside the tiles' points and covering files
ZIP_LEVEL = 1
ZIP_READ = 1 << 22  # compressed bytes per read of zipped_blocks()


class Zipped:
    """A work file being written compressed (see ZIP_LEVEL): :meth:`write` records as they come."""

    def __init__(self, out: Any) -> None:
        import zstandard

        self.out = out
        self.z: Any = zstandard.ZstdCompressor(level=ZIP_LEVEL).compressobj()

    def write(self, rows: np.ndarray) -> None:
        self.out.write(self.z.compress(cast(Any, np.ascontiguousarray(rows))))

    def commit(self) -> list[int]:
        if self.z is not None:
            self.out.write(self.z.flush())
            self.z = None
        return cast(list[int], self.out.commit())

    def close(self) -> None:
        self.out.close()


def _unzipper() -> Any:
    import zstandard

    return zstandard.ZstdDecompressor().decompressobj()


def unzipped(data: bytes, dtype: Any, name: str) -> np.ndarray:
    """The records of a whole work file written by :class:`Zipped`."""
    import zstandard

    try:
        return np.frombuffer(_unzipper().decompress(data), dtype)
    except (zstandard.ZstdError, ValueError) as exc:  # (a damage its checksum did not find: a forged marker)
        from ...errors import InputError

        raise InputError(f"{name} is not a file of records ({exc})") from None


def zipped_blocks(path: tuple[Store, str], dtype: Any, count: int, rows: int) -> Iterator[tuple[int, np.ndarray]]:
    """``(first row, rows)`` blocks of a work file written by :class:`Zipped` (``count`` records)."""
    store, name = path
    dt = np.dtype(dtype)
    z, pending, lo = _unzipper(), b"", 0
    with store.open(name) as f:
        while lo < count:
            while len(pending) < min(rows, count - lo) * dt.itemsize:
                raw = f.read(ZIP_READ)
                if not raw:
                    break
                pending += z.decompress(raw)
            m = min(rows, count - lo, len(pending) // dt.itemsize)
            if m == 0:
                raise OSError(f"{store.url}/{name}: truncated ({lo} of {count} rows)")
            yield lo, np.frombuffer(pending[: m * dt.itemsize], dt).copy()
            pending = pending[m * dt.itemsize:]
            lo += m


def _source(path: Path | tuple[Store, str]) -> tuple[Store, str]:
    return path if isinstance(path, tuple) else (LocalStore(Path(path).parent), Path(path).name)


def read_rows(f: Any, dt: np.dtype, count: int) -> np.ndarray:
    """Up to ``count`` records from the file object ``f`` (a local file: np.fromfile)."""
    if isinstance(f, io.BufferedReader):
        return np.fromfile(f, dtype=dt, count=count)
    out = np.empty(count, dt)
    raw = memoryview(cast(Any, out)).cast("B")
    got = 0
    while got < raw.nbytes:
        k = f.readinto(raw[got:])
        if not k:
            break
        got += k
    return out[: got // dt.itemsize]


def read_runs(srt: np.ndarray, gap: int, width: int) -> list[tuple[int, int]]:
    """The reads of :func:`gather` for sorted row numbers ``srt`` of ``width`` bytes each: runs
    ``(i, j)`` of ``srt[i:j]``, a new run wherever two rows are more than ``gap`` apart, a run
    holding MAX_RUN_ROWS rows or reaching RUN_BYTES beyond its first row's start. Whole-array work
    and one binary search per run (a loop over the rows cost a quarter of a tiled build's covering)."""
    m = srt.shape[0]
    if m == 0:
        return []
    ends = np.append(np.flatnonzero(np.diff(srt) > gap) + 1, m)
    start = srt.astype(np.int64) * width
    runs = []
    i = 0
    for e in ends.tolist():
        while i < e:
            j = min(e, i + MAX_RUN_ROWS, int(np.searchsorted(start[i:e], start[i] + RUN_BYTES, "left")) + i)
            runs.append((i, j))
            i = j
    return runs


def gather(path: Path | tuple[Store, str], dtype: Any, shape: tuple[int, ...], idx: np.ndarray) -> np.ndarray:
    """Rows ``idx`` of a raw file (a path, or a store and an object's name; any order), read in
    sorted runs (ranged reads; no memory map)."""
    store, name = _source(path)
    dt = np.dtype(dtype)
    width = dt.itemsize * int(np.prod(shape)) if shape else dt.itemsize
    order = np.argsort(idx, kind="stable")
    srt = idx[order]
    out = np.empty((idx.shape[0], *shape), dtype=dt)
    flat = out.reshape(idx.shape[0], -1) if shape else out
    # contiguous runs of sorted indices are read in one range each; gaps of up to store.gap(width)
    # rows are read over (a seek locally, the cost of a request on an object store)
    runs = read_runs(srt, store.gap(width), width)
    raws = store.read_ranges(name, [int(srt[i]) * width for i, _ in runs],
                             [(int(srt[j - 1]) + 1) * width for i, j in runs])
    for (i, j), raw in zip(runs, raws, strict=True):
        first, last = int(srt[i]), int(srt[j - 1])
        if len(raw) != (last - first + 1) * width:
            raise OSError(f"{store.url}/{name}: truncated (rows {first}..{last} wanted)")
        run = np.frombuffer(raw, dtype=dt).reshape(last - first + 1, -1) if shape else np.frombuffer(raw, dtype=dt)
        flat[order[i:j]] = run[srt[i:j] - first]
    return out


def segment(work: Any, files: list[tuple[str, int, int]], dtype: str, k0: int, k1: int) -> np.ndarray:
    """Positions ``k0 .. k1`` of the stored order from ``files`` (name, first and end position of
    each, in order)."""
    dt = np.dtype(dtype)
    out = []
    for fname, a, z in files:
        if a < k1 and z > k0:
            out.append(as_store(work).read_array(fname, dt, max(k0, a) - a, min(k1, z) - max(k0, a)))
    got = np.concatenate(out) if out else np.zeros(0, dt)
    if got.shape[0] != k1 - k0:
        raise RuntimeError(f"{files[0][0]} and the files after it hold {got.shape[0]} of positions {k0} to {k1}")
    return got


def sorted_slice(store: Store, name: str, dtype: np.dtype, k0: int, k1: int, key: str = "rank"
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """The records of an object sorted by field ``key`` with key in ``[k0, k1)``, and the last
    record before them (None when there is none): two binary searches and one read (a local file
    through a read-only memory map; an object store reads a small object whole, a large one by
    ranged reads of single records for the searches)."""
    size = (store.size(name) or 0) // dtype.itemsize
    if size == 0:
        return np.zeros(0, dtype), None
    if isinstance(store, LocalStore):
        mm = np.memmap(store.path(name), dtype=dtype, mode="r", shape=(size,))
        try:
            ranks = mm[key]
            a, z = int(np.searchsorted(ranks, k0, "left")), int(np.searchsorted(ranks, k1, "left"))
            return np.array(mm[a:z]), (np.array(mm[a - 1]) if a > 0 else None)
        finally:
            del mm
    if size * dtype.itemsize <= WHOLE_BYTES:
        recs = store.read_array(name, dtype)
        a, z = int(np.searchsorted(recs[key], k0, "left")), int(np.searchsorted(recs[key], k1, "left"))
        return recs[a:z].copy(), (recs[a - 1].copy() if a > 0 else None)

    def first_at_least(k: int) -> int:
        lo, hi = 0, size
        while lo < hi:
            mid = (lo + hi) // 2
            if store.read_array(name, dtype, mid, 1)[key][0] < k:
                lo = mid + 1
            else:
                hi = mid
        return lo

    a, z = first_at_least(k0), first_at_least(k1)
    recs = store.read_array(name, dtype, max(a - 1, 0), z - max(a - 1, 0))
    return (recs[1:], recs[0]) if a > 0 else (recs, None)


def opaque_rows(a: np.ndarray) -> np.ndarray:
    """A structured array seen as opaque fixed-size rows: NumPy gathers and scatters those about
    ten times faster than structured records (field by field)."""
    return a.view(np.dtype((np.void, a.dtype.itemsize)))
