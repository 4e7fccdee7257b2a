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
    crcs: list[Any] | None = None  # each read block's sums (blocks.rows_sum: the write's re-read checks them)

    def to_json(self) -> dict[str, Any]:
        return {"n": self.n, "lo": self.lo.tolist(), "hi": self.hi.tolist(),
                "fields": {k: [d, list(s)] for k, (d, s) in self.fields.items()},
                "metadata": self.metadata, "reader": self.reader, "members": self.members,
                "encoding": self.encoding, "files": self.files or {}, "blocks": self.blocks or [], "rows": self.rows,
                "crcs": self.crcs}

    @classmethod
    def from_json(cls, d: dict[str, Any], sample: np.ndarray) -> Spill:
        return cls(int(d["n"]), np.asarray(d["lo"]), np.asarray(d["hi"]),
                   {k: (v[0], tuple(v[1])) for k, v in d["fields"].items()}, sample, d["metadata"], d["reader"],
                   d.get("members") or [], d.get("encoding", "float64"), d.get("files"), d.get("blocks"),
                   int(d.get("rows", BLOCK)), d.get("crcs"))


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
#: blocks' attributes; the write's bucket pieces: BUCKET_ZIP_LEVEL). Level 1 halves them (records
#: of an airborne LAZ survey: 2.2 x smaller, at about 285 MB/s of one core to compress and 525 MB/s
#: to decompress; zlib's level 1 made them as small at 80 and 220 MB/s): the largest work files,
#: alive beside the tiles' points and covering files
ZIP_LEVEL = 1
#: the write's bucket pieces (written once, read once, by tasks whose CPU is the build's): zstandard's
#: fast level -3 compresses those records 1.15 x and decompresses them 1.6 x faster than level 1, the
#: files 16 % larger (72-byte records of the airborne survey: 1.76 x smaller instead of 2.05 x)
BUCKET_ZIP_LEVEL = -3
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


def put_zipped(store: Store, name: str, rows: np.ndarray) -> list[int]:
    """Write the work file ``name`` whole, compressed (:class:`Zipped`); returns its size and CRC-32."""
    z = Zipped(store.writer(name))
    try:
        z.write(rows)
        return z.commit()
    finally:
        z.close()


def get_zipped(store: Store, name: str, dtype: Any) -> np.ndarray:
    """The records of a whole work file written by :func:`put_zipped` (or :class:`Zipped`)."""
    return unzipped(store.get(name), dtype, name)


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
    each, in order; each written by :func:`put_framed`)."""
    dt = np.dtype(dtype)
    out = []
    for fname, a, z in files:
        if a < k1 and z > k0:
            out.append(read_framed(as_store(work), fname, dt, max(k0, a) - a, min(k1, z) - max(k0, a)))
    got = np.concatenate(out) if out else np.zeros(0, dt)
    if got.shape[0] != k1 - k0:
        raise RuntimeError(f"{files[0][0]} and the files after it hold {got.shape[0]} of positions {k0} to {k1}")
    return got


#: a frame of a framed file: its first and last key (a banded file) or row (a file framed by rows),
#: byte offset and length, records
FRAME = np.dtype([("first", "<i8"), ("last", "<i8"), ("offset", "<i8"), ("nbytes", "<i8"), ("count", "<i8")])
FRAME_ROWS = 1 << 16  # records per frame of put_framed()
#: bytes of a framed file's end read for its index at once (an index of up to 1,638 frames)
INDEX_READ = 1 << 16


def _put_frames(store: Store, name: str, recs: np.ndarray, bounds: list[int], keys: np.ndarray) -> list[int]:
    """Write ``recs[bounds[i]:bounds[i + 1]]`` as one zstandard frame each (:data:`ZIP_LEVEL`, with
    a checksum), then the frames' index (FRAME records, ``keys`` giving each frame's first and
    last) and its length (one int64). Returns the file's size and CRC-32."""
    import zstandard

    z = zstandard.ZstdCompressor(level=ZIP_LEVEL, write_checksum=True)  # (a damaged frame is found)
    index = np.zeros(max(len(bounds) - 1, 0), FRAME)
    out = store.writer(name)
    try:
        offset = 0
        for i, (a, e) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            data = z.compress(cast(Any, np.ascontiguousarray(recs[a:e])))
            index[i] = (keys[a], keys[e - 1], offset, len(data), e - a)
            out.write(data)
            offset += len(data)
        out.write(index)
        out.write(np.array([index.shape[0]], "<i8"))
        return cast(list[int], out.commit())
    finally:
        out.close()


def _frames_index(store: Store, name: str) -> np.ndarray:
    """A framed file's index (see :func:`_put_frames`): its end read once (:data:`INDEX_READ`
    bytes, as one suffix range on an object store: no request for the size first), again only
    for an index longer than that."""
    end = store.tail(name, INDEX_READ)
    count = int(np.frombuffer(end[-8:], "<i8")[0]) if len(end) >= 8 else -1
    need = 8 + count * FRAME.itemsize
    if count >= 0 and need > len(end) == INDEX_READ:
        end = store.tail(name, need)
    if count < 0 or need > len(end):
        raise OSError(f"{store.url}/{name}: not a framed work file")
    return np.frombuffer(end[len(end) - need:len(end) - 8], FRAME)


def _read_frames(store: Store, name: str, index: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """The records of the consecutive frames ``index`` (rows of the file's index), in one read."""
    import zstandard

    if index.shape[0] == 0:
        return np.zeros(0, dtype)
    lo, hi = int(index["offset"][0]), int(index["offset"][-1] + index["nbytes"][-1])
    (data,) = store.read_ranges(name, [lo], [hi])
    d = zstandard.ZstdDecompressor()
    parts = []
    for f in index:
        a = int(f["offset"]) - lo
        try:
            part = np.frombuffer(d.decompress(data[a:a + int(f["nbytes"])]), dtype)
        except zstandard.ZstdError as exc:
            raise OSError(f"{store.url}/{name}: a damaged frame ({exc})") from None
        if part.shape[0] != int(f["count"]):
            raise OSError(f"{store.url}/{name}: a frame holds {part.shape[0]} records, its index {int(f['count'])}")
        parts.append(part)
    return np.concatenate(parts)


def put_banded(store: Store, name: str, recs: np.ndarray, band: int, key: str = "rank") -> list[int]:
    """Write records sorted by the integer field ``key`` as a *banded* file: one compressed frame
    per band of ``band`` key values that holds records, and the frames' index, so that
    :func:`banded_slice` reads a band of keys with two small reads and one read of its frames.
    Returns the file's size and CRC-32."""
    keys = recs[key]
    cuts = np.flatnonzero(np.diff(keys // band)) + 1 if keys.shape[0] else np.zeros(0, np.int64)
    bounds = [0, *cuts.tolist(), keys.shape[0]] if keys.shape[0] else [0]
    return _put_frames(store, name, recs, bounds, keys)


def banded_slice(store: Store, name: str, dtype: np.dtype, k0: int, k1: int, key: str = "rank"
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """The records of a banded file (:func:`put_banded`) with key in ``[k0, k1)``, and the last
    record before them (None when there is none): the index read, then the frames that hold them
    (and the one before, for the record before) in one ranged read."""
    index = _frames_index(store, name)
    i0 = max(0, int(np.searchsorted(index["first"], k0, "left")) - 1)
    i1 = int(np.searchsorted(index["first"], k1, "left"))
    if i1 <= i0:
        return np.zeros(0, dtype), None
    recs = _read_frames(store, name, index[i0:i1], dtype)
    a, z = int(np.searchsorted(recs[key], k0, "left")), int(np.searchsorted(recs[key], k1, "left"))
    return recs[a:z].copy(), (recs[a - 1].copy() if a > 0 else None)


class Framed:
    """A file being written compressed in frames of ``rows`` records (see :func:`_put_frames`),
    records as they come (``out``: a store's writer); :meth:`commit` writes the last frame and the
    index, and returns the file's size and CRC-32."""

    def __init__(self, out: Any, rows: int = FRAME_ROWS) -> None:
        import zstandard

        self.out, self.rows = out, rows
        self.z = zstandard.ZstdCompressor(level=ZIP_LEVEL, write_checksum=True)
        self.pending: list[np.ndarray] = []
        self.held = self.written = self.offset = 0
        self.index: list[tuple[int, int, int, int, int]] = []

    def write(self, recs: np.ndarray) -> None:
        self.pending.append(np.ascontiguousarray(recs))
        self.held += recs.shape[0]
        while self.held >= self.rows:
            self._frame(self.rows)

    def _frame(self, m: int) -> None:
        allrec = np.concatenate(self.pending) if len(self.pending) > 1 else self.pending[0]
        data = self.z.compress(cast(Any, np.ascontiguousarray(allrec[:m])))
        self.index.append((self.written, self.written + m - 1, self.offset, len(data), m))
        self.out.write(data)
        self.offset += len(data)
        self.written += m
        self.pending = [allrec[m:]] if allrec.shape[0] > m else []
        self.held -= m

    def commit(self) -> list[int]:
        if self.held:
            self._frame(self.held)
        self.out.write(np.array(self.index, np.int64).reshape(-1, 5).view(FRAME).reshape(-1))
        self.out.write(np.array([len(self.index)], "<i8"))
        return cast(list[int], self.out.commit())

    def close(self) -> None:
        self.out.close()


def put_framed(store: Store, name: str, recs: np.ndarray, rows: int = FRAME_ROWS) -> list[int]:
    """Write records as a file compressed in frames of ``rows`` records (:class:`Framed`), so
    that :func:`read_framed` reads any run of rows with two small reads and one read of the frames
    that hold it. Returns the file's size and CRC-32."""
    f = Framed(store.writer(name), rows)
    try:
        f.write(recs)
        return f.commit()
    finally:
        f.close()


def put_stream(store: Store, name: str, stream: np.ndarray, rows: int = FRAME_ROWS) -> list[int]:
    """A tile's ordering stream (STREAM rows by descending key) as the bands of the merge read it
    (:func:`.merge.merge_band`): input index and key of each row (:data:`.layout.KEYS`; the seam
    points' coordinates and margins are in ``seam.<t>.bin``), in frames of at most ``rows`` rows
    as :func:`put_framed` writes them, but never across two key bins (:func:`.layout.key_bins`): a
    band of the merge is whole fine bins (:func:`.layout.hist_bins`, eight in a key bin), so it
    decompresses its own frames and at most one more at each end. Returns the file's size and CRC-32."""
    n = stream.shape[0]
    keys = np.empty(n, WL.KEYS)
    keys["g"], keys["key"] = stream["g"], stream["key"]
    runs = [0, *(np.flatnonzero(np.diff(WL.key_bins(keys["key"]))) + 1).tolist(), n] if n else [0]
    bounds = [a for s, e in zip(runs[:-1], runs[1:], strict=True) for a in range(s, e, rows)] + [n]
    return _put_frames(store, name, keys, bounds, np.arange(n))


def read_framed(store: Store, name: str, dtype: np.dtype, start: int, count: int) -> np.ndarray:
    """Rows ``start .. start + count`` of a file written by :class:`Framed` (fewer where it ends)."""
    return FramedReader(store, name, dtype).read(start, count)


class FramedReader:
    """Runs of rows of one file written by :class:`Framed`, its index read once and the last
    frames read kept (runs read one after another decompress each frame once)."""

    def __init__(self, store: Store, name: str, dtype: np.dtype) -> None:
        self.store, self.name, self.dtype = store, name, np.dtype(dtype)
        self.index: np.ndarray | None = None
        self.first, self.recs = 0, np.zeros(0, self.dtype)  # (the rows last decompressed)

    def read(self, start: int, count: int) -> np.ndarray:
        held = self.first + self.recs.shape[0]
        if not (self.first <= start and start + count <= held):
            if self.index is None:
                self.index = _frames_index(self.store, self.name)
            index = self.index
            i1 = int(np.searchsorted(index["first"], start + count, "left"))
            if self.first <= start < held:  # (a run read on from the last: its held frames are not read again)
                i0 = int(np.searchsorted(index["first"], held, "left"))
                self.recs = np.concatenate([self.recs[start - self.first:],
                                            _read_frames(self.store, self.name, index[i0:i1], self.dtype)])
                self.first = start
            else:
                i0 = int(np.searchsorted(index["last"], start, "left"))
                self.recs = _read_frames(self.store, self.name, index[i0:i1], self.dtype)
                self.first = int(index["first"][i0]) if i1 > i0 else start
        return self.recs[start - self.first:start - self.first + count].copy()


def opaque_rows(a: np.ndarray) -> np.ndarray:
    """A structured array seen as opaque fixed-size rows: NumPy gathers and scatters those about
    ten times faster than structured records (field by field)."""
    return a.view(np.dtype((np.void, a.dtype.itemsize)))
