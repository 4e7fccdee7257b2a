"""One scan build as a self-contained job: what runs on a worker (the calling process, a local
process or a Dask worker).

``build_one(job)`` reads the scan (or takes the in-memory one), applies its pose, orders it and
writes a one-scan *part* archive with the archive writer (atomically: a killed worker leaves no
part). The parent merges finished parts into the archive. Workers need the part directory on a
file system they share with the parent (always true for a local pool or LocalCluster).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import mmap
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._resources import (
    TRIM_MIN_POINTS,
    PassMap,
    drop_library_pages,
    map_large_blocks,
    release_pages,
)
from ..errors import EmptyScanError
from ..io.crs import KEY_REPROJECTION
from ..progress import ProgressCallback
from .options import BuildOptions

log = logging.getLogger(__name__)


@dataclass
class ScanJob:
    """Everything a worker needs to build one scan (picklable; ``scan`` holds an in-memory
    :class:`~lodbuilder.io.Scan` given to the API, and then the job runs in the calling process)."""

    name: str
    path: str | None
    key: str
    part: str
    options: BuildOptions = field(default_factory=BuildOptions)
    pose: list[list[float]] | None = None
    scan_index: int | None = None
    sha256: str | None = ""
    size_bytes: int | None = 0
    scan: Any = None
    pose_kind: str = "rigid"
    tiled: bool = False
    members: list[dict[str, Any]] = field(default_factory=list)
    given: str | None = None  # the path as the caller wrote it (for messages)
    work_url: str | None = None  # where the tiled build's work files go (None: beside the part)

    @property
    def source(self) -> str:
        if self.members:
            return f"{len(self.members)} scans (joint)"
        if self.path is None:
            return "<in-memory scan>"
        return self.given or self.path

    @property
    def work(self) -> Path:
        """The tiled build's work directory (beside its part file: a resumed build finds it)."""
        part = Path(self.part)
        return part.with_name(part.name[: -len(".h5")] + ".work")

    @property
    def work_store(self) -> Any:
        """Where the tiled build keeps its work files (:mod:`lodbuilder.build.tiled.store`): the
        work directory, or ``<work_url>/<archive>/<part>.work`` (a resumed build finds it too)."""
        from .tiled.store import as_store

        if self.work_url is None:
            return as_store(self.work)
        part = Path(self.part)
        archive = part.parent.name.strip(".")[: -len(".parts")]
        return as_store(f"{self.work_url.rstrip('/')}/{archive}/{self.work.name}")


def job_key(sha256: str | None, params: dict[str, Any], pose: Any, scan_index: int | None, name: str) -> str:
    """Hash of everything that determines a built scan: source bytes, parameters, pose, scan index,
    name. The same key means the archive's scan is up to date (the resume key of every build)."""
    from .. import __version__

    payload = {
        "sha256": sha256,
        "params": {k: params.get(k) for k in sorted(params)},
        "pose": None if pose is None else np.asarray(pose, dtype=np.float64).round(15).tolist(),
        "scan_index": scan_index,
        "name": name,
        "schema": 1,
        "lodbuilder": __version__.split("+")[0],
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


def scan_digest(scan: Any) -> str:
    """SHA-256 of an in-memory scan's coordinates and attributes (its resume key's source)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(scan.points, dtype=np.float64).tobytes())
    for k in sorted(scan.attributes):
        a = np.ascontiguousarray(scan.attributes[k])
        h.update(k.encode())
        h.update(str(a.dtype).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def read_job_scan(job: ScanJob) -> Any:
    """The job's scan, read (or taken from memory), named and posed."""
    from ..io import read_scan, read_scans
    from ..io.pose import apply_pose

    crs, override = job.options.crs, job.options.crs_override
    if job.scan is not None:
        # the caller's Scan keeps its name, points and metadata
        scan = dataclasses.replace(job.scan, metadata=dict(job.scan.metadata))
        if crs is not None:
            from ..io.crs import assign_crs

            assign_crs(scan.metadata, crs, override=override, what=f"scan {job.name!r}")
    elif job.scan_index is None:
        scan = read_scan(job.path, name=job.name, crs=crs, crs_override=override)  # type: ignore[arg-type]
    else:
        scan = read_scans(job.path, crs=crs, crs_override=override)[job.scan_index]  # type: ignore[arg-type]
    scan.name = job.name
    if job.pose is not None:
        scan.points = np.ascontiguousarray(apply_pose(scan.points, np.asarray(job.pose)))
    if job.options.to_crs is not None:
        from ..io.crs import reproject_scan

        reproject_scan(scan, job.options.to_crs)
    return scan


def provenance(job: ScanJob, reader: str) -> dict[str, Any]:
    """The one provenance record of a built scan: source file name, size, SHA-256 and reader."""
    return {
        "source_name": None if job.path is None else Path(job.path).name,
        "source_size": job.size_bytes if job.path is not None else None,
        "source_sha256": job.sha256 if job.path is not None else None,
        "reader": reader,
    }


def build_record_of(job: ScanJob, progress: ProgressCallback = None) -> tuple[Any, dict[str, float]]:
    """Read and order the job's scan in memory; returns ``(ScanRecord, phase seconds)``.

    A scan read from a file of at least ASIDE_MIN_POINTS points waits in the job's work directory
    while it is ordered (see :func:`set_aside`); :func:`build_one` removes that directory."""
    from ..progress import report
    from .record import build_record

    t0 = time.perf_counter()
    report(progress, "read", 0, 1)
    scan = read_job_scan(job)
    report(progress, "read", 1, 1)
    t_read = time.perf_counter() - t0
    if job.scan is None and not job.options.features and len(scan) >= ASIDE_MIN_POINTS:
        progress = set_aside(scan, job.work, progress)
    if len(scan) >= TRIM_MIN_POINTS:
        map_large_blocks()  # (freed temporaries go back to the system at once)
        load_kernels(progress)
    rec = build_record(scan, job.options, progress=progress)
    t_order = time.perf_counter() - t0 - t_read
    return rec, {"read": t_read, "order": t_order}


ASIDE_MIN_POINTS = 200_000  # below this a scan's arrays are a few MB: not worth two files


def load_kernels(progress: ProgressCallback = None) -> None:
    """Load every kernel of the engine now (compiling them first when numba's cache is cold), then
    give the pages of the compiler's code and of every other library's back
    (:func:`lodbuilder._resources.drop_library_pages`). Loaded on first call instead, each kernel
    brings some of LLVM's code back into the process in the middle of its phase (about 10 MiB of
    it at the ordering's peak)."""
    from .._kernels.warm import compile_group, ensure_compiled

    with _numba_without_scipy():
        ensure_compiled(progress)
        for group in ("band", "thin", "ordering"):
            compile_group(group)
    drop_library_pages()


@contextlib.contextmanager
def _numba_without_scipy() -> Any:
    """numba's first kernel load sets up its compiler's implementations, and one of them checks
    whether scipy's BLAS is there (for np.dot of two vectors in compiled code: BLAS, else a loop)
    by importing scipy.linalg: 14 MiB of the build process for code no kernel here uses. While
    numba sets up, ``scipy.linalg`` cannot be imported (numba then takes the loop; a compiled
    np.dot of matrices imports scipy itself later); nothing changes when scipy.linalg is already
    imported (by the caller) or numba already set up."""
    import sys

    if "scipy.linalg" in sys.modules:
        yield
        return
    sys.modules["scipy.linalg"] = None  # type: ignore[assignment]
    try:
        yield
    finally:
        if "scipy.linalg" in sys.modules and sys.modules["scipy.linalg"] is None:
            del sys.modules["scipy.linalg"]


def set_aside(scan: Any, work: Path, progress: ProgressCallback = None) -> ProgressCallback:
    """Move ``scan``'s points and attributes into files of the work directory ``work`` and map
    them back (copy-on-write: the same values, dtypes and shapes), so that they take no memory of their
    own while the engine orders the points: the attributes are not read until the archive is
    written, the points only while the band is built, a pass at a time (the points are a
    :class:`~lodbuilder._resources.PassMap`: the band gives their pages back after each pass over
    them). Returns ``progress`` wrapped to give the points' pages back to the file once the band
    stage reports it is done (a page read after that comes back from the file). Arrays numpy
    cannot store without pickling stay in memory."""
    from ..archive.files import make_own_dir
    from ..progress import report

    try:
        make_own_dir(work, work.name)
        pts = _map_aside(scan.points, work / "points.bin")
        maps = {key: _map_aside(arr, work / f"a{i}.bin")
                for i, (key, arr) in enumerate(scan.attributes.items()) if not arr.dtype.hasobject}
    except OSError as exc:  # a full disk, a work directory that is not ours, ...: order it in memory
        log.info("scan %r stays in memory while it is ordered: %s", scan.name, exc)
        return progress
    scan.points = points = np.ndarray(scan.points.shape, scan.points.dtype, buffer=pts)
    for key, mm in maps.items():
        arr = scan.attributes[key]
        scan.attributes[key] = np.ndarray(arr.shape, arr.dtype, buffer=mm)

    def aside_progress(stage: str, done: int, total: int) -> None:
        if stage == "band" and done == total:
            release_pages(points)
        report(progress, stage, done, total)

    return aside_progress


def _map_aside(arr: np.ndarray, path: Path) -> mmap.mmap:
    """Write ``arr``'s bytes (C order) to ``path`` and map the file copy-on-write: never written
    back, and writeable like the array it replaces (a read-only array is another type to numba,
    and every kernel it reached would be compiled a second time)."""
    np.ascontiguousarray(arr).tofile(path)
    with open(path, "rb") as f:
        return PassMap(f.fileno(), 0, access=mmap.ACCESS_COPY) if arr.nbytes else mmap.mmap(-1, 1)


def build_one(job: ScanJob, progress: ProgressCallback = None) -> dict[str, Any]:
    """Build ``job`` into its part archive; return a summary (runs on a worker)."""
    from ..archive.files import remove_own_dir

    try:
        return _build_one(job, progress)
    finally:
        with contextlib.suppress(OSError):  # (a directory that is not lodbuilder's is left alone)
            remove_own_dir(job.work, job.work.name)  # what set_aside left (the maps stay valid)


def _build_one(job: ScanJob, progress: ProgressCallback) -> dict[str, Any]:
    from ..archive.reader import open_archive
    from ..archive.writer import write_archive
    from ..progress import report

    t0 = time.perf_counter()
    rec, phases = build_record_of(job, progress)
    o = job.options
    rec.build.update({
        "voxel_size_requested": o.voxel_size,
        "band_radius_requested": o.band_radius,
        "size_requested": o.size,
        "rho_requested": o.rho,
        "seeds_given": o.seeds is not None,
        "pose": job.pose,
        "pose_kind": job.pose_kind,
        "scan_index": job.scan_index,
        "collection_key": job.key,
        "method": "in-memory",
        "seconds_read": round(phases["read"], 4),
        "seconds_order": round(phases["order"], 4),
        "worker_pid": os.getpid(),
    })
    rec.provenance.update(provenance(job, rec.scan.reader))
    if KEY_REPROJECTION in rec.scan.metadata:
        rec.provenance[KEY_REPROJECTION] = rec.scan.metadata[KEY_REPROJECTION]
    t1 = time.perf_counter()
    report(progress, "write", 0, 1)
    write_archive(job.part, [rec])
    report(progress, "write", 1, 1)
    phases["write"] = time.perf_counter() - t1
    with open_archive(job.part) as arc:
        encoding = arc.scan(job.name).encoding
    return {
        "name": job.name,
        "part": job.part,
        "n_points": len(rec.scan),
        "n_ordered": len(rec.ordering),
        "encoding": encoding,
        "method": "in-memory",
        "seconds": round(time.perf_counter() - t0, 4),
        "phases": {k: round(v, 4) for k, v in phases.items()},
        "worker_pid": os.getpid(),
    }


# ------------------------------------------------------------------------------------ tiled

def tiled_sources(job: ScanJob) -> list[tuple[Any, Any, int | None, Any]]:
    """The streams of a tiled job: ``(stream, pose, member id, reopen)`` for each scan it orders.
    ``reopen`` (a picklable :class:`TiledInput`) opens the same stream again on a worker; None for
    a scan held in memory or read whole (a format that does not stream: the parent hands it out)."""
    from ..io.stream import scan_stream

    crs, override = job.options.crs, job.options.crs_override
    if job.scan is not None:
        scan = read_job_scan(job)  # the in-memory scan with its CRS (reprojected already)
        return [(scan_stream(scan), None, None, None)]
    members = job.members or [{"path": job.path, "scan_index": job.scan_index, "pose": job.pose}]
    out = [(_member_stream(job, m, crs, override), m.get("pose"), i if job.members else None)
           for i, m in enumerate(members)]
    kept = [(o, m) for o, m in zip(out, members, strict=True) if o[0].n_points > 0]
    if not kept:
        raise EmptyScanError(f"joint scan {job.name!r}: " + ("its input holds no points" if len(members) == 1 else
                             f"none of its {len(members)} inputs holds a point") + "; nothing to build")
    for (s, _, i), m in zip(out, members, strict=True):
        if s.n_points == 0:
            log.warning("%s holds no points: member %d of the joint scan %r, with none", m["path"], i, job.name)
    target = one_crs([o for o, _ in kept], [Path(m["path"]).name for _, m in kept], job.options.to_crs)
    return [(s, pose, member, None) if s.n_points == 0 else
            (*to_target(s, pose, member, target),
             TiledInput(str(m["path"]), m.get("scan_index"), crs, override, target, pose) if s.streams else None)
            for (s, pose, member), m in zip(out, members, strict=True)]


def _member_stream(job: ScanJob, m: dict[str, Any], crs: str | None, override: bool) -> Any:
    """The stream of one input of a tiled job; a joint scan's input that holds no points (a survey
    tile over water, say) is a member with none (an empty stream), not a failed build."""
    from ..io.stream import PointStream, open_stream

    try:
        return open_stream(m["path"], scan_index=m.get("scan_index"), crs=crs, crs_override=override)
    except EmptyScanError:
        if not job.members:
            raise
    return PointStream(Path(m["path"]), str(m.get("name")), "empty", 0, {}, {}, False, lambda *_: iter(()))


@dataclass(frozen=True)
class TiledInput:
    """How a worker opens one input of a tiled job again: the file, its CRS options, the CRS to
    reproject it to (None: none) and its pose; calling it gives ``(stream, pose)`` as
    :func:`tiled_sources` gives them to the parent."""

    path: str
    scan_index: int | None
    crs: str | None
    crs_override: bool
    target: str | None
    pose: Any

    def __call__(self) -> tuple[Any, Any]:
        from ..io.stream import open_stream

        s = open_stream(self.path, scan_index=self.scan_index, crs=self.crs, crs_override=self.crs_override)
        stream, pose, _ = to_target(s, self.pose, None, self.target)
        return stream, pose


def one_crs(sources: list[tuple[Any, Any, int | None]], names: list[str], to_crs: str | None) -> str | None:
    """The CRS one ordering's streams are stored in: refused when they disagree (see
    :func:`lodbuilder.io.crs.common_crs`); None when no ``to_crs`` asks to reproject them
    (:func:`to_target` then leaves each as it is)."""
    from ..io.crs import KEY_WKT, common_crs

    target = common_crs([(n, s.metadata.get(KEY_WKT)) for n, (s, _, _) in zip(names, sources, strict=True)], to_crs)
    return None if to_crs is None else target


def to_target(stream: Any, pose: Any, member: int | None, target: str | None) -> tuple[Any, Any, int | None]:
    """``(stream, pose, member)`` with the stream wrapped to reproject its chunks to ``target``
    (after its pose, which the wrapper applies) with the transform recorded in its metadata."""
    from ..io.crs import KEY_WKT, Reprojection, reproject_metadata, same_crs
    from ..io.pose import apply_pose

    if target is None or (stream.metadata.get(KEY_WKT) and same_crs(stream.metadata[KEY_WKT], target)):
        return stream, pose, member
    rep = Reprojection(stream.metadata[KEY_WKT], target)

    def it(size: int, start: int, stop: int) -> Any:
        for chunk in stream.chunks(size, start, stop):
            pts = chunk.points if pose is None else apply_pose(chunk.points, np.asarray(pose))
            yield dataclasses.replace(chunk, points=rep(pts))

    return dataclasses.replace(stream, metadata=reproject_metadata(stream.metadata, rep), _iter=it), None, member


def build_tiled_job(job: ScanJob, executor: Any, parallel: int, progress: ProgressCallback = None) -> dict[str, Any]:
    """Build ``job`` with the tiled (out-of-core) path, its tiles on ``executor``; the parent runs
    this (it reads, merges and writes in bounded blocks) and returns the same summary as
    :func:`build_one`."""
    from .tiled import SEAM_SPACING, build_tiled
    from .tiled.driver import TILE_PASSES

    o = job.options
    build: dict[str, Any] = {
        "voxel_size_requested": o.voxel_size,
        "band_radius_requested": o.band_radius,
        "size_requested": None,
        "rho_requested": None,
        "seeds_given": False,
        "pose": job.pose,
        "pose_kind": job.pose_kind,
        "scan_index": job.scan_index,
        "collection_key": job.key,
        "worker_pid": os.getpid(),
    }
    if job.members:
        build["joint"] = {"scans": [{k: m.get(k) for k in ("id", "name", "source", "sha256", "pose", "pose_kind",
                                                            "scan_index")} for m in job.members]}
    reader = "joint" if job.members else None
    sources = tiled_sources(job)
    prov = provenance(job, reader) if reader else {k: v for k, v in provenance(job, "").items() if k != "reader"}
    reps = [s[0].metadata[KEY_REPROJECTION] for s in sources if KEY_REPROJECTION in s[0].metadata]
    if reps:
        prov[KEY_REPROJECTION] = reps if job.members else reps[0]
    res = build_tiled(
        sources, Path(job.part), job.name, job.work_store, executor, parallel=parallel,
        max_memory=o.max_memory, voxel_size=o.voxel_size, band_radius=o.band_radius,
        seam_spacing=o.seam_spacing if o.seam_spacing is not None else SEAM_SPACING, seam_rounds=o.seam_rounds,
        tile_points=o.tile_points, passes=o.tile_passes or TILE_PASSES, build=build,
        provenance=prov,
        progress=progress,
    )
    res.update({"name": job.name, "method": "tiled"})
    return res


def decide_tiling(jobs: list[ScanJob], options: BuildOptions, work_url: str | None = None, force: bool = False
                  ) -> None:
    """Mark the jobs that take the tiled path: joint builds, and scans whose in-memory build would
    not fit the memory budget (``max_memory``, default 60 % of this machine's memory).
    Partial orderings (size/rho), seeds and feature options are in-memory builds only. ``work_url``:
    where their work files go (None: beside their parts); ``force``: what an earlier build left
    there is deleted (as the runner deletes a work directory beside the archive)."""
    for job in jobs:
        job.work_url = work_url
        if not options.in_memory_only:
            job.tiled = bool(job.members or options.tile_points) or _too_big(job, options)
        if force and work_url is not None and job.tiled:
            job.work_store.clear()


def _too_big(job: ScanJob, options: BuildOptions) -> bool:
    """True when the in-memory build of ``job``'s scan would not fit ``max_memory``."""
    from ..io.stream import peek_stream
    from .tiled.plan import needs_tiling

    if job.scan is not None:
        n = len(job.scan)
        row = 24 + sum(a.dtype.itemsize * int(a.size // max(n, 1)) for a in job.scan.attributes.values())
    else:
        try:
            st = peek_stream(job.path) if job.scan_index is None else None  # type: ignore[arg-type]
        except Exception:  # noqa: BLE001 - the build reads the file again and reports its error
            st = None
        if st is not None:
            n = st.n_points
            row = 24 + sum(int(np.dtype(d).itemsize * max(1, int(np.prod(sh)))) for d, sh in st.fields.values())
        else:  # a format that does not stream: about 30 bytes of file per point
            n, row = (job.size_bytes or 0) // 30, 24
    return needs_tiling(n, row, options.max_memory)
