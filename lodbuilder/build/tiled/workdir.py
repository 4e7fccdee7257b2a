"""The work directory of a tiled build: the scan spilled to raw files, read back in chunks (the
files and their records are listed in :mod:`.layout`).

Every pass reads these with explicit reads of bounded blocks (no memory maps left open), so the
resident memory of the process that runs it stays at one block.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...progress import ProgressCallback, report
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

    def to_json(self) -> dict[str, Any]:
        return {"n": self.n, "lo": self.lo.tolist(), "hi": self.hi.tolist(),
                "fields": {k: [d, list(s)] for k, (d, s) in self.fields.items()},
                "metadata": self.metadata, "reader": self.reader, "members": self.members,
                "encoding": self.encoding, "files": self.files or {}}

    @classmethod
    def from_json(cls, d: dict[str, Any], sample: np.ndarray) -> Spill:
        return cls(int(d["n"]), np.asarray(d["lo"]), np.asarray(d["hi"]),
                   {k: (v[0], tuple(v[1])) for k, v in d["fields"].items()}, sample, d["metadata"], d["reader"],
                   d.get("members") or [], d.get("encoding", "float64"))


def attr_file(work: Path, i: int) -> Path:
    return work / WL.attr(i)


def spill(sources: list[tuple[Any, Any, int | None]], work: Path, progress: ProgressCallback = None,
          total: int | None = None, chunk_rows: int | None = None) -> Spill:
    """Read every source (``(PointStream, pose or None, member id or None)``) chunk by chunk into
    the work directory. A joint build (several sources) keeps the attributes all of them have and
    adds ``scan_id`` (int32) and ``scan_point`` (int64: the index in its own scan)."""
    from ...archive.layout import choose_encoding, encode_points
    from ...io.pose import apply_pose

    joint = len(sources) > 1 or sources[0][2] is not None
    common = set(sources[0][0].fields)
    for s, _, _ in sources[1:]:
        common &= {k for k, v in s.fields.items() if v == sources[0][0].fields.get(k)}
    names = sorted(common) if joint else list(sources[0][0].fields)
    fields = {k: (np.dtype(sources[0][0].fields[k][0]).str, tuple(sources[0][0].fields[k][1])) for k in names}
    if joint:
        fields["scan_id"] = (np.dtype(np.int32).str, ())
        fields["scan_point"] = (np.dtype(np.int64).str, ())
    n_total = total if total is not None else sum(s.n_points for s, _, _ in sources)
    step = max(1, n_total // SAMPLE)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    samples = []
    files = {k: SumFile(attr_file(work, i)) for i, k in enumerate(fields)}
    members = []
    encodings: set[str] = set()
    meta = dict(sources[0][0].metadata) if not joint else _joint_crs(sources)
    g = 0
    try:
        with SumFile(work / WL.POINTS) as fp:
            report(progress, "read", 0, n_total)
            for stream, pose, member in sources:
                first = g
                for chunk in stream.chunks(chunk_rows or BLOCK):
                    pts = chunk.points if pose is None else apply_pose(chunk.points, np.asarray(pose))
                    pts = np.ascontiguousarray(pts, dtype="<f8")
                    fp.write(pts)
                    encodings.add(encode_points(pts, meta)[1])
                    lo = np.minimum(lo, pts.min(axis=0))
                    hi = np.maximum(hi, pts.max(axis=0))
                    off = (-g) % step
                    samples.append(pts[off::step].copy())
                    for k in names:
                        files[k].write(np.ascontiguousarray(chunk.attributes[k], dtype=fields[k][0]))
                    if joint:
                        m = len(chunk)
                        files["scan_id"].write(np.full(m, member if member is not None else 0, "<i4"))
                        files["scan_point"].write(np.arange(chunk.start, chunk.start + m, dtype="<i8"))
                    g += len(chunk)
                    report(progress, "read", g, n_total)
                source = getattr(stream, "path", None)  # (for messages: the file a failed tile's points came from)
                members.append({"id": member, "n_points": g - first, "first": first,
                                "source": Path(source).name if source and Path(source).is_file() else None})
    finally:
        for f in files.values():
            f.close()
    sample = np.concatenate(samples) if samples else np.zeros((0, 3))
    sums = {WL.POINTS: fp.sum, **{f.path.name: f.sum for f in files.values()}}
    return Spill(g, lo, hi, fields, sample, meta, sources[0][0].reader if not joint else "joint", members,
                 choose_encoding(encodings or {"float64"}), sums)


def _joint_crs(sources: list[tuple[Any, Any, int | None]]) -> dict[str, Any]:
    """The CRS metadata of a joint scan: the sources' own when they all share one CRS (the build
    refused them otherwise, or reprojected them to one), else none."""
    from ...io.crs import KEY_REPROJECTION, KEY_SOURCE, KEY_UNITS, KEY_WKT

    metas = [s.metadata for s, _, _ in sources]
    if not metas[0].get(KEY_WKT) or any(m.get(KEY_WKT) != metas[0][KEY_WKT] for m in metas):
        return {}
    keys = (KEY_WKT, KEY_UNITS, KEY_SOURCE)
    out = {k: metas[0][k] for k in keys if metas[0].get(k) is not None}
    reps = [m[KEY_REPROJECTION] for m in metas if KEY_REPROJECTION in m]
    if reps:
        out[KEY_REPROJECTION] = reps
    return out


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


def point_blocks(work: Path, n: int, rows: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
    rows = rows or BLOCK
    for lo, a in blocks(work / WL.POINTS, "<f8", 3 * n, 3 * rows):
        yield lo // 3, a.reshape(-1, 3)


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


class TileWriter:
    """Appends records to the core and halo files of every tile."""

    def __init__(self, work: Path, n_tiles: int) -> None:
        self.core = [SumFile(work / WL.core(t)) for t in range(n_tiles)]
        self.halo = [SumFile(work / WL.halo(t)) for t in range(n_tiles)]
        self.n_core = np.zeros(n_tiles, np.int64)
        self.n_halo = np.zeros(n_tiles, np.int64)

    def add(self, which: str, t: int, rec: np.ndarray) -> None:
        (self.core if which == "core" else self.halo)[t].write(rec)
        (self.n_core if which == "core" else self.n_halo)[t] += rec.shape[0]

    def close(self) -> None:
        for f in self.core + self.halo:
            f.close()

    def sums(self) -> dict[str, list[int]]:
        return {f.path.name: f.sum for f in self.core + self.halo}


def opaque_rows(a: np.ndarray) -> np.ndarray:
    """A structured array seen as opaque fixed-size rows: NumPy gathers and scatters those about
    ten times faster than structured records (field by field)."""
    return a.view(np.dtype((np.void, a.dtype.itemsize)))


def distribute(work: Path, n: int, tiles: list[Any], grid: Any, lookup: np.ndarray, halo: float,
               progress: ProgressCallback = None) -> tuple[np.ndarray, np.ndarray, dict[str, list[int]]]:
    """Write the core and halo files of every tile; returns (core counts, halo counts, the files'
    sums)."""
    tw = TileWriter(work, len(tiles))
    t_lo = np.array([t.lo for t in tiles], float)
    t_hi = np.array([t.hi for t in tiles], float)
    los, his = t_lo - halo, t_hi + halo
    try:
        for g0, pts in point_blocks(work, n):
            m = pts.shape[0]
            rec = np.empty(m, REC)
            rec["g"] = np.arange(g0, g0 + m)
            rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
            raw = opaque_rows(rec)
            own = lookup[grid.index(pts)]
            order = np.argsort(own, kind="stable")
            bounds = np.searchsorted(own[order], np.arange(len(tiles) + 1))
            # only a point within the halo width of its own tile's faces can lie in another tile's
            # halo (the tiles' boxes do not overlap): test those against every tile
            lo_own, hi_own = t_lo[own], t_hi[own]
            is_near = np.zeros(m, bool)
            for a in range(3):  # column by column: NumPy reduces a short axis slowly
                is_near |= pts[:, a] - lo_own[:, a] <= halo
                is_near |= hi_own[:, a] - pts[:, a] <= halo
            near = np.flatnonzero(is_near)
            p_near, own_near = pts[near], own[near]
            for t in range(len(tiles)):
                sel = order[bounds[t]:bounds[t + 1]]
                if sel.size:
                    tw.add("core", t, raw[sel])
                inside = own_near != t
                for a in range(3):
                    inside &= (p_near[:, a] >= los[t, a]) & (p_near[:, a] <= his[t, a])
                if inside.any():
                    tw.add("halo", t, raw[near[inside]])
            report(progress, "split", g0 + m, n)
    finally:
        tw.close()
    return tw.n_core, tw.n_halo, tw.sums()


class Decimator:
    """The decimated copy: one point per cubic cell of size ``cell`` (the first in input order),
    collected block by block."""

    def __init__(self, lo: np.ndarray, cell: float) -> None:
        self.lo = np.asarray(lo, float)
        self.cell = float(cell)
        self.keys: list[np.ndarray] = []
        self.gs: list[np.ndarray] = []
        self.sum: list[int] = [0, 0]  # size and CRC-32 of the file written

    def add(self, g0: int, pts: np.ndarray) -> None:
        c = np.floor((pts - self.lo) / self.cell).astype(np.int64)
        key = (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]
        ukey, first = np.unique(key, return_index=True)
        self.keys.append(ukey)
        self.gs.append(first + g0)

    def write(self, path: Path) -> int:
        keys = np.concatenate(self.keys)
        gs = np.concatenate(self.gs)
        order = np.lexsort((gs, keys))
        keys, gs = keys[order], gs[order]
        keep = np.ones(keys.shape[0], bool)
        keep[1:] = keys[1:] != keys[:-1]
        dec = np.sort(gs[keep]).astype("<i8")
        with SumFile(path) as f:
            f.write(dec)
        self.sum = f.sum
        return int(dec.shape[0])
