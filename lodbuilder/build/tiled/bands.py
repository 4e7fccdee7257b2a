"""Phase 7 of a tiled build: the part file written in bands of stored positions, by tasks.

The stored order is cut into *bands* of whole row groups of the archive (each band is one bucket of
the write's external permutation: :func:`band_rows`). A band task (:func:`write_band`) reads its
bucket's pieces, puts its points in stored order, takes their input indices, radii and parents
from the merge's and the radii's files, checks every row as the archive's scan writer does, and
filters its rows' datasets into finished HDF5 chunks (:func:`lodbuilder.archive.chunks.filter_rows`:
HDF5's own filters in an in-memory file with the archive's dataset creation properties). It
publishes their bytes as ``chunks.<b>.bin`` and its marker lists each chunk's size and filter
mask, the band's bounds, its entries of the radius index and two sums of its input indices.

The first band runs alone: its first row group decides the datasets' creation properties (the
*spec*: which datasets are worth compressing), as the scan writer decides them. Then the other
bands run at once, and the parent places every band's chunks, in stored order, as they arrive
(:class:`lodbuilder.archive.chunkwriter.ChunkWriter`: ``write_direct_chunk``, bytes copied, no
filter), and writes the small metadata. The part file is the one a single scan writer fed the
rows in order writes (same datasets, same bytes). Parent work: O(archive bytes) of copying, no
pass over the points.

Every input point stored exactly once: each band checks that its bucket fills its positions once
and that its input indices are distinct and in range; the parent checks that the bands' sums of
the input indices and of their squares (mod 2^64) are those of 0 .. n - 1.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ...archive import layout as L
from ...errors import BuildError, InputError
from ...progress import ProgressCallback, TaskCounts, report_tasks
from . import layout as WL
from .merge import order_files
from .pool import result, submit
from .store import as_store
from .sums import done, mark, prune
from .timing import timed_task
from .workdir import opaque_rows, segment
from .write import bucket_parts, damaged, record_dtype

MASK = (1 << 64) - 1


def index_sums(n: int) -> list[int]:
    """The sums of 0 .. n - 1 and of their squares, mod 2^64 (what the bands' sums add up to)."""
    return [(n * (n - 1) // 2) & MASK, ((n - 1) * n * (2 * n - 1) // 6) & MASK]


def _ordered(work: Path, band: int, k0: int, k1: int, fields: dict[str, Any], pieces: list[list[Any]],
             encoding: str) -> np.ndarray:
    """The band's bucket (its coordinates in ``encoding``): its points' records in stored order,
    each position filled once."""
    rec = record_dtype(fields, encoding)
    parts = bucket_parts(as_store(work), pieces, rec)  # (scattered piece by piece: no copy of the bucket)
    pos = np.concatenate([p["pos"] for p in parts]) - k0 if parts else np.zeros(0, np.int64)
    if pos.shape[0] != k1 - k0 or (pos.size and (pos.min() < 0 or pos.max() >= k1 - k0)) \
            or np.bincount(pos, minlength=k1 - k0).max(initial=1) != 1:
        raise InputError(f"bucket {band} holds {pos.shape[0]} rows, not each of positions {k0} to {k1} once")
    srt = np.empty(k1 - k0, rec)
    out, a = opaque_rows(srt), 0
    for p in parts:
        out[pos[a:a + p.shape[0]]] = opaque_rows(p)
        a += p.shape[0]
    return srt


def _arrays(work: Any, band: int, k0: int, k1: int, rows: int, args: dict[str, Any]) -> tuple[dict[str, Any], ...]:
    """The band's datasets as stored (the scan writer's order: source_index, radius, parent,
    points, attributes), checked as the scan writer checks them; and what the parent needs."""
    from ...archive.chunks import check_points, check_rows, encode_exactly
    from ...sampling.spacing import axis_max, axis_min

    n, name, bands = int(args["n"]), args["name"], args["radii_bands"]
    xyz = args.get("xyz", "float64")
    srt = _ordered(work, band, k0, k1, args["fields"], args["pieces"], xyz)
    radius = [(WL.radius(b), a, z) for b, (a, z) in enumerate(bands)]
    g = segment(work, order_files(work), "<i8", k0, k1)
    rad = segment(work, radius, "<f8", k0, k1)
    par = segment(work, [(WL.parent(b), a, z) for b, (a, z) in enumerate(bands)], "<i8", k0, k1)
    last = math.inf if k0 == 0 else float(segment(work, radius, "<f8", k0 - 1, k0)[0])
    where = f"scan {name!r}"
    offset, scale = L.metadata_scale(args["metadata"])
    pts = np.ascontiguousarray(L.decode_points(srt["xyz"], xyz, offset, scale))
    check_points(pts, where, k0)
    check_rows(g, rad, par, n, k0, last, where)
    if xyz == args["encoding"]:  # (the buckets hold the stored coordinates already)
        stored = np.ascontiguousarray(srt["xyz"])
    else:  # (buckets of an older lodbuilder: float64)
        stored = np.concatenate([encode_exactly(pts[a:a + rows], args["encoding"], offset, scale, where, k0 + a)
                                 for a in range(0, k1 - k0, rows)])
    arrays = {L.D_SOURCE_INDEX: g, L.D_RADIUS: rad, L.D_PARENT: par, L.D_POINTS: stored}
    for i, key in enumerate(args["fields"]):
        arrays[f"{L.G_ATTRIBUTES}/{key}"] = np.ascontiguousarray(srt[f"a{i}"])
    tail = np.flatnonzero((rad != 0) | (par != -1))
    gu = g.astype(np.uint64)
    info = {"lo": axis_min(pts).tolist(), "hi": axis_max(pts).tolist(), "last_radius": float(rad[-1]),
            "last_tail": k0 + int(tail[-1]) if tail.size else -1,
            "sums": [int(gu.sum(dtype=np.uint64)), int((gu * gu).sum(dtype=np.uint64))]}
    return arrays, info


@timed_task
def write_band(work: str, band: int, k0: int, k1: int, rows: int, spec: Any, args: dict[str, Any]) -> dict[str, Any]:
    """Band ``band`` (stored positions ``k0 .. k1``, whole row groups of ``rows``) as finished
    chunks (see the module); ``spec`` the datasets' creation properties, None for the first band
    (which decides them from its first row group and returns them). ``args``: the scan's name,
    ``n``, ``fields``, ``metadata``, ``encoding``, the band's bucket ``pieces`` and the radii's
    ``radii_bands``."""
    from ...archive.chunks import filter_rows, spec_of
    from ...archive.chunkwriter import radius_index

    w = as_store(work)
    try:
        arrays, info = _arrays(w, band, k0, k1, rows, args)
        if spec is None:  # (the scan writer's checks of the attributes' names and dtypes, once)
            for key, (dt, _) in args["fields"].items():
                L.check_name(key, "attribute name")
                if np.dtype(dt).kind not in "biuf":
                    raise InputError(f"attribute {key!r} of scan {args['name']!r} has dtype {np.dtype(dt)}; store "
                                     "numbers (bool, int, float)")
            spec = spec_of({k: a[:rows] for k, a in arrays.items()})
        table, blob = filter_rows(spec, rows, arrays)
    except InputError as exc:
        raise damaged(args["name"], exc) from None
    files = {WL.chunks(band): as_store(w).put(WL.chunks(band), np.frombuffer(blob, np.uint8))}
    return {"band": band, "k0": k0, "k1": k1, "spec": spec, "table": table,
            "rindex": radius_index(arrays[L.D_RADIUS], k0).tolist(), **info, "files": files}


def write_phase(ex: Any, work: Any, part: Path, name: str, sp: Any, finish: Callable[[], dict[str, Any]],
                buckets: dict[str, Any], radii: dict[str, Any], progress: ProgressCallback = None) -> Any:
    """The part file ``part`` from the band tasks' chunks (finished bands a resume finds are not
    redone); ``finish()`` the keywords of :meth:`ScanWriter.finish` (asked for once every band is
    placed). Returns the PartInfo."""
    from ...archive.chunkwriter import ChunkWriter

    n, block = sp.n, int(buckets["block"])
    rows = L.row_group_rows(n)
    if block % rows:
        raise BuildError(f"scan {name!r}: the tiled build's buckets of {block} rows are not whole row groups of "
                         f"{rows}; run the build again with --force")
    bands = [(k0, min(n, k0 + block)) for k0 in range(0, n, block)]
    args = {"name": name, "n": n, "fields": sp.fields, "metadata": sp.metadata, "encoding": sp.encoding,
            "xyz": buckets.get("xyz", "float64"), "radii_bands": radii["bands"]}
    got = {b: doc for b in range(len(bands)) if (doc := done(work, WL.chunks_piece(b))) is not None}

    def call(b: int, spec: Any) -> tuple[int, Any, tuple]:
        return (b, write_band, (work, b, *bands[b], rows, spec, {**args, "pieces": buckets["pieces"][b]}))

    runs: dict[range, list[str]] = {}  # the bucket files by the run of bands they hold
    for f in {p[0] for pieces in buckets["pieces"] for p in pieces}:
        runs.setdefault(WL.bucket_range(f), []).append(f)

    def drop() -> None:  # the bucket files of runs whose bands are all written: read by no one now
        for ks in [ks for ks in runs if all(k in got for k in ks)]:
            prune(work, sorted(runs.pop(ks)))

    if 0 not in got:  # the first band alone: it decides the datasets' creation properties
        _run(work, name, submit(ex, [call(0, None)]), bands, got, progress, drop)
    # the other bands run while the part file is made and the first band placed
    running = submit(ex, [call(b, got[0]["spec"]) for b in range(len(bands)) if b not in got])
    try:
        with ChunkWriter(part, name, n, got[0]["spec"], metadata=sp.metadata, encoding=sp.encoding) as w:
            placed = [0]

            def place() -> None:  # every band in stored order as soon as the ones before it are placed
                while placed[0] < len(bands) and placed[0] in got:
                    _place(w, work, got[placed[0]])
                    placed[0] += 1

            def then() -> None:
                place()
                drop()

            place()
            _run(work, name, running, bands, got, progress, then)
            sums = [sum(int(got[b]["sums"][i]) for b in got) & MASK for i in range(2)]
            if sums != index_sums(n):
                raise damaged(name, InputError(f"source_index of scan {name!r} repeats an input index"))
            return w.finish(n_ordered=n, **finish())
    except BaseException:
        for f in running:
            f.cancel()
        raise


def _run(work: Any, name: str, running: dict[cf.Future, int], bands: list[tuple[int, int]],
         got: dict[int, dict[str, Any]], progress: ProgressCallback, then: Callable[[], None] | None = None) -> None:
    """Wait for the submitted band tasks ``running`` (future -> band); mark each one as it finishes
    (into ``got``), then call ``then``. Progress: the phase's tasks and points (a failure names the
    band and its positions)."""
    n_all = bands[-1][1]

    def tell() -> None:
        pts = sum(bands[b][1] - bands[b][0] for b in got)
        report_tasks(progress, "write", TaskCounts(len(got), len(bands), pts, n_all, len(running), "band"))

    tell()
    try:
        while running:
            fin, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
            for fut in fin:
                b = running.pop(fut)
                k0, k1 = bands[b]
                res = result(fut, name, f"the write of band {b + 1} of {len(bands)} (positions {k0} to {k1})")
                got[b] = mark(work, WL.chunks_piece(b), res)
                tell()
                if then is not None:
                    then()
    except BaseException:
        for f in running:
            f.cancel()
        raise


def _place(w: Any, work: Any, doc: dict[str, Any]) -> None:
    """One band's chunks into the part file."""
    blob = as_store(work).get(WL.chunks(int(doc["band"])))
    w.write_chunks(int(doc["k0"]), int(doc["k1"]), doc["table"], blob, bounds=(doc["lo"], doc["hi"]),
                   radius_index=np.array([float(x) for x in doc["rindex"]]), last_tail=int(doc["last_tail"]),
                   last_radius=float(doc["last_radius"]))
