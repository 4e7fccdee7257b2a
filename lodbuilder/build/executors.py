"""Where build jobs run: in the calling process, on a local process pool, or on a Dask cluster.

All three are ``concurrent.futures`` executors, so the pipeline has one loop for them. Dask is
imported only when a scheduler address or ``dask_local`` is given.

Workers die with their parent: a pool worker and the forkserver it is forked from ask the kernel
(Linux ``prctl(PR_SET_PDEATHSIG)``) to be killed when their parent dies, so a ``kill -9`` of a
build leaves no process behind (reliability finding 8).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import os
import signal
import sys
from collections.abc import Iterator
from typing import Any

from ..errors import InputError, LodbuilderError, MissingDependencyError

log = logging.getLogger(__name__)

#: how long to try reaching a Dask scheduler given by address
DASK_CONNECT_TIMEOUT = "15s"

#: the modules the forkserver imports before forking workers (libraries loaded and kernels warm)
PRELOAD = ["lodbuilder.build.jobs", "lodbuilder.build._warm"]


#: glibc tunables the workers' server starts with (they are read when a process starts, so they go
#: into the forkserver's environment: every worker forked from it has them). ``glibc.malloc.hugetlb=1``:
#: the blocks glibc maps on their own (every array over 4 MiB, see
#: :func:`lodbuilder._resources.map_large_blocks`) are advised to the kernel's transparent huge
#: pages (where it offers them on request, as Linux's default "madvise" mode does): a fault per 2 MiB
#: instead of per 4 KiB. On the 21.56M-point survey in 197 tiles the tree's page faults went 2.04 M
#: -> 0.17 M and its system time 17.2 -> 14.8 s (docs/benchmarks.md, "Less kernel work between tasks")
WORKER_TUNABLES = {"glibc.malloc.hugetlb": "1"}


def worker_tunables(current: str | None) -> str:
    """``GLIBC_TUNABLES`` for the workers' server: ``current`` (the caller's, if any) with each of
    :data:`WORKER_TUNABLES` it does not set already."""
    parts = [p for p in (current or "").split(":") if p]
    have = {p.split("=", 1)[0] for p in parts}
    return ":".join(parts + [f"{k}={v}" for k, v in WORKER_TUNABLES.items() if k not in have])


def _start_server() -> None:
    """Start the forkserver (if it is not running) with :func:`worker_tunables` in its environment;
    the caller's environment is left as it was."""
    from multiprocessing import forkserver

    before = os.environ.get("GLIBC_TUNABLES")
    os.environ["GLIBC_TUNABLES"] = worker_tunables(before)
    try:
        forkserver.ensure_running()
    finally:
        if before is None:
            del os.environ["GLIBC_TUNABLES"]
        else:
            os.environ["GLIBC_TUNABLES"] = before


def preload(rounds: bool = False) -> list[str]:
    """:data:`PRELOAD`, and the radius rounds' warm-up (:mod:`._warm_rounds`) for a build with
    ``seam_rounds``."""
    return PRELOAD + (["lodbuilder.build._warm_rounds"] if rounds else [])


def one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if isinstance(exc, LodbuilderError):
        return text
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def die_with_parent() -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux; a no-op elsewhere).

    Called in every pool worker (their parent is the forkserver, or the build's process with the
    ``fork`` start method) and in the forkserver itself (whose parent is the build's process), so a
    killed build takes its workers with it."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    parent = os.getppid()
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


def start_method() -> str:
    """How worker processes start: ``forkserver`` (they fork from a clean server process, with no
    copies of the caller's open files or threads); ``fork`` when the caller's main script has no
    file to re-import (a script read from stdin)."""
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    return "fork" if main_file is not None and not os.path.isfile(main_file) else "forkserver"


def mp_context(rounds: bool = False) -> Any:
    """The workers' multiprocessing context (:func:`start_method`); a forkserver not yet started
    will preload :func:`preload` (``rounds``: with the radius rounds' warm-up)."""
    import multiprocessing

    method = start_method()
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":
        # the server imports the build's libraries and loads the compiled kernels once; the
        # workers forked from it start warm (takes effect when the server starts)
        ctx.set_forkserver_preload(preload(rounds))
        _start_server()  # (here, not by the pool: with the workers' tunables)
    return ctx


def start_pool_server(workers: int | None, scheduler: str | None = None, dask_local: int | None = None,
                      rounds: bool = False) -> None:
    """For a build on a local process pool of ``workers`` (given: a build without workers may run in
    its own process; with a Dask scheduler or cluster: none), start the pool's forkserver now, where
    it is the start method: it imports the build's libraries and loads the compiled kernels (about
    1.1 CPU-s) while this process plans the build (the inputs' headers and checksums: 1.1 s for a
    survey of 196 LAZ files), instead of when the first task is submitted. The pool of :func:`make_executor` then forks its workers
    from it. Its parent-death request (``_warm``) is tied to the calling thread."""
    if workers is None or scheduler is not None or dask_local is not None or start_method() != "forkserver":
        return
    mp_context(rounds)  # (the preload list; starts the server)


#: Dask settings of a LocalCluster (its workers run nothing but the build's tasks; measured with a
#: busy 8 s task in a worker on a loaded 2-core machine: the worker's other threads added 10 % to
#: the task's CPU with distributed's defaults, 0.7 % with these):
#:
#: * ``pre-spawn-environ``: distributed's nanny sets these variables in the *calling* process's
#:   environment before it starts a worker (by default ``MALLOC_TRIM_THRESHOLD_=65536`` and
#:   ``OMP/MKL/OPENBLAS_NUM_THREADS=1``), where they stay after the build, and the forkserver
#:   started then inherits them: every worker forked from it, Dask's and a later process pool's,
#:   had glibc's allocator with a fixed 64 KiB trim threshold, which also turns off its adaptive
#:   mmap threshold: every array over 128 KiB mapped fresh from the kernel and unmapped when freed
#:   (page faults: +35 % CPU on a NumPy loop of 1.6 MB arrays). The workers give freed memory back
#:   themselves after a task that grew (:mod:`.tiled.timing`), so none is set: Dask's workers run in
#:   the environment the pool's run in (with :data:`WORKER_TUNABLES`).
#: * ``worker.profile.enabled``: the worker's statistical profiler sampled the task's stack every
#:   10 ms (for the dashboard; the build records its own task timings): 4 of those 10 %.
#: * ``admin.tick.interval`` (20 ms: an event-loop health check), ``admin.system-monitor.interval``
#:   (500 ms) and ``worker.memory.monitor-interval`` (100 ms: the worker's and the nanny's memory
#:   checks, psutil each time): the rest. A nanny still restarts a worker over 95 % of its memory
#:   limit, within a second instead of a tenth.
DASK_LOCAL_CONFIG: dict[str, Any] = {
    "distributed.nanny.pre-spawn-environ": {},
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "1s",
}


def dask_mp_context(rounds: bool = False) -> Any:
    """The multiprocessing context of distributed's nannies (``distributed.utils.get_mp_context``,
    under the current Dask configuration), with lodbuilder's forkserver preload (:data:`PRELOAD`)
    beside distributed's own: distributed sets its list of modules the first time it is asked, which
    replaced lodbuilder's, and every Dask worker started cold (imports and numba's cache loaded
    again in each). The server is started here (see below)."""
    from distributed.utils import get_mp_context

    ctx = get_mp_context()  # (sets distributed's preload, once per process)
    if ctx.get_start_method() == "forkserver":
        ctx.set_forkserver_preload(["distributed", *preload(rounds)])  # (takes effect when the server starts)
        # started here, by the calling thread: the server asks to die with the thread that started
        # it (die_with_parent), and distributed would start it from its event loop's thread, which
        # ends with the cluster (a process pool started after it then found no server)
        _start_server()
    return ctx


class InlineExecutor(cf.Executor):
    """Runs each job in the calling process when it is submitted (a single scan needs no pool)."""

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> cf.Future:
        fut: cf.Future = cf.Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as exc:
            fut.set_exception(exc)
        return fut


def check_workers(workers: Any, what: str = "workers") -> int | None:
    """``workers`` as an int >= 1 (None: the default). 0 and negative counts are refused alike."""
    if workers is None:
        return None
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"{what} must be a whole number of worker processes >= 1, got {workers!r}")
    return int(workers)


#: address schemes of dask.distributed's comm registry
DASK_SCHEMES = ("inproc", "tcp", "tls", "ucx", "ws", "wss")


def check_scheduler(scheduler: Any) -> Any:
    """``scheduler`` (a Dask address, ``tcp://host:port`` or ``host:port``; None) with its
    scheme checked before any work: an unknown one is one line, not distributed's traceback."""
    if scheduler is None:
        return None
    if not isinstance(scheduler, str) or not scheduler.strip():
        raise InputError(f"scheduler must be a Dask address like tcp://HOST:PORT, got {scheduler!r}")
    scheme, sep, _ = scheduler.partition("://")
    if sep and scheme.lower() not in DASK_SCHEMES:
        raise InputError(
            f"scheduler address {scheduler!r} has an unknown scheme {scheme!r}; give "
            f"tcp://HOST:PORT (or {', '.join(s for s in DASK_SCHEMES if s != 'tcp')})"
        )
    return scheduler


def _plural(n: int) -> str:
    return f"{n} worker{'s' if n > 1 else ''}"


@contextlib.contextmanager
def make_executor(workers: int | None = None, scheduler: str | None = None, dask_local: int | None = None,
                  *, inline: bool = False, rounds: bool = False) -> Iterator[tuple[cf.Executor, str]]:
    """``(executor, description)``: the calling process (``inline``), a local process pool of
    ``workers`` (default: one per core), or a Dask client's executor (``rounds``: its workers
    preload the radius rounds' warm-up, :func:`preload`)."""
    workers = check_workers(workers)
    dask_local = check_workers(dask_local, "dask_local")
    check_scheduler(scheduler)
    if scheduler is not None and dask_local is not None:
        raise InputError("give either a Dask scheduler address or dask_local, not both")
    if scheduler is None and dask_local is None:
        if inline:
            yield InlineExecutor(), "this process"
            return
        n = workers or os.cpu_count() or 1
        with cf.ProcessPoolExecutor(max_workers=n, mp_context=mp_context(rounds), initializer=die_with_parent) as ex:
            yield ex, f"process pool ({_plural(n)})"
        return
    try:
        import dask.distributed  # noqa: F401  (a missing extra is said here, before any work)
    except ImportError:
        raise MissingDependencyError(
            "building on Dask needs dask.distributed; pip install lodbuilder[distributed]"
        ) from None
    # distributed logs its start-up at INFO (scheduler, nannies, workers): follow lodbuilder's level
    # instead (-v shows them), and leave the caller's setting as it was afterwards
    dask_logger = logging.getLogger("distributed")
    dask_level = dask_logger.level
    dask_logger.setLevel(logging.getLogger("lodbuilder").getEffectiveLevel())
    try:
        with _dask_client(dask_local, scheduler, rounds) as (client, desc):
            yield client.get_executor(pure=False), desc
    finally:
        dask_logger.setLevel(dask_level)


@contextlib.contextmanager
def _dask_client(dask_local: int | None, scheduler: str | None, rounds: bool = False) -> Iterator[tuple[Any, str]]:
    """A Dask client on a new LocalCluster of ``dask_local`` workers or on ``scheduler``."""
    from dask.distributed import Client, LocalCluster

    cluster = None
    if dask_local is not None:
        import dask

        # the same start method, warm forkserver and environment as the local pool (see
        # DASK_LOCAL_CONFIG and dask_mp_context); Dask's default, spawn, starts every worker cold.
        # The scheduler's HTTP server always starts (None keeps the default port 8787, and a second
        # build at once warned "Port 8787 is already in use"): any free port instead
        with dask.config.set(DASK_LOCAL_CONFIG | {"distributed.worker.multiprocessing-method": start_method()}):
            dask_mp_context(rounds)
            cluster = LocalCluster(n_workers=dask_local, threads_per_worker=1, processes=True,
                                   dashboard_address=":0", silence_logs=logging.WARNING)
        client = Client(cluster)
        desc = f"Dask LocalCluster ({_plural(dask_local)})"
    else:
        try:
            client = Client(scheduler, timeout=DASK_CONNECT_TIMEOUT)
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"cannot reach Dask scheduler {scheduler!r} ({one_line(exc)}); check the address") from None
        desc = f"Dask scheduler {scheduler}"
    try:
        yield client, desc
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
