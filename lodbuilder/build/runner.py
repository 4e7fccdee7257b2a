"""The one build pipeline: inputs -> scan jobs -> executor -> part archives -> the archive.

A single scan is a collection of one. Every input (a file, several files, directories, globs, a
manifest, an in-memory :class:`~lodbuilder.io.Scan`) becomes a :class:`~lodbuilder.build.jobs.ScanJob`
submitted to a ``concurrent.futures`` executor: the calling process (one scan, or in-memory
scans), a local ``ProcessPoolExecutor`` (``workers``), or a Dask client's executor (``scheduler``
address, or ``dask_local=N`` for a ``LocalCluster``). Each job writes its scan to its own part
archive under ``.<archive>.parts/``; as jobs finish, the parent merges their parts into the
archive with the archive writer (atomic: a kill at any moment leaves the previous archive intact).

One naming rule (the file stem, made safe and unique; ``name`` for a single scan), one
duplicate-name policy and one resume key (``collection_key`` in each scan's build record: the hash
of the source's SHA-256, the build parameters, the pose and the name):

* a scan already in the archive with the same key is ``skipped`` (``force`` rebuilds it);
* a scan of the same name with another key (other contents, pose or parameters, or another file)
  is refused unless ``overwrite``, which replaces it;
* a finished part left by a killed build whose key still matches is merged without rebuilding.

One failing scan is reported with its cause and does not stop the others.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import os
import time
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from ..errors import ArchiveError, BuildError, InputError, LodbuilderError
from ..io.pose import pose_kind
from ..progress import ProgressCallback, report
from .archive_crs import check_build_crs
from .executors import (
    DASK_CONNECT_TIMEOUT,
    check_scheduler,
    make_executor,
    one_line,
    start_pool_server,
)
from .inputs import ScanSource, expand_inputs
from .jobs import ScanJob, build_one, decide_tiling, job_key, scan_digest
from .options import BuildOptions
from .result import BuildResult, CollectionResult, ScanStatus, StatusCallback
from .tiled.urls import check_work_url

log = logging.getLogger(__name__)

__all__ = ["BuildResult", "CollectionResult", "DASK_CONNECT_TIMEOUT", "ScanStatus", "build", "merge_parts",
           "parts_dir", "plan_jobs"]

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
    """True when ``part`` is a regular file (never a link followed) holding exactly scan ``name``."""
    import stat

    from ..archive.reader import open_archive

    try:
        if not stat.S_ISREG(os.lstat(part).st_mode):
            return False
        with open_archive(part) as arc:
            return arc.scans == [name]
    except Exception:
        return False


def _check_parts_dir(archive: Path) -> None:
    """Refuse a work directory beside ``archive`` that lodbuilder did not make (a symbolic link, a
    mount point, a directory without lodbuilder's marker): it is never read, followed or emptied."""
    from ..archive.files import check_own_dir

    d = parts_dir(archive)
    if os.path.lexists(d):
        check_own_dir(d, archive.name)


def _clean_parts(archive: Path, keep: set[Path], running: set[Path]) -> None:
    """Delete leftovers of earlier builds: parts not in ``keep``, work directories of parts not
    ``running`` (a tiled build resumes from its work directory), temporaries of dead writers.
    Runs under the archive's lock, in a work directory checked to be lodbuilder's."""
    from ..archive.files import MARKER, remove_own_dir
    from ..archive.writer import remove_stale_temps

    d = parts_dir(archive)
    if not os.path.lexists(d):
        return
    _check_parts_dir(archive)
    work = {p.with_name(p.name[: -len(".h5")] + ".work") for p in running}
    for p in d.iterdir():
        if p.name == MARKER:
            continue
        if ".tmp-" in p.name and p.name.startswith("."):
            remove_stale_temps(d / p.name[1:].split(".tmp-")[0])
        elif p.suffix == ".h5" and p not in keep:
            _drop_part(p)  # a link is removed, never followed
        elif p.suffix == ".work" and p not in work:
            remove_own_dir(p, p.name)  # the work of a build whose parameters changed (refused if not ours)


def _drop_part(part: Path) -> None:
    """Delete a part archive and the lock file its writer left beside it."""
    for p in (part, part.with_name(f".{part.name}.lock")):
        with contextlib.suppress(OSError):
            p.unlink()


def _tidy_parts(archive: Path) -> None:
    """Remove locks of parts that are gone, and the work directory when nothing else is left."""
    from ..archive.files import own_dir_problem, remove_own_dir_if_empty

    d = parts_dir(archive)
    if own_dir_problem(d, archive.name) is not None:
        return
    for lock in d.glob(".*.lock"):  # locks of parts that are gone
        if not lock.with_name(lock.name[1:-5]).exists():
            with contextlib.suppress(OSError):
                lock.unlink()
    remove_own_dir_if_empty(d, archive.name)


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


# ---------------------------------------------------------------------------------------- plan

def _conflict(archive: Path, name: str, old_source: str | None) -> ArchiveError:
    src = f"built from {old_source}" if old_source else "built from another input"
    return ArchiveError(
        f"archive {archive} already holds scan {name!r} ({src} with other contents, pose or parameters); "
        "pass --overwrite (overwrite=True) to replace it or choose another --name"
    )


def plan_jobs(sources: list[ScanSource], archive: Path, options: BuildOptions, *, force: bool = False,
              overwrite: bool = False):
    """Split sources into (jobs to run, recovered parts, skipped, failed-before-start)."""
    from ..io import file_sha256

    existing = _existing_scans(archive)
    jobs: list[ScanJob] = []
    recovered: list[tuple[ScanJob, Path]] = []
    skipped: list[ScanStatus] = []
    failed: list[ScanStatus] = []
    for src in sources:
        where = str(src.path) if src.path is not None else "<in-memory scan>"
        try:
            if src.path is None:
                sha, nbytes = scan_digest(src.scan), None
            else:
                if src.path.resolve() == archive.resolve():
                    raise InputError(f"input {src.path} is the archive itself; choose another -o")
                sha = file_sha256(src.path)
                nbytes = src.path.stat().st_size
        except LodbuilderError as exc:
            failed.append(ScanStatus(src.name, where, "failed", error=one_line(exc), exception=exc))
            continue
        except OSError as exc:
            err = ArchiveError(f"{src.path}: cannot be read ({exc.strerror or exc}); check the path")
            failed.append(ScanStatus(src.name, where, "failed", error=str(err), exception=err))
            continue
        pose = None if src.pose is None else src.pose.tolist()
        key = job_key(sha, options.key_params, pose, src.scan_index, src.name)
        part = _part_path(archive, src.name, key)
        job = ScanJob(name=src.name, path=None if src.path is None else os.path.abspath(src.path), key=key,
                      part=str(part), options=options, pose=pose, scan_index=src.scan_index, sha256=sha,
                      size_bytes=nbytes, scan=src.scan, pose_kind=pose_kind(src.pose),
                      given=None if src.path is None else str(src.path))
        _place(job, where, existing, archive, force, overwrite, jobs, recovered, skipped, failed)
    return jobs, recovered, skipped, failed


def _place(job: ScanJob, where: str, existing: dict[str, tuple[str | None, str | None]], archive: Path,
           force: bool, overwrite: bool, jobs: list, recovered: list, skipped: list, failed: list) -> None:
    """The one duplicate-name policy: skip an unchanged scan, refuse a changed one unless
    ``overwrite``, merge a finished part of an interrupted build, else build."""
    part = Path(job.part)
    old_key, old_source = existing.get(job.name, (None, None))
    if job.name in existing and old_key == job.key and not force:
        skipped.append(ScanStatus(job.name, where, "skipped"))
    elif job.name in existing and old_key != job.key and not overwrite:
        err = _conflict(archive, job.name, old_source)
        failed.append(ScanStatus(job.name, where, "failed", error=str(err), exception=err))
    elif not force and part.is_file() and _part_ok(part, job.name):
        recovered.append((job, part))
    else:
        jobs.append(job)


def plan_joint(sources: list[ScanSource], archive: Path, options: BuildOptions, name: str, *,
               force: bool = False, overwrite: bool = False):
    """One job ordering every source as one surface (a joint build), placed like any scan."""
    import hashlib
    from concurrent.futures import ThreadPoolExecutor

    from .._resources import cores
    from ..io import file_sha256

    members: list[dict[str, Any]] = []
    h = hashlib.sha256()
    seen: dict[tuple[Any, ...], int] = {}
    paths: list[Path] = []
    for i, src in enumerate(sources):
        if src.path is None:
            raise InputError("a joint build orders scan files; save in-memory scans to files first")
        paths.append(src.path)
        if src.path.resolve() == archive.resolve():
            raise InputError(f"input {src.path} is the archive itself; choose another -o")
        same = (src.path.resolve(), src.scan_index, None if src.pose is None else str(src.pose.tolist()))
        if same in seen:  # (a glob and the same file named again: every point would be stored twice)
            raise InputError(f"input {src.path} is given twice (inputs {seen[same] + 1} and {i + 1}) for the joint "
                             f"scan {name!r}; give each file once")
        seen[same] = i
    # the files' digests side by side (hashlib lets go of the GIL): a survey's bytes are no serial pass
    # (196 files, 118 MB: 0.089 s one after another, 0.057 s on this 2-core machine)
    with ThreadPoolExecutor(max(1, min(len(sources), 2 * cores()))) as pool:
        shas = list(pool.map(file_sha256, paths))
    for i, (src, path, sha) in enumerate(zip(sources, paths, shas, strict=True)):
        h.update(sha.encode())
        members.append({"id": i, "name": src.name, "path": os.path.abspath(path), "source": path.name,
                        "sha256": sha, "pose": None if src.pose is None else src.pose.tolist(),
                        "pose_kind": pose_kind(src.pose), "scan_index": src.scan_index})
    key = job_key(h.hexdigest(), {**options.key_params, "joint": True}, [m["pose"] for m in members],
                  None, name)
    job = ScanJob(name=name, path=None, key=key, part=str(_part_path(archive, name, key)), options=options,
                  sha256=h.hexdigest(), size_bytes=sum(Path(m["path"]).stat().st_size for m in members),
                  members=members, tiled=True)
    out: tuple[list, list, list, list] = ([], [], [], [])
    _place(job, job.source, _existing_scans(archive), archive, force, overwrite, *out)
    return out


def _sources(inputs: Any, manifest: Any, name: str | None) -> list[ScanSource]:
    from ..io import Scan

    items = [inputs] if isinstance(inputs, (str, os.PathLike, Scan)) else list(inputs or [])
    scans = [x for x in items if isinstance(x, Scan)]
    files = [x for x in items if not isinstance(x, Scan)]
    bad = [x for x in files if not isinstance(x, (str, os.PathLike))]
    if bad:
        raise InputError(f"build inputs must be file paths or lodbuilder.Scan objects, got {type(bad[0]).__name__}")
    sources = [] if not files and manifest is None else expand_inputs(files, manifest)
    from ..archive.layout import check_name
    from .inputs import safe_name, unique_names

    for s in scans:
        sources.append(ScanSource(path=None, name=check_name(s.name) if s.name else "scan", scan=s))
    if not sources:
        raise InputError("no input scans given; pass files, directories, globs or --manifest")
    if name is not None:
        if len(sources) != 1:
            raise InputError(f"--name (name=) names a single scan, but the inputs hold {len(sources)} scans; "
                             "a collection names each scan after its file")
        sources[0].name = check_name(name)
    elif scans:
        for src, n in zip(sources, unique_names([safe_name(s.name) if s.scan is None else s.name
                                                 for s in sources]), strict=True):
            src.name = n
    return sources


# ---------------------------------------------------------------------------------------- build

def build(
    inputs: Any,
    archive: str | os.PathLike[str],
    options: BuildOptions,
    *,
    name: str | None = None,
    manifest: str | os.PathLike[str] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    dask_local: int | None = None,
    force: bool = False,
    overwrite: bool = False,
    joint: bool | str = False,
    wait: float | None = None,
    work_dir: str | os.PathLike[str] | None = None,
    raise_on_failure: bool | None = None,
    progress: ProgressCallback = None,
    on_status: StatusCallback = None,
) -> BuildResult:
    """Build every scan of ``inputs`` into ``archive``; see :func:`lodbuilder.build_archive`."""
    from ..archive.reader import check_archive_file
    from ..archive.writer import check_writable_dir

    t0 = time.perf_counter()
    archive = Path(os.path.abspath(archive))  # absolute paths in jobs: workers may run elsewhere
    check_scheduler(scheduler)
    work_url = check_work_url(work_dir)  # (a directory made absolute: workers may run elsewhere)
    check_writable_dir(archive, "archive")
    if archive.exists():
        check_archive_file(archive)  # fail before any expensive work
    joint_name = _joint_name(joint, name, manifest, inputs) if joint else None
    sources = _sources(inputs, manifest, None if joint else name)
    check_build_crs(sources, archive, options, joint_name)
    if options.seeds is not None and (len(sources) != 1 or joint):
        raise InputError("seeds are input indices of one scan; give a single scan with seeds")
    if joint and (options.partial or options.features):
        raise InputError("a joint build orders every point (size/rho and feature options are not available)")
    in_memory = any(s.scan is not None for s in sources)
    if in_memory and (workers is not None or scheduler is not None or dask_local is not None):
        raise InputError("in-memory scans are built in this process; save them to files to use workers or Dask")
    # (its imports meanwhile: the plan reads the headers)
    start_pool_server(workers, scheduler, dask_local, options.seam_rounds)
    if wait is not None:
        wait = _check_wait(wait)
    result = BuildResult(archive=archive)
    # one writer of the archive at a time, from the plan to the last merge: everything this build
    # creates or removes beside the archive (its work directory, parts, tidy-ups) happens under the
    # archive's lock, so another build waits for it and never sees (or removes) its files
    from ..archive.files import lock

    with lock(archive, wait=wait, what="a build"):
        try:
            total = _build_locked(sources, archive, options, result, joint_name, in_memory, force=force,
                                  overwrite=overwrite, workers=workers, scheduler=scheduler,
                                  dask_local=dask_local, progress=progress, on_status=on_status,
                                  raise_on_failure=raise_on_failure, work_url=work_url)
        finally:
            _tidy_parts(archive)
    result.seconds = time.perf_counter() - t0
    _raise_failures(result, total, raise_on_failure)
    return result


def _check_wait(wait: Any) -> float:
    try:
        w = float(wait)
    except (TypeError, ValueError):
        w = float("nan")
    if isinstance(wait, bool) or not w >= 0 or w == float("inf"):
        raise InputError(f"wait must be a number of seconds >= 0, got {wait!r}")
    return w


def _build_locked(sources: list[ScanSource], archive: Path, options: BuildOptions, result: BuildResult,
                  joint_name: str | None, in_memory: bool, *, force: bool, overwrite: bool, workers: int | None,
                  scheduler: str | None, dask_local: int | None, progress: ProgressCallback,
                  on_status: StatusCallback, raise_on_failure: bool | None, work_url: str | None = None) -> int:
    """Plan, run and merge the build (the caller holds the archive's lock); returns the number of
    scans it was given (a joint build: 1)."""
    _check_parts_dir(archive)  # before a part in it is read
    if joint_name is not None:
        jobs, recovered, skipped, failed = plan_joint(sources, archive, options, joint_name, force=force,
                                                      overwrite=overwrite)
        total = 1
    else:
        jobs, recovered, skipped, failed = plan_jobs(sources, archive, options, force=force, overwrite=overwrite)
        total = len(sources)
    decide_tiling(jobs, options, work_url, force)
    names_in_archive = set(_existing_scans(archive))
    emit = _Statuses(result, total, progress, on_status,
                     quiet_failure=on_status is not None or (raise_on_failure is None and total == 1))
    if total > 1:
        report(progress, "scans", 0, total)
    for st in skipped + failed:
        emit(st)
    keep_parts = {Path(j.part) for j in jobs} | {p for _, p in recovered}
    # force: every scan from its source, whatever an interrupted build left (its work files too)
    _clean_parts(archive, keep_parts - ({Path(j.part) for j in jobs} if force else set()),
                 set() if force else {Path(j.part) for j in jobs})
    if recovered:
        merge_parts(archive, [(j.name, p) for j, p in recovered])
        for j, p in recovered:
            _drop_part(p)
            names_in_archive.add(j.name)
            emit(ScanStatus(j.name, j.source, "recovered"))
    if jobs:
        _run(jobs, archive, result, emit, names_in_archive, in_memory, total, workers, scheduler, dask_local,
             progress)
    result.archive_scans = len(names_in_archive) if archive.exists() else 0
    return total


class _Statuses:
    """Reports each scan's status as it is known: into the result, the log, ``on_status`` and, for a
    collection, the progress of scans and points (failures are warnings unless ``quiet_failure``:
    the caller shows or raises them)."""

    def __init__(self, result: BuildResult, total: int, progress: ProgressCallback, on_status: StatusCallback,
                 *, quiet_failure: bool) -> None:
        self.result, self.total, self.progress, self.on_status = result, total, progress, on_status
        self.quiet_failure = quiet_failure
        self.done = self.points = 0

    def __call__(self, st: ScanStatus) -> None:
        self.result.scans.append(st)
        self.done += 1
        self.points += st.n_points or 0
        level = logging.WARNING if st.status == "failed" and not self.quiet_failure else logging.INFO
        log.log(level, "[%d/%d] %s: %s%s", self.done, self.total, st.name, st.status,
                f" ({st.error})" if st.error else "")
        if self.on_status is not None:
            self.on_status(st)
        if self.total > 1:  # a collection shows scans and points; a single scan shows its phases
            report(self.progress, "scans", self.done, self.total)
            report(self.progress, "points", self.points, 0)


def _run(jobs: list[ScanJob], archive: Path, result: BuildResult, emit: Any, names_in_archive: set[str],
         in_memory: bool, total: int, workers: int | None, scheduler: str | None, dask_local: int | None,
         progress: ProgressCallback) -> None:
    """Run the jobs (in memory ones first, then the tiled ones) on one executor, merging each part."""
    from ..archive.files import make_own_dir

    make_own_dir(parts_dir(archive), archive.name)
    jobs.sort(key=lambda j: -(j.size_bytes or 0))  # largest first: better packing on the workers
    tiled = [j for j in jobs if j.tiled]
    small = [j for j in jobs if not j.tiled]
    default = workers is None and scheduler is None and dask_local is None
    inline = in_memory or (len(jobs) == 1 and default and not tiled)
    t_start = time.perf_counter()
    rounds = any(j.tiled and j.options.seam_rounds for j in jobs)
    with make_executor(workers, scheduler, dask_local, inline=inline, rounds=rounds) as (ex, desc):
        result.startup_seconds = time.perf_counter() - t_start
        result.executor = desc
        log.info("building %d scan(s) on %s", len(jobs), desc)
        if small:
            _run_jobs(ex, small, archive, result, emit, names_in_archive,
                      progress if (inline and total == 1) else None)
        parallel = 1 if inline or scheduler is not None else (dask_local or workers or os.cpu_count() or 1)
        for job in tiled:
            _run_tiled(ex, parallel, job, archive, result, emit, names_in_archive,
                       progress if total == 1 else None)


def _run_jobs(ex: cf.Executor, jobs: list[ScanJob], archive: Path, result: BuildResult, emit: Any,
              names_in_archive: set[str], progress: ProgressCallback) -> None:
    from .executors import InlineExecutor

    inline = isinstance(ex, InlineExecutor)
    pending: dict[cf.Future, ScanJob] = {}
    queue = list(jobs)

    def submit_next() -> None:
        job = queue.pop(0)
        pending[ex.submit(build_one, job, progress) if inline else ex.submit(build_one, job)] = job

    try:
        # in this process, one job at a time (each is merged before the next starts)
        for _ in range(1 if inline else len(queue)):
            submit_next()
        while pending:
            finished, _ = cf.wait(list(pending), return_when=cf.FIRST_COMPLETED)
            good: list[tuple[ScanJob, dict[str, Any]]] = []
            for fut in finished:
                job = pending.pop(fut)
                try:
                    good.append((job, fut.result()))
                except BrokenProcessPool:
                    emit(ScanStatus(job.name, job.source, "failed", error=(
                        "its worker process died (killed, out of memory, or failed to start: see the log)")))
                except Exception as exc:
                    exc = _as_given(exc, job)
                    emit(ScanStatus(job.name, job.source, "failed", error=one_line(exc), exception=exc))
            if good:
                t_merge = time.perf_counter()
                try:
                    merge_parts(archive, [(j.name, Path(r["part"])) for j, r in good])
                    result.merge_seconds += time.perf_counter() - t_merge
                except Exception as exc:
                    for j, _ in good:
                        emit(ScanStatus(j.name, j.source, "failed", error=f"merge failed: {one_line(exc)}",
                                        exception=exc))
                else:
                    for j, r in good:
                        _drop_part(Path(r["part"]))
                        names_in_archive.add(j.name)
                        emit(ScanStatus(j.name, j.source, "built", n_points=r["n_points"], seconds=r["seconds"],
                                        worker_pid=r["worker_pid"], n_ordered=r.get("n_ordered"),
                                        encoding=r.get("encoding"), method=r.get("method"),
                                        phases=r.get("phases") or {}))
            if inline and queue:
                submit_next()
    except BaseException:  # interrupted: do not start the scans still queued
        for fut in pending:
            fut.cancel()
        raise


def _run_tiled(ex: cf.Executor, parallel: int, job: ScanJob, archive: Path, result: BuildResult, emit: Any,
               names_in_archive: set[str], progress: ProgressCallback) -> None:
    """A tiled job: driven from this process, its tiles on the executor; then its part is merged."""
    from .jobs import build_tiled_job

    try:
        r = build_tiled_job(job, ex, parallel, progress)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:
        exc = _as_given(exc, job)
        emit(ScanStatus(job.name, job.source, "failed", error=one_line(exc), exception=exc))
        return
    t_merge = time.perf_counter()
    try:
        merge_parts(archive, [(job.name, Path(r["part"]))])
        result.merge_seconds += time.perf_counter() - t_merge
    except Exception as exc:
        emit(ScanStatus(job.name, job.source, "failed", error=f"merge failed: {one_line(exc)}", exception=exc))
        return
    _drop_part(Path(r["part"]))
    names_in_archive.add(job.name)
    emit(ScanStatus(job.name, job.source, "built", n_points=r["n_points"], seconds=r["seconds"],
                    worker_pid=r["worker_pid"], n_ordered=r["n_ordered"], encoding=r["encoding"], method="tiled",
                    phases=r["phases"]))


def _joint_name(joint: Any, name: str | None, manifest: Any, inputs: Any) -> str:
    """The name of a joint scan: ``name``, a string given as ``joint``, the manifest's stem, or
    "joint"."""
    from ..archive.layout import check_name
    from .inputs import MANIFEST_SUFFIXES, safe_name

    if name is not None:
        return check_name(name)
    if isinstance(joint, str):
        return check_name(joint)
    items = [inputs] if isinstance(inputs, (str, os.PathLike)) else list(inputs or [])
    manifests = [Path(manifest)] if manifest is not None else []
    manifests += [Path(x) for x in items if isinstance(x, (str, os.PathLike))
                  and Path(x).suffix.lower() in MANIFEST_SUFFIXES]
    return safe_name(manifests[0].stem) if len(manifests) == 1 else "joint"


def _as_given(exc: Exception, job: ScanJob) -> Exception:
    """The job's error naming its file as the caller gave it (jobs carry absolute paths)."""
    if job.path is None or not job.given or job.given == job.path or job.path not in str(exc):
        return exc
    if isinstance(exc, LodbuilderError) and len(exc.args) == 1 and isinstance(exc.args[0], str):
        new = type(exc)(exc.args[0].replace(job.path, job.given))
        new.__cause__ = exc.__cause__
        return new
    return exc


def _raise_failures(result: BuildResult, total: int, raise_on_failure: bool | None) -> None:
    failed = result.failed
    if not failed or raise_on_failure is False:
        return
    if total == 1 and failed[0].exception is not None and isinstance(failed[0].exception, LodbuilderError):
        raise failed[0].exception
    if raise_on_failure or total == 1:
        names = ", ".join(f"{s.name} ({s.error})" for s in failed[:3])
        more = f" and {len(failed) - 3} more" if len(failed) > 3 else ""
        raise BuildError(f"{len(failed)} of {total} scan(s) failed: {names}{more}")
