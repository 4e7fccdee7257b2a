"""Writing a tiled scan into its part file, in stored (prefix) order, without holding it.

The points and attributes stay in the inputs (a copy in the work directory would be about the
archive's size again), in input order, and their stored positions in
``rank.<b>.i8`` (one file per read block: :mod:`.ranks`); the archive wants them in the merged order.
An external permutation does it in two passes: every read block is read from its input again and
split by destination block into bucket pieces (one record per point: position, coordinates,
attributes; a task per read block, :func:`bucket_block`, which checks that it reads the rows the
read phase read), then each bucket (a band of whole row groups of the archive: :func:`band_rows`)
is read, put in order and written as finished HDF5 chunks by a task of
its own (:mod:`.bands`). Memory: one bucket per task.

:func:`write_scan` is the same write by one process through the archive's
:class:`~lodbuilder.archive.scanwriter.ScanWriter` (the buckets in order): the reference the banded
write equals (tests compare the two).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...archive import layout as L
from ...errors import BuildError, InputError, ScanFileError
from ...progress import ProgressCallback, report
from . import layout as WL
from .store import LocalStore, Store, as_store
from .timing import timed_task
from .workdir import Spill, Zipped, opaque_rows, read_rows, segment, unzipped

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
def bucket_block(work: Store | str, b: int, source: Any, member: int | None, start: int, stop: int,
                 spec: dict[str, Any], crc: list[int], n: int, block: int) -> dict[str, Any]:
    """The first pass for read block ``b`` (a task): its points and attributes read from the input
    again (``source`` as :func:`.blocks.read_block` takes it, rows ``start .. stop``; checked
    against the read's sums ``crc``), with their stored positions (``rank.<b>.i8``), split by
    destination block (``block`` rows of the stored order) into the bucket pieces
    ``bucket.<k>.<b>.bin``, in input order."""
    from .blocks import block_rows, rows_sum

    w = as_store(work)
    stream, pose = source() if callable(source) else source
    fields = {k: (v[0], tuple(v[1])) for k, v in spec["fields"].items()}
    rec = record_dtype(fields)
    n_buckets = (n + block - 1) // block
    counts = np.zeros(n_buckets, np.int64)
    out: dict[str, Zipped] = {}
    sums = [0, 0]
    try:
        with w.open(WL.rank_file(b)) as fr:
            for pts, at in block_rows(stream, pose, member, start, stop, spec):
                sums = rows_sum(sums, pts, at)
                r = np.empty(pts.shape[0], rec)
                r["xyz"] = pts
                if at is not None:  # (None: no field kept)
                    for i in range(len(fields)):
                        r[f"a{i}"] = at[f"a{i}"]
                r["pos"] = read_rows(fr, np.dtype("<i8"), r.shape[0])
                _split(w, b, r, block, out, counts)
        if sums != [int(x) for x in crc]:
            raise ScanFileError(f"{stream.path}: rows {start} to {stop} are not the rows this build read from it "
                                "(the file changed during the build); run the build again")
        files = {name: f.commit() for name, f in out.items()}
    finally:
        for f in out.values():
            f.close()
    return {"block": b, "counts": counts.tolist(), "files": files}


def _split(w: Store, b: int, r: np.ndarray, block: int, out: dict[str, Zipped], counts: np.ndarray) -> None:
    """Records ``r`` of read block ``b`` (positions filled) appended to their buckets' pieces."""
    dest = r["pos"] // block
    order = np.argsort(dest.astype(np.int32), kind="stable")  # radix sort
    cuts = np.searchsorted(dest[order], np.arange(counts.shape[0] + 1))
    srt = opaque_rows(r)[order]
    for k in np.flatnonzero(np.diff(cuts)):
        name = WL.bucket(int(k), b)
        if name not in out:
            out[name] = Zipped(w.writer(name))
        out[name].write(srt[cuts[k]:cuts[k + 1]])
        counts[k] += cuts[k + 1] - cuts[k]


def buckets_phase(ex: Any, work: Any, name: str, sp: Spill, sources: list[tuple[Any, ...]],
                  progress: ProgressCallback = None) -> dict[str, Any]:
    """The first pass of the write as tasks, one per read block (or what a finished one recorded):
    each block read from its input again (``sources`` as the read phase took them; an input the
    parent holds, by the parent)."""
    from .pool import collect, submit
    from .sums import done, mark

    doc = done(work, "buckets")
    if doc is not None:
        return doc
    n, raw = sp.n, sp.blocks or []
    if sp.crcs is None or any(c is None for c in sp.crcs):
        raise BuildError(f"scan {name!r}: its work directory was left by an older lodbuilder; run the build "
                         "again with --force")
    block = band_rows(n, BLOCK)  # the write's bands: whole row groups of the archive
    spec = {"fields": {k: [v[0], list(v[1])] for k, v in sp.fields.items()}, "rows": sp.rows,
            "joint": len(sp.members) > 1 or sp.members[0].get("id") is not None}
    results: dict[int, dict[str, Any]] = {}
    calls: list[tuple[int, Any, tuple]] = []
    inline: list[tuple[int, Any, tuple]] = []
    for b, (i, a, z, _) in enumerate(raw):
        prev = done(work, WL.bucket_piece(b))
        if prev is not None:
            results[b] = prev
            continue
        stream, pose, member, reopen = sources[int(i)]
        args = (work, b, reopen if reopen is not None else (stream, pose), member, int(a), int(z), spec,
                sp.crcs[b], n, block)
        (calls if reopen is not None else inline).append((b, bucket_block, args))

    def record(res: dict[str, Any]) -> None:
        results[res["block"]] = mark(work, WL.bucket_piece(res["block"]), res)

    futs = submit(ex, calls)
    try:
        for _, fn, args in inline:
            record(fn(*args))
    finally:
        collect(futs, lambda b: f"the permutation of block {b + 1}", name, n, progress, "permute", record,
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
            r = np.concatenate([bucket_records(local, p, rec) for p in buckets["pieces"][b]] or [np.zeros(0, rec)])
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
