"""Writing a tiled scan into its part file, in stored (prefix) order, without holding it.

The points and attributes sit in input order in the raw blocks of the work directory, the ranks in
``rank.<b>.i8`` (one file per raw block: :mod:`.ranks`); the archive wants them in the merged order. An external permutation does it in two passes: every raw block is split by
destination block into bucket pieces (one record per point: position, coordinates, attributes; a
task per raw block, :func:`bucket_block`), then each bucket (a band of whole row groups of the
archive: :func:`band_rows`) is read, put in order and written as finished HDF5 chunks by a task of
its own (:mod:`.bands`). Memory: one bucket per task.

:func:`write_scan` is the same write by one process through the archive's
:class:`~lodbuilder.archive.scanwriter.ScanWriter` (the buckets in order): the reference the banded
write equals (tests compare the two).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ...archive import layout as L
from ...errors import BuildError, InputError
from ...progress import ProgressCallback, report
from . import layout as WL
from .store import LocalStore, Store, as_store
from .timing import timed_task
from .workdir import Zipped, blocks, opaque_rows, read_rows, unzipped, zipped_blocks

BLOCK = 1 << 18  # rows per destination bucket (one bucket is in memory at a time)


def record_dtype(fields: dict[str, tuple[str, tuple[int, ...]]]) -> np.dtype:
    spec: list[Any] = [("pos", "<i8"), ("xyz", "<f8", (3,))]
    for i, (_, (dt, shape)) in enumerate(fields.items()):
        spec.append((f"a{i}", dt, tuple(shape)) if shape else (f"a{i}", dt))
    return np.dtype(spec)


def bucket_records(store: Store, name: str, rec: np.dtype) -> np.ndarray:
    """The records of a bucket piece (compressed: :class:`.workdir.Zipped`)."""
    return unzipped(store.get(name), rec, name)


@timed_task
def bucket_block(work: Store | str, b: int, g0: int, m: int, fields: dict[str, tuple[str, tuple[int, ...]]], n: int,
                 block: int, rows: int) -> dict[str, Any]:
    """The first pass for raw block ``b`` (a task): its points and attributes, with their stored
    positions (``rank.<b>.i8``, input indices ``g0 .. g0 + m``), split by destination block (``block`` rows of
    the stored order) into the bucket pieces ``bucket.<k>.<b>.bin``, in input order."""
    w = as_store(work)
    n_buckets = (n + block - 1) // block
    counts = np.zeros(n_buckets, np.int64)
    out: dict[str, Zipped] = {}
    try:
        with w.open(WL.rank_file(b)) as fr:
            for _, r in _raw_records(w, fields, [[0, 0, m, g0]], rows, first=b):
                r["pos"] = read_rows(fr, np.dtype("<i8"), r.shape[0])
                dest = r["pos"] // block
                order = np.argsort(dest.astype(np.int32), kind="stable")  # radix sort
                cuts = np.searchsorted(dest[order], np.arange(n_buckets + 1))
                srt = opaque_rows(r)[order]
                for k in np.flatnonzero(np.diff(cuts)):
                    name = WL.bucket(int(k), b)
                    if name not in out:
                        out[name] = Zipped(w.writer(name))
                    out[name].write(srt[cuts[k]:cuts[k + 1]])
                    counts[k] += cuts[k + 1] - cuts[k]
        files = {name: f.commit() for name, f in out.items()}
    finally:
        for f in out.values():
            f.close()
    return {"block": b, "counts": counts.tolist(), "files": files}


def buckets_phase(ex: Any, work: Any, name: str, n: int, fields: dict[str, tuple[str, tuple[int, ...]]],
                  raw: list[list[int]], rows: int, progress: ProgressCallback = None) -> dict[str, Any]:
    """The first pass of the write as tasks, one per raw block (or what a finished one recorded)."""
    from .pool import collect, submit
    from .sums import done, mark

    doc = done(work, "buckets")
    if doc is not None:
        return doc
    block = band_rows(n, BLOCK)  # the write's bands: whole row groups of the archive
    results: dict[int, dict[str, Any]] = {}
    calls = []
    for b, (_, a, z, g0) in enumerate(raw):
        prev = done(work, WL.bucket_piece(b))
        if prev is not None:
            results[b] = prev
        else:
            calls.append((b, bucket_block, (work, b, int(g0), int(z) - int(a), fields, n, block, rows)))

    def record(res: dict[str, Any]) -> None:
        results[res["block"]] = mark(work, WL.bucket_piece(res["block"]), res)

    collect(submit(ex, calls), lambda b: f"the permutation of block {b + 1}", name, n, progress, "permute", record,
            lambda r: int(np.sum(r["counts"])), sum(int(np.sum(r["counts"])) for r in results.values()))
    doc = bucket_pieces([results[b] for b in range(len(raw))], block)
    return mark(work, "buckets", doc)


def band_rows(n: int, block: int) -> int:
    """Rows per band of a scan of ``n`` points: the whole row groups nearest ``block`` rows."""
    rows = L.row_group_rows(n)
    return rows * max(1, round(block / rows))


def damaged(name: str, exc: InputError) -> BuildError:
    """The archive's own check failed on rows of the work files: they disagree with each other."""
    what = str(exc).split(";")[0]
    return BuildError(f"scan {name!r}: the tiled build's work files disagree ({what}); they are damaged: run "
                      "the build again with --force")


def bucket_pieces(results: list[dict[str, Any]], block: int) -> dict[str, Any]:
    """The buckets phase's marker from every block's result: each bucket's pieces in block order."""
    counts = np.array([r["counts"] for r in results], np.int64).reshape(len(results), -1)
    pieces = [[WL.bucket(k, int(b)) for b in np.flatnonzero(counts[:, k])] for k in range(counts.shape[1])]
    return {"block": block, "buckets": counts.shape[1], "pieces": pieces,
            "files": {k: v for r in results for k, v in r["files"].items()}}


def _raw_records(work: Any, fields: dict[str, tuple[str, tuple[int, ...]]], raw: list[list[int]],
                 rows: int, first: int = 0) -> Iterator[tuple[int, np.ndarray]]:
    """``(first input index, records)``: the raw blocks ``raw`` (numbered from ``first``)'s
    coordinates and attributes as bucket records (``pos`` left to fill), ``rows`` at a time, in
    input order."""
    store = as_store(work)
    rec = record_dtype(fields)
    attr = WL.attr_record(fields)
    for b, (_, a, z, g0) in enumerate(raw, start=first):
        m_b = int(z) - int(a)
        ats: Any = zipped_blocks((store, WL.raw_attr(b)), attr, m_b, rows) if attr.itemsize else None
        try:
            for r0, xyz in blocks((store, WL.raw_xyz(b)), "<f8", 3 * m_b, 3 * rows):
                pts = xyz.reshape(-1, 3)
                r = np.empty(pts.shape[0], rec)
                r["xyz"] = pts
                if ats is not None:
                    _, at = next(ats)
                    for i in range(len(fields)):
                        r[f"a{i}"] = at[f"a{i}"]
                yield int(g0) + r0 // 3, r
        finally:
            if ats is not None:
                ats.close()


def write_scan(work: Path, part: Path, name: str, n: int, fields: dict[str, tuple[str, tuple[int, ...]]],
               metadata: dict[str, Any], encoding: str, seeds: np.ndarray, build: dict[str, Any],
               provenance: dict[str, Any], progress: ProgressCallback, buckets: dict[str, Any],
               radii: dict[str, Any]) -> Any:
    """Write the bucketed points (``buckets``: what :func:`buckets_phase` recorded) in stored
    order as the part ``part``, with their radii and parents (``radii``: the radii's bands)."""
    if isinstance(work, LocalStore):  # (the one-process reference write reads a local directory)
        work = work.root
    try:
        return _write_buckets(work, part, name, n, fields, metadata, encoding, seeds, build, provenance, progress,
                              buckets, radii)
    except InputError as exc:  # the scan writer's own check: the work files disagree with each other
        raise damaged(name, exc) from None


def _write_buckets(work: Path, part: Path, name: str, n: int, fields: dict[str, tuple[str, tuple[int, ...]]],
                   metadata: dict[str, Any], encoding: str, seeds: np.ndarray, build: dict[str, Any],
                   provenance: dict[str, Any], progress: ProgressCallback, buckets: dict[str, Any],
                   radii: dict[str, Any]) -> Any:
    from ...archive.scanwriter import ScanWriter

    block = int(buckets["block"])
    rec = record_dtype(fields)
    names = list(fields)
    bands = range(len(radii["bands"]))
    frad, fpar = _Joined([work / WL.radius(b) for b in bands], "<f8"), _Joined([work / WL.parent(b) for b in bands], "<i8")
    with ScanWriter(part, name, n, metadata=metadata, encoding=encoding) as w, frad, fpar:
        for b in range(int(buckets["buckets"])):
            k0 = b * block
            k1 = min(n, k0 + block)
            local = LocalStore(work)
            r = np.concatenate([bucket_records(local, p, rec) for p in buckets["pieces"][b]] or [np.zeros(0, rec)])
            if r.shape[0] != k1 - k0:
                raise RuntimeError(f"bucket {b} holds {r.shape[0]} rows, expected {k1 - k0}")
            srt = np.empty(k1 - k0, rec)
            opaque_rows(srt)[r["pos"] - k0] = opaque_rows(r)
            del r
            g = _order_block(work, k0, k1)
            rad, par = frad.read(k1 - k0), fpar.read(k1 - k0)
            w.write(srt["xyz"], g, rad, par, attributes={k: srt[f"a{i}"] for i, k in enumerate(names)})
            report(progress, "write", k1, n)
        return w.finish(n_ordered=n, seeds=seeds, build=build, provenance=provenance)


class _Joined:
    """Sequential reads of records from files one after another (the radii's bands)."""

    def __init__(self, paths: list[Path], dtype: str) -> None:
        self.paths, self.dtype = list(paths), np.dtype(dtype)
        self.f: Any = None

    def read(self, m: int) -> np.ndarray:
        parts = []
        while m > 0 and (self.f is not None or self.paths):
            if self.f is None:
                self.f = open(self.paths.pop(0), "rb")  # noqa: SIM115 - closed at its end or by __exit__
            a = np.fromfile(self.f, dtype=self.dtype, count=m)
            parts.append(a)
            m -= a.shape[0]
            if m > 0:
                self.f.close()
                self.f = None
        return np.concatenate(parts) if parts else np.zeros(0, self.dtype)

    def __enter__(self) -> _Joined:
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.f is not None:
            self.f.close()


def _order_block(work: Path, k0: int, k1: int) -> np.ndarray:
    from .merge import order_files
    from .workdir import segment

    return segment(LocalStore(work), order_files(LocalStore(work)), "<i8", k0, k1)
