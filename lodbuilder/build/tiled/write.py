"""Writing a tiled scan into its part file, in stored (prefix) order, without holding it.

The points and attributes stay in the inputs (a copy in the work directory would be about the
archive's size again), in input order, and their stored positions in ``rank.<b>.i8`` (one file per
read block: :mod:`.ranks`); the archive wants them in the merged order. An external permutation
does it in two passes: every read block is read from its input again and split by destination
block into bucket pieces (one record per point: position, coordinates, attributes; a task per read
block, :func:`bucket_block`, which checks that it reads the rows the read phase read), then each
bucket (a band of whole row groups of the archive: :func:`band_rows`) is read, put in order and
written as finished HDF5 chunks by a task of
its own (:mod:`.bands`). Memory: one bucket per task.

:func:`write_scan` is the same write by one process through the archive's
:class:`~lodbuilder.archive.scanwriter.ScanWriter` (the buckets in order): the reference the banded
write equals (tests compare the two).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np

from ...archive import layout as L
from ...errors import BuildError, InputError, ScanFileError
from ...progress import ProgressCallback, report
from . import layout as WL
from .store import LocalStore, Store, as_store
from .timing import timed_task
from .workdir import BUCKET_ZIP_LEVEL, Spill, opaque_rows, read_rows, segment, unzipped

BLOCK = 1 << 18  # rows per destination bucket (one bucket is in memory at a time)
BUCKET_FILES = 16  # bucket files per read block, at most (see bucket_run)


def record_dtype(fields: dict[str, tuple[str, tuple[int, ...]]], encoding: str = "float64") -> np.dtype:
    """A bucket record: stored position, coordinates as the archive stores them (``encoding``, one of
    :data:`lodbuilder.archive.layout.ENCODINGS`, each a NumPy dtype's name; the buckets are the peak
    of a survey's work files, and float64 made them 1.27-1.54 x an int32 archive), attributes."""
    if encoding not in L.ENCODINGS:
        raise ValueError(f"unknown coordinate encoding {encoding!r}")
    spec: list[Any] = [("pos", "<i8"), ("xyz", np.dtype(encoding).newbyteorder("<"), (3,))]
    for i, (_, (dt, shape)) in enumerate(fields.items()):
        spec.append((f"a{i}", dt, tuple(shape)) if shape else (f"a{i}", dt))
    return np.dtype(spec)


def bucket_records(store: Store, pieces: list[list[Any]], rec: np.dtype) -> np.ndarray:
    """The records of a bucket from its pieces (``[file, start, end]``: one compressed frame each,
    in block order; a file's frames read in one request)."""
    parts = bucket_parts(store, pieces, rec)
    return np.concatenate(parts) if parts else np.zeros(0, rec)


def bucket_parts(store: Store, pieces: list[list[Any]], rec: np.dtype) -> list[np.ndarray]:
    """:func:`bucket_records` piece by piece (not copied into one array)."""
    where: dict[str, list[int]] = {}
    for i, p in enumerate(pieces):
        where.setdefault(p[0], []).append(i)
    blobs: list[bytes] = [b""] * len(pieces)
    for name, idx in where.items():
        got = store.read_ranges(name, [int(pieces[i][1]) for i in idx], [int(pieces[i][2]) for i in idx])
        for i, data in zip(idx, got, strict=True):
            blobs[i] = data
    return [unzipped(data, rec, p[0]) for data, p in zip(blobs, pieces, strict=True)]


def bucket_run(n_buckets: int) -> int:
    """Buckets per bucket file: a read block writes at most :data:`BUCKET_FILES` files, whatever the
    number of bands (blocks x bands files made a 10^8-point survey's permutation write 307,800)."""
    return max(1, -(-n_buckets // BUCKET_FILES))


@timed_task
def bucket_block(work: Store | str, b: int, source: Any, member: int | None, start: int, stop: int,
                 spec: dict[str, Any], crc: list[int], n: int, block: int, run: int) -> dict[str, Any]:
    """The first pass for read block ``b`` (a task): its points and attributes read from the input
    again (``source`` as :func:`.blocks.read_block` takes it, rows ``start .. stop``; checked
    against the read's sums ``crc``), with their stored positions (``rank.<b>.i8``), split by
    destination block (``block`` rows of the stored order) into pieces, in input order: one
    compressed frame per piece, in the bucket files ``bucket.<k0>_<k1>.<b>.bin`` of ``run``
    consecutive buckets. Returns each bucket's pieces as ``[file, start, end]``."""
    from .blocks import block_rows, rows_sum

    w = as_store(work)
    stream, pose = source() if callable(source) else source
    fields = {k: (v[0], tuple(v[1])) for k, v in spec["fields"].items()}
    enc, offset, scale = spec["xyz"]
    rec = record_dtype(fields, enc)
    n_buckets = (n + block - 1) // block
    out = _Buckets(w, b, n_buckets, run)
    sums = [0, 0]
    stored: np.ndarray | None = np.empty(0)
    try:
        with w.open(WL.rank_file(b)) as fr:
            for pts, at in block_rows(stream, pose, member, start, stop, spec):
                sums = rows_sum(sums, pts, at)
                r = np.empty(pts.shape[0], rec)
                stored = L.encode_as(pts, enc, offset, scale)  # (the read phase found every row exact)
                if stored is None:
                    break  # (not the rows the read read: said below)
                r["xyz"] = stored
                if at is not None:  # (None: no field kept)
                    for i in range(len(fields)):
                        r[f"a{i}"] = at[f"a{i}"]
                r["pos"] = read_rows(fr, np.dtype("<i8"), r.shape[0])
                out.split(r, block)
        if stored is None or sums != [int(x) for x in crc]:
            raise ScanFileError(f"{stream.path}: rows {start} to {stop} are not the rows this build read from it "
                                "(the file changed during the build); run the build again")
        files = {name: f.commit() for name, f in out.out.items()}
    finally:
        for f in out.out.values():
            f.close()
    return {"block": b, "counts": out.counts.tolist(), "pieces": out.pieces, "files": files}


class _Buckets:
    """The bucket files of read block ``b`` being written (``run`` consecutive buckets a file): each
    bucket's pieces (``[file, start, end]``) and rows."""

    def __init__(self, w: Store, b: int, n_buckets: int, run: int) -> None:
        import zstandard

        self.w, self.b, self.n_buckets, self.run = w, b, n_buckets, run
        self.counts = np.zeros(n_buckets, np.int64)
        self.pieces: list[list[list[Any]]] = [[] for _ in range(n_buckets)]
        self.zc = zstandard.ZstdCompressor(level=BUCKET_ZIP_LEVEL)
        self.out: dict[str, Any] = {}
        self.ends: dict[str, int] = {}

    def split(self, r: np.ndarray, block: int) -> None:
        """Records ``r`` (positions filled) appended to their buckets, one frame per bucket."""
        dest = r["pos"] // block
        order = np.argsort(dest.astype(np.int32), kind="stable")  # radix sort
        cuts = np.searchsorted(dest[order], np.arange(self.n_buckets + 1))
        srt = opaque_rows(r)[order]
        for k in np.flatnonzero(np.diff(cuts)):
            k0 = int(k) // self.run * self.run
            name = WL.bucket(k0, min(self.n_buckets, k0 + self.run), self.b)
            if name not in self.out:
                self.out[name], self.ends[name] = self.w.writer(name), 0
            frame = self.zc.compress(cast(Any, np.ascontiguousarray(srt[cuts[k]:cuts[k + 1]])))
            self.out[name].write(frame)
            self.pieces[k].append([name, self.ends[name], self.ends[name] + len(frame)])
            self.ends[name] += len(frame)
            self.counts[k] += cuts[k + 1] - cuts[k]


def buckets_phase(ex: Any, work: Any, name: str, sp: Spill, sources: list[tuple[Any, ...]],
                  progress: ProgressCallback = None) -> dict[str, Any]:
    """The first pass of the write as tasks, one per read block (or what a finished one recorded):
    each block read from its input again (``sources`` as the read phase took them; an input the
    parent holds, by the parent)."""
    from .pool import collect, submit
    from .sums import done, mark, prune

    doc = done(work, "buckets")
    if doc is not None:
        return doc
    n, raw = sp.n, sp.blocks or []
    if sp.crcs is None or any(c is None for c in sp.crcs):
        raise BuildError(f"scan {name!r}: its work directory was left by an older lodbuilder; run the build "
                         "again with --force")
    block = band_rows(n, BLOCK)  # the write's bands: whole row groups of the archive
    run = bucket_run((n + block - 1) // block)
    spec = {"fields": {k: [v[0], list(v[1])] for k, v in sp.fields.items()}, "rows": sp.rows,
            "joint": len(sp.members) > 1 or sp.members[0].get("id") is not None,
            "xyz": [sp.encoding, *(None if x is None else x.tolist() for x in L.metadata_scale(sp.metadata))]}
    results: dict[int, dict[str, Any]] = {}
    calls: list[tuple[int, Any, tuple]] = []
    inline: list[tuple[int, Any, tuple]] = []
    for b, (i, a, z, _) in enumerate(raw):
        prev = done(work, WL.bucket_piece(b))
        if prev is not None and "pieces" not in prev:
            raise BuildError(f"scan {name!r}: its work directory was left by an older lodbuilder; run the build "
                             "again with --force")
        if prev is not None:
            results[b] = prev
            prune(work, [WL.rank_file(b)])  # (a build stopped between the marker and the deletion)
            continue
        stream, pose, member, reopen = sources[int(i)]
        args = (work, b, reopen if reopen is not None else (stream, pose), member, int(a), int(z), spec,
                sp.crcs[b], n, block, run)
        (calls if reopen is not None else inline).append((b, bucket_block, args))

    def record(res: dict[str, Any]) -> None:
        results[res["block"]] = mark(work, WL.bucket_piece(res["block"]), res)
        prune(work, [WL.rank_file(res["block"])])  # (its last reader: see layout.consumers)

    futs = submit(ex, calls)
    try:
        for _, fn, args in inline:
            record(fn(*args))
    finally:
        collect(futs, lambda b: f"the permutation of block {b + 1}", name, n, progress, "permute", record,
                lambda r: int(np.sum(r["counts"])), sum(int(np.sum(r["counts"])) for r in results.values()))
    doc = bucket_pieces([results[b] for b in range(len(raw))], block)
    return mark(work, "buckets", {**doc, "xyz": sp.encoding})


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
    enc = buckets.get("xyz", "float64")  # (a work directory of an older lodbuilder: float64)
    rec = record_dtype(fields, enc)
    offset, scale = L.metadata_scale(metadata)
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
            w.write(L.decode_points(srt["xyz"], enc, offset, scale), g, rad, par,
                    attributes={k: srt[f"a{i}"] for i, k in enumerate(names)})
            report(progress, "write", k1, n)
        return w.finish(n_ordered=n, seeds=seeds, build=build, provenance=provenance)


def _order_block(work: Path, k0: int, k1: int) -> np.ndarray:
    from .merge import order_files

    return segment(LocalStore(work), order_files(LocalStore(work)), "<i8", k0, k1)
