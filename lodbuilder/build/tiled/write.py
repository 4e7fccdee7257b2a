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
from typing import Any, cast

import numpy as np

from ...archive import layout as L
from ...errors import BuildError, InputError
from ...progress import ProgressCallback, report
from . import layout as WL
from .store import LocalStore, Store, as_store
from .timing import timed_task
from .workdir import ZIP_LEVEL, opaque_rows, read_rows, segment, unzipped, zipped_blocks

BLOCK = 1 << 18  # rows per destination bucket (one bucket is in memory at a time)
BUCKET_FILES = 16  # bucket files per raw block, at most (see bucket_run)


def record_dtype(fields: dict[str, tuple[str, tuple[int, ...]]]) -> np.dtype:
    spec: list[Any] = [("pos", "<i8"), ("xyz", "<f8", (3,))]
    for i, (_, (dt, shape)) in enumerate(fields.items()):
        spec.append((f"a{i}", dt, tuple(shape)) if shape else (f"a{i}", dt))
    return np.dtype(spec)


def bucket_records(store: Store, pieces: list[list[Any]], rec: np.dtype) -> np.ndarray:
    """The records of a bucket from its pieces (``[file, start, end]``: one compressed frame each,
    in block order; a file's frames read in one request)."""
    where: dict[str, list[int]] = {}
    for i, p in enumerate(pieces):
        where.setdefault(p[0], []).append(i)
    blobs: list[bytes] = [b""] * len(pieces)
    for name, idx in where.items():
        got = store.read_ranges(name, [int(pieces[i][1]) for i in idx], [int(pieces[i][2]) for i in idx])
        for i, data in zip(idx, got, strict=True):
            blobs[i] = data
    parts = [unzipped(data, rec, p[0]) for data, p in zip(blobs, pieces, strict=True)]
    return np.concatenate(parts) if parts else np.zeros(0, rec)


def bucket_run(n_buckets: int) -> int:
    """Buckets per bucket file: a raw block writes at most :data:`BUCKET_FILES` files, whatever the
    number of bands (blocks x bands files made a 10^8-point survey's permutation write 307,800)."""
    return max(1, -(-n_buckets // BUCKET_FILES))


@timed_task
def bucket_block(work: Store | str, b: int, g0: int, m: int, fields: dict[str, tuple[str, tuple[int, ...]]], n: int,
                 block: int, run: int, rows: int) -> dict[str, Any]:
    """The first pass for raw block ``b`` (a task): its points and attributes, with their stored
    positions (``rank.<b>.i8``, input indices ``g0 .. g0 + m``), split by destination block (``block`` rows of
    the stored order) into pieces, in input order: one compressed frame per piece, in the bucket
    files ``bucket.<k0>_<k1>.<b>.bin`` of ``run`` consecutive buckets. Returns each bucket's pieces
    as ``[file, start, end]``."""
    import zstandard

    w = as_store(work)
    n_buckets = (n + block - 1) // block
    counts = np.zeros(n_buckets, np.int64)
    pieces: list[list[list[Any]]] = [[] for _ in range(n_buckets)]
    zc = zstandard.ZstdCompressor(level=ZIP_LEVEL)
    out: dict[str, Any] = {}
    ends: dict[str, int] = {}
    try:
        with w.open(WL.rank_file(b)) as fr:
            for _, r in _raw_records(w, fields, [[0, 0, m, g0]], rows, first=b):
                r["pos"] = read_rows(fr, np.dtype("<i8"), r.shape[0])
                dest = r["pos"] // block
                order = np.argsort(dest.astype(np.int32), kind="stable")  # radix sort
                cuts = np.searchsorted(dest[order], np.arange(n_buckets + 1))
                srt = opaque_rows(r)[order]
                for k in np.flatnonzero(np.diff(cuts)):
                    k0 = int(k) // run * run
                    name = WL.bucket(k0, min(n_buckets, k0 + run), b)
                    if name not in out:
                        out[name], ends[name] = w.writer(name), 0
                    frame = zc.compress(cast(Any, np.ascontiguousarray(srt[cuts[k]:cuts[k + 1]])))
                    out[name].write(frame)
                    pieces[k].append([name, ends[name], ends[name] + len(frame)])
                    ends[name] += len(frame)
                    counts[k] += cuts[k + 1] - cuts[k]
        files = {name: f.commit() for name, f in out.items()}
    finally:
        for f in out.values():
            f.close()
    return {"block": b, "counts": counts.tolist(), "pieces": pieces, "files": files}


def buckets_phase(ex: Any, work: Any, name: str, n: int, fields: dict[str, tuple[str, tuple[int, ...]]],
                  raw: list[list[int]], rows: int, progress: ProgressCallback = None) -> dict[str, Any]:
    """The first pass of the write as tasks, one per raw block (or what a finished one recorded)."""
    from .pool import collect, submit
    from .sums import done, mark, prune

    doc = done(work, "buckets")
    if doc is not None:
        return doc
    block = band_rows(n, BLOCK)  # the write's bands: whole row groups of the archive
    run = bucket_run((n + block - 1) // block)
    results: dict[int, dict[str, Any]] = {}
    calls = []
    for b, (_, a, z, g0) in enumerate(raw):
        prev = done(work, WL.bucket_piece(b))
        if prev is not None and "pieces" not in prev:
            raise BuildError(f"scan {name!r}: its work directory was left by an older lodbuilder; run the build "
                             "again with --force")
        if prev is not None:
            results[b] = prev
        else:
            calls.append((b, bucket_block, (work, b, int(g0), int(z) - int(a), fields, n, block, run, rows)))

    def record(res: dict[str, Any]) -> None:
        b = res["block"]
        results[b] = mark(work, WL.bucket_piece(b), res)
        prune(work, [WL.raw_xyz(b), WL.raw_attr(b)])  # (read by no other piece: see layout.consumers)

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
    pieces = [[p for r in results for p in r["pieces"][k]] for k in range(counts.shape[1])]
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
            for r0, xyz in zipped_blocks((store, WL.raw_xyz(b)), "<f8", 3 * m_b, 3 * rows):
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
    frad = [(WL.radius(b), a, z) for b, (a, z) in zip(bands, radii["bands"], strict=True)]
    fpar = [(WL.parent(b), a, z) for b, (a, z) in zip(bands, radii["bands"], strict=True)]
    with ScanWriter(part, name, n, metadata=metadata, encoding=encoding) as w:
        for b in range(int(buckets["buckets"])):
            k0 = b * block
            k1 = min(n, k0 + block)
            local = LocalStore(work)
            r = bucket_records(local, buckets["pieces"][b], rec)
            if r.shape[0] != k1 - k0:
                raise RuntimeError(f"bucket {b} holds {r.shape[0]} rows, expected {k1 - k0}")
            srt = np.empty(k1 - k0, rec)
            opaque_rows(srt)[r["pos"] - k0] = opaque_rows(r)
            del r
            g = _order_block(work, k0, k1)
            rad, par = segment(local, frad, "<f8", k0, k1), segment(local, fpar, "<i8", k0, k1)
            w.write(srt["xyz"], g, rad, par, attributes={k: srt[f"a{i}"] for i, k in enumerate(names)})
            report(progress, "write", k1, n)
        return w.finish(n_ordered=n, seeds=seeds, build=build, provenance=provenance)


def _order_block(work: Path, k0: int, k1: int) -> np.ndarray:
    from .merge import order_files

    return segment(LocalStore(work), order_files(LocalStore(work)), "<i8", k0, k1)
