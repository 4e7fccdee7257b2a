"""Writing a tiled scan into its part file, in stored (prefix) order, without holding it.

The points, attributes and ranks sit in input order in the work directory; the archive wants them
in the merged order. An external permutation does it in two sequential passes: every input block
is split by destination block into bucket files (one record per point: position, coordinates,
attributes), then each bucket is read, put in order and handed to the archive's
:class:`~lodbuilder.archive.scanwriter.ScanWriter` with its radii and parents. Memory: one block.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import BuildError, InputError
from ...progress import ProgressCallback, report
from . import layout as WL
from .sums import SumFile
from .workdir import attr_file, blocks, opaque_rows, point_blocks

BLOCK = 1 << 18  # rows per destination bucket (one bucket is in memory at a time)


def record_dtype(fields: dict[str, tuple[str, tuple[int, ...]]]) -> np.dtype:
    spec: list[Any] = [("pos", "<i8"), ("xyz", "<f8", (3,))]
    for i, (_, (dt, shape)) in enumerate(fields.items()):
        spec.append((f"a{i}", dt, tuple(shape)) if shape else (f"a{i}", dt))
    return np.dtype(spec)


def bucket_points(work: Path, n: int, fields: dict[str, tuple[str, tuple[int, ...]]],
                  progress: ProgressCallback = None, block: int | None = None) -> dict[str, Any]:
    """The first pass: every input block split by destination block into bucket files."""
    block = block or BLOCK
    rec = record_dtype(fields)
    names = list(fields)
    n_buckets = (n + block - 1) // block
    files = [SumFile(work / WL.bucket(b)) for b in range(n_buckets)]
    attr_iters = [blocks(attr_file(work, i), np.dtype(fields[k][0]), n * int(np.prod(fields[k][1] or (1,))),
                         block * int(np.prod(fields[k][1] or (1,)))) for i, k in enumerate(names)]
    try:
        with open(work / WL.RANK, "rb") as fr:
            for g0, pts in point_blocks(work, n, block):
                m = pts.shape[0]
                r = np.empty(m, rec)
                r["pos"] = np.fromfile(fr, dtype="<i8", count=m)
                r["xyz"] = pts
                for i, it in enumerate(attr_iters):
                    _, a = next(it)
                    shape = fields[names[i]][1]
                    r[f"a{i}"] = a.reshape(m, *shape) if shape else a
                dest = r["pos"] // block
                order = np.argsort(dest.astype(np.int32), kind="stable")  # radix sort
                cuts = np.searchsorted(dest[order], np.arange(n_buckets + 1))
                srt = opaque_rows(r)[order]
                for b in range(n_buckets):
                    if cuts[b + 1] > cuts[b]:
                        files[b].write(srt[cuts[b]:cuts[b + 1]])
                report(progress, "permute", g0 + m, n)
    finally:
        for f in files:
            f.close()
        for it in attr_iters:
            with contextlib.suppress(Exception):
                it.close()  # type: ignore[attr-defined]
    return {"block": block, "buckets": n_buckets, "files": {f.path.name: f.sum for f in files}}


def write_scan(work: Path, part: Path, name: str, n: int, fields: dict[str, tuple[str, tuple[int, ...]]],
               metadata: dict[str, Any], encoding: str, seeds: np.ndarray, build: dict[str, Any],
               provenance: dict[str, Any], progress: ProgressCallback = None,
               buckets: dict[str, Any] | None = None) -> Any:
    """Write the bucketed points (:func:`bucket_points`, done first if ``buckets`` is None) in
    stored order as the part ``part``, with their radii and parents."""
    if buckets is None:
        buckets = bucket_points(work, n, fields, progress)
    try:
        return _write_buckets(work, part, name, n, fields, metadata, encoding, seeds, build, provenance, progress,
                              buckets)
    except InputError as exc:  # the scan writer's own check: the work files disagree with each other
        what = str(exc).split(";")[0]
        raise BuildError(f"scan {name!r}: the tiled build's work files disagree ({what}); they are damaged: run "
                         "the build again with --force") from None


def _write_buckets(work: Path, part: Path, name: str, n: int, fields: dict[str, tuple[str, tuple[int, ...]]],
                   metadata: dict[str, Any], encoding: str, seeds: np.ndarray, build: dict[str, Any],
                   provenance: dict[str, Any], progress: ProgressCallback, buckets: dict[str, Any]) -> Any:
    from ...archive.scanwriter import ScanWriter

    block = int(buckets["block"])
    rec = record_dtype(fields)
    names = list(fields)
    with ScanWriter(part, name, n, metadata=metadata, encoding=encoding) as w, \
            open(work / WL.RADIUS, "rb") as frad, open(work / WL.PARENT, "rb") as fpar:
        for b in range(int(buckets["buckets"])):
            path = work / WL.bucket(b)
            k0 = b * block
            k1 = min(n, k0 + block)
            r = np.fromfile(path, dtype=rec)
            if r.shape[0] != k1 - k0:
                raise RuntimeError(f"bucket {b} holds {r.shape[0]} rows, expected {k1 - k0}")
            srt = np.empty(k1 - k0, rec)
            opaque_rows(srt)[r["pos"] - k0] = opaque_rows(r)
            del r
            g = _order_block(work, k0, k1)
            rad = np.fromfile(frad, dtype="<f8", count=k1 - k0)
            par = np.fromfile(fpar, dtype="<i8", count=k1 - k0)
            w.write(srt["xyz"], g, rad, par, attributes={k: srt[f"a{i}"] for i, k in enumerate(names)})
            report(progress, "write", k1, n)
        return w.finish(n_ordered=n, seeds=seeds, build=build, provenance=provenance)


def _order_block(work: Path, k0: int, k1: int) -> np.ndarray:
    with open(work / WL.ORDER, "rb") as f:
        f.seek(k0 * 8)
        return np.fromfile(f, dtype="<i8", count=k1 - k0)
