"""Build many scans into one archive on a local process pool or a Dask cluster.

One code path: every scan is a :class:`~lodbuilder.collection.jobs.ScanJob` submitted to a
``concurrent.futures`` executor: a ``ProcessPoolExecutor`` (``workers``), or the executor of a Dask
``Client`` (``scheduler`` address, or ``dask_local=N`` to start a ``LocalCluster``; dask is imported
only then). Each worker writes its scan to its own part archive under ``.<archive>.parts/``; as
jobs finish, the parent merges their parts into the archive with the archive writer (atomic: the
archive is replaced as a whole, so a kill at any moment leaves the previous archive intact).

Resume: a scan is skipped when the archive already holds it with the same ``collection_key`` (the
hash of the source file's SHA-256, the build parameters, the pose and the scan name). A part left by
a killed build whose key still matches is merged without rebuilding. One failing scan is reported
with its cause and does not stop the others.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._validate import check_positive, strict_methods
from ..errors import BuildError, InputError, LodbuilderError, MissingDependencyError
from ..progress import ProgressCallback, report
from .inputs import ScanSource, expand_inputs
from .jobs import ScanJob, build_one, job_key

log = logging.getLogger(__name__)

#: how long to try reaching a Dask scheduler given by address
DASK_CONNECT_TIMEOUT = "15s"


@strict_methods
@dataclass
class ScanStatus:
    """What happened to one scan: ``built``, ``recovered`` (a finished part merged), ``skipped``
    (unchanged in the archive) or ``failed`` (with ``error``)."""

    name: str
    source: str
    status: str
    n_points: int | None = None
    seconds: float | None = None
    error: str | None = None
    worker_pid: int | None = None


@strict_methods
@dataclass
class CollectionResult:
    archive: Path
    scans: list[ScanStatus] = field(default_factory=list)
    seconds: float = 0.0
    executor: str = ""
    startup_seconds: float = 0.0  # starting the pool / connecting to or starting the Dask cluster
    merge_seconds: float = 0.0  # merging finished parts into the archive (in the parent)

    def by_status(self, status: str) -> list[ScanStatus]:
        return [s for s in self.scans if s.status == status]

    @property
    def failed(self) -> list[ScanStatus]:
        return self.by_status("failed")

    @property
    def ok(self) -> bool:
        return not self.failed

    def summary(self) -> dict[str, Any]:
        counts: dict[str, int] = {}
        for s in self.scans:
            counts[s.status] = counts.get(s.status, 0) + 1
        return {"archive": str(self.archive), "seconds": round(self.seconds, 3), "executor": self.executor,
                "startup_seconds": round(self.startup_seconds, 3), "merge_seconds": round(self.merge_seconds, 3),
                **counts}


StatusCallback = Callable[[ScanStatus], None] | None


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if isinstance(exc, LodbuilderError):
        return text
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# ------------------------------------------------------------------------------------ executors

def _start_method() -> str:
    """How worker processes start: ``forkserver`` (they fork from a clean server process, with no
    copies of the caller's open files or threads); ``fork`` when the caller's main script has no
    file to re-import (a script read from stdin)."""
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    return "fork" if main_file is not None and not os.path.isfile(main_file) else "forkserver"


def _mp_context() -> Any:
    import multiprocessing

    method = _start_method()
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":
        # the server imports the build's libraries and loads the compiled kernels once; the
        # workers forked from it start warm (takes effect when the server starts)
        ctx.set_forkserver_preload(["lodbuilder.collection.jobs", "lodbuilder.collection._warm"])
    return ctx


@contextlib.contextmanager
def make_executor(workers: int | None = None, scheduler: str | None = None,
                  dask_local: int | None = None) -> Iterator[tuple[cf.Executor, str]]:
    """``(executor, description)``: a local process pool, or a Dask client's executor."""
    if scheduler is not None and dask_local is not None:
        raise InputError("give either a Dask scheduler address or dask_local, not both")
    if scheduler is None and dask_local is None:
        n = workers or os.cpu_count() or 1
        if int(n) < 1:
            raise InputError(f"workers must be >= 1, got {workers}")
        ctx = _mp_context()
        with cf.ProcessPoolExecutor(max_workers=int(n), mp_context=ctx) as ex:
            yield ex, f"process pool ({int(n)} worker{'s' if int(n) > 1 else ''})"
        return
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise MissingDependencyError(
            "building on Dask needs dask.distributed; pip install lodbuilder[distributed]"
        ) from None
    cluster = None
    if dask_local is not None:
        if int(dask_local) < 1:
            raise InputError(f"dask_local must be >= 1 workers, got {dask_local}")
        import dask

        # the same start method (and warm forkserver) as the local pool; Dask's default, spawn,
        # starts every worker cold
        _mp_context()
        with dask.config.set({"distributed.worker.multiprocessing-method": _start_method()}):
            cluster = LocalCluster(n_workers=int(dask_local), threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.WARNING)
        client = Client(cluster)
        desc = f"Dask LocalCluster ({int(dask_local)} worker{'s' if int(dask_local) > 1 else ''})"
    else:
        try:
            client = Client(scheduler, timeout=DASK_CONNECT_TIMEOUT)
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot reach Dask scheduler {scheduler!r} ({_one_line(exc)}); check the address") from None
        desc = f"Dask scheduler {scheduler}"
    try:
        yield client.get_executor(pure=False), desc
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# ---------------------------------------------------------------------------------------- parts

def parts_dir(archive: Path) -> Path:
    return archive.with_name(f".{archive.name}.parts")


def _part_path(archive: Path, name: str, key: str) -> Path:
    return parts_dir(archive) / f"{name}.{key[:20]}.h5"


def merge_parts(archive: Path, parts: list[tuple[str, Path]]) -> None:
    """Register one-scan part archives in ``archive`` (atomically, O(the parts), replacing same names)."""
    from ..archive.writer import register_parts

    register_parts(archive, [p for _, p in parts], overwrite=True)


def _part_ok(part: Path, name: str) -> bool:
    from ..archive.reader import open_archive

    try:
        with open_archive(part) as arc:
            return arc.scans == [name]
    except Exception:
        return False


def _clean_parts(archive: Path, keep: set[Path]) -> None:
    from ..archive.writer import remove_stale_temps

    d = parts_dir(archive)
    if not d.is_dir():
        return
    for p in d.iterdir():
        if ".tmp-" in p.name and p.name.startswith("."):
            remove_stale_temps(d / p.name[1:].split(".tmp-")[0])
        elif p.suffix == ".h5" and p not in keep:
            _drop_part(p)


def _drop_part(part: Path) -> None:
    """Delete a part archive and the lock file its writer left beside it."""
    for p in (part, part.with_name(f".{part.name}.lock")):
        with contextlib.suppress(OSError):
            p.unlink()


def _existing_scans(archive: Path) -> dict[str, tuple[str | None, str | None]]:
    """name -> (collection_key, source file name) of the scans already in the archive."""
    if not archive.exists():
        return {}
    from ..archive.reader import open_archive

    with open_archive(archive) as arc:
        out = {}
        for n in arc.scans:
            v = arc.scan(n)
            out[n] = (v.build.get("collection_key"), v.provenance.get("source_name"))
        return out


# ---------------------------------------------------------------------------------------- build

def _params(voxel_size: Any, band_radius: Any, size: Any, rho: Any,
            features: dict[str, Any] | None = None) -> dict[str, Any]:
    params: dict[str, Any] = {
        "voxel_size": check_positive(voxel_size, "voxel_size"),
        "band_radius": check_positive(band_radius, "band_radius"),
        "rho": check_positive(rho, "rho"),
        "size": None,
    }
    if size is not None:
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise InputError(f"size must be a whole number of points >= 1, got {size!r}")
        params["size"] = int(size)
    feats = {k: v for k, v in (features or {}).items() if v is not None}
    if feats:
        if params["size"] is not None or params["rho"] is not None:
            raise InputError("size/rho (partial orderings) do not combine with feature options; drop one")
        params["features"] = feats
    return params


def plan_jobs(sources: list[ScanSource], archive: Path, params: dict[str, Any], *, force: bool = False,
              overwrite: bool = False):
    """Split sources into (jobs to run, recovered parts, skipped, failed-before-start).

    A scan already in the archive is rebuilt when its key changed (new file contents, parameters or
    pose) if it came from a file of the same name, or with ``overwrite``; a same-named scan from
    another file is refused (failed) otherwise."""
    from ..io import file_sha256

    existing = _existing_scans(archive)
    jobs: list[ScanJob] = []
    recovered: list[tuple[ScanJob, Path]] = []
    skipped: list[ScanStatus] = []
    failed: list[ScanStatus] = []
    for src in sources:
        try:
            if src.path.resolve() == archive.resolve():
                raise InputError(f"input {src.path} is the archive itself; choose another -o")
            sha = file_sha256(src.path)
            nbytes = src.path.stat().st_size
        except LodbuilderError as exc:
            failed.append(ScanStatus(src.name, str(src.path), "failed", error=_one_line(exc)))
            continue
        except OSError as exc:
            failed.append(ScanStatus(src.name, str(src.path), "failed",
                                     error=f"{src.path}: cannot be read ({exc.strerror or exc}); check the path"))
            continue
        pose = None if src.pose is None else src.pose.tolist()
        key = job_key(sha, params, pose, src.scan_index, src.name)
        part = _part_path(archive, src.name, key)
        job = ScanJob(name=src.name, path=str(src.path.resolve()), key=key, part=str(part), params=dict(params),
                      pose=pose, scan_index=src.scan_index, sha256=sha, size_bytes=nbytes)
        old_key, old_source = existing.get(src.name, (None, None))
        if not force and old_key == key:
            skipped.append(ScanStatus(src.name, str(src.path), "skipped"))
        elif src.name in existing and not overwrite and old_source != src.path.name:
            failed.append(ScanStatus(src.name, str(src.path), "failed", error=(
                f"archive {archive} already holds a scan {src.name!r} built from {old_source or 'another input'}; "
                "pass --overwrite (overwrite=True) to replace it or rename the file")))
        elif not force and part.is_file() and _part_ok(part, src.name):
            recovered.append((job, part))
        else:
            jobs.append(job)
    return jobs, recovered, skipped, failed


def build_collection(
    inputs: Any = (),
    archive: str | os.PathLike[str] = "collection.h5",
    *,
    manifest: str | os.PathLike[str] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    dask_local: int | None = None,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    size: int | None = None,
    rho: float | None = None,
    force: bool = False,
    overwrite: bool = False,
    raise_on_failure: bool = False,
    progress: ProgressCallback = None,
    on_status: StatusCallback = None,
    **features: Any,
) -> CollectionResult:
    """Build every scan of ``inputs`` (files, directories, globs, manifests) into ``archive``.

    ``force`` rebuilds scans even when unchanged; ``overwrite`` lets a scan replace a same-named
    scan built from another file. ``size``/``rho`` stop each scan's ordering early (at most ``size`` points; ``size`` larger than a
    scan means the whole scan); by default every point is ordered. ``features`` are the feature
    options of a single-scan build (``importance``, ``adaptive``, ``density_floor``, ...). Returns a
    :class:`CollectionResult` with one status per scan; with ``raise_on_failure`` a BuildError
    naming the failed scans is raised after all the others are finished and merged.
    """
    from ..archive.reader import check_archive_file
    from ..archive.writer import check_writable_dir

    t0 = time.perf_counter()
    archive = Path(archive).resolve()  # absolute paths in jobs: Dask workers may run elsewhere
    check_writable_dir(archive, "archive")
    if archive.exists():
        check_archive_file(archive)
    params = _params(voxel_size, band_radius, size, rho, features)
    sources = expand_inputs(inputs, manifest)
    jobs, recovered, skipped, failed = plan_jobs(sources, archive, params, force=force, overwrite=overwrite)
    result = CollectionResult(archive=archive)
    total = len(sources)
    done = 0

    def emit(st: ScanStatus) -> None:
        nonlocal done
        result.scans.append(st)
        done += 1
        # failures are warnings unless the caller shows statuses itself
        level = logging.WARNING if st.status == "failed" and on_status is None else logging.INFO
        log.log(level, "[%d/%d] %s: %s%s", done, total, st.name, st.status,
                f" ({st.error})" if st.error else "")
        if on_status is not None:
            on_status(st)
        report(progress, "scans", done, total)

    report(progress, "scans", 0, total)
    for st in skipped + failed:
        emit(st)
    keep_parts = {Path(j.part) for j in jobs} | {p for _, p in recovered}
    _clean_parts(archive, keep_parts)
    if recovered:
        merge_parts(archive, [(j.name, p) for j, p in recovered])
        for j, p in recovered:
            _drop_part(p)
            emit(ScanStatus(j.name, j.path, "recovered"))
    if jobs:
        parts_dir(archive).mkdir(exist_ok=True)
        jobs.sort(key=lambda j: -j.size_bytes)  # largest first: better packing on the workers
        t_start = time.perf_counter()
        with make_executor(workers, scheduler, dask_local) as (ex, desc):
            result.startup_seconds = time.perf_counter() - t_start
            result.executor = desc
            log.info("building %d scan(s) on %s", len(jobs), desc)
            pending = {ex.submit(build_one, j): j for j in jobs}
            try:
                while pending:
                    finished, _ = cf.wait(list(pending), return_when=cf.FIRST_COMPLETED)
                    good: list[tuple[ScanJob, dict[str, Any]]] = []
                    for fut in finished:
                        job = pending.pop(fut)
                        try:
                            good.append((job, fut.result()))
                        except cf.process.BrokenProcessPool:
                            emit(ScanStatus(job.name, job.path, "failed",
                                            error="its worker process died (killed, out of memory, or failed to start: see the log)"))
                        except Exception as exc:
                            emit(ScanStatus(job.name, job.path, "failed", error=_one_line(exc)))
                    if good:
                        t_merge = time.perf_counter()
                        try:
                            merge_parts(archive, [(j.name, Path(r["part"])) for j, r in good])
                            result.merge_seconds += time.perf_counter() - t_merge
                        except Exception as exc:
                            for j, _ in good:
                                emit(ScanStatus(j.name, j.path, "failed", error=f"merge failed: {_one_line(exc)}"))
                            continue
                        for j, r in good:
                            _drop_part(Path(r["part"]))
                            emit(ScanStatus(j.name, j.path, "built", n_points=r["n_points"],
                                            seconds=r["seconds"], worker_pid=r["worker_pid"]))
            except BaseException:  # interrupted: do not start the scans still queued
                for fut in pending:
                    fut.cancel()
                raise
    d = parts_dir(archive)
    if d.is_dir():
        for lock in d.glob(".*.lock"):  # locks of parts that are gone
            if not lock.with_name(lock.name[1:-5]).exists():
                with contextlib.suppress(OSError):
                    lock.unlink()
        with contextlib.suppress(OSError):
            d.rmdir()  # only when empty
    result.seconds = time.perf_counter() - t0
    if raise_on_failure and result.failed:
        names = ", ".join(f"{s.name} ({s.error})" for s in result.failed[:3])
        more = f" and {len(result.failed) - 3} more" if len(result.failed) > 3 else ""
        raise BuildError(f"{len(result.failed)} of {total} scan(s) failed: {names}{more}")
    return result
