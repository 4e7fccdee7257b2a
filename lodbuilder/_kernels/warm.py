"""First-run compilation of the kernels.

The kernels compile on first use and numba caches them (``cache=True``; in ``__pycache__`` beside
this package, or in ``NUMBA_CACHE_DIR``). A cold cache costs seconds, so when it is cold the engine
compiles the marching kernel (``grid_phase`` with the march and its heaps: about half of the
compile time) in a child process while this process compiles all the others (two cores do it in
about half the time), and says so through the progress callback. The tail's kernels come last
here: the helpers they share with the march (heaps, cell keys) are in the cache by then. The two
kernels of the one-sided band (thin parts only) compile when first used.
On a busy machine (load average above the cores minus one) everything compiles in this process:
a child would only compete with it (measured on 2 cores at load ~4: 17 s instead of 24 s for a
cold ``lodbuilder demo``). Python's garbage collector runs less often meanwhile.

Every kernel is compiled for one signature: the dtypes the engine passes are fixed, and the
prototypes below are those dtypes (a test checks that an ordering compiles nothing else).
"""

from __future__ import annotations

import contextlib
import gc
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

MESSAGE = "compiling kernels, first run only"
_WARM = False  # every kernel is known to be compiled or cached (in this process)

_F64_2 = np.empty((0, 3))
_F32_2 = np.empty((0, 3), np.float32)
_I32_2 = np.empty((0, 6), np.int32)
_F64 = np.empty(0)
_F32 = np.empty(0, np.float32)
_I64 = np.empty(0, np.int64)
_I32 = np.empty(0, np.int32)
_U8 = np.empty(0, np.uint8)


def _prototypes() -> dict[str, dict[str, tuple[Any, ...]]]:
    """Per group, per kernel (module.name): example arguments of the engine's call."""
    i, f, b = np.int64(0), 0.5, True
    return {
        "band": {  # this process, in this order
            "grid.cell_order": (_F64_2, _F64, f),
            "grid.hash_collisions": (_F64_2,),
            "grid.radix_argsort": (_I64,),
            "grid.kth_neighbour": (_F64_2, _I32, _I64, _F64_2, i),
            "grid.grid_coords": (_F64_2, _I32, _F64, f),
            "sheets.cell_separation": (_F64_2, _I32, f, f, f, f),
            "grid.band_voxels": (_F64_2, _F64, _F64, _I32, _I64, _I32, _I64, i),
            "grid.neighbour_table": (_I64,),
            "topology.nearest_corners": (_F64_2, _I32_2, _I32, _F32),
            "topology.point_pieces": (_I32_2, _I32, _U8, _F32),
            "grid.coarse_runs": (_I64, _I32, i),
            "pieces.first_entries": (_I32, _I32, i),
            "tail.euclid_tail": (
                _F64_2, _I32_2, _I32, _I64, _I32, _I32, _I32, i, _F64, b, f, _F32, _F32_2, f,
                _I32, _I32, _I32, _F64, _I32, i, i, f, _I32, _F64, _I64,
            ),
        },
        "thin": {  # only scans with thin parts use these: compiled on first use (about 0.5 s)
            "grid.one_sided_cost": (_I64, _I32, _F64_2, _F32_2, _F64, _F64, f, f),
            "sheets.sheet_cut": (_I64, _I32_2, _I32, _I32, _F32, _F64_2, _F32_2, _F64),
            "sheets.normal_agreement": (_F64_2, _I32, _F64, _F64_2, f, i),
            "topology.nearest_corners_since": (_F64_2, _I32_2, _I32, _F32, _F32, _U8),
        },
        "ordering": {  # the child process
            "march.grid_phase": (
                _F64_2, _I64, _I32_2, _I32, _U8, _F32, _F64, b, _I32, _F32_2, f, _I32, i, f, f, b, _I32, _F64, _I64,
                _I32, i,
            ),
        },
    }


def _dispatcher(name: str) -> Any:
    import importlib

    module, func = name.split(".")
    return getattr(importlib.import_module(f"lodbuilder._kernels.{module}"), func)


def signatures(group: str) -> dict[str, tuple[Any, ...]]:
    """The numba signature each kernel of ``group`` is compiled for."""
    import numba

    return {name: tuple(numba.typeof(a) for a in args) for name, args in _prototypes()[group].items()}


@contextlib.contextmanager
def fewer_collections() -> Iterator[None]:
    """Python's cyclic garbage collector, less often: numba's compiler makes millions of small
    objects and the collections they trigger traverse every object of the process again and
    again (about 10 % of the compile time; 0.15 of the 1.3 CPU-s of ``lodbuilder build`` of a
    small scan, mostly numba's import and kernel loading). The objects that exist already are
    frozen (never traversed) and the first generation is collected every 10,000 allocations
    instead of 700; everything is back as before afterwards (about 20 MB more at the peak). Nested,
    the outermost one unfreezes (an inner one only freezes the objects made since; it does not
    ask for the freeze count, which walks every frozen object: 6 ms a call inside a build)."""
    global _HELD
    old = gc.get_threshold()
    outermost = _HELD == 0 and gc.get_freeze_count() == 0
    gc.freeze()
    gc.set_threshold(10_000, 10, 10)
    _HELD += 1
    try:
        yield
    finally:
        _HELD -= 1
        gc.set_threshold(*old)
        if outermost:
            gc.unfreeze()


_HELD = 0  # fewer_collections blocks open


def compile_group(group: str) -> None:
    """Compile (or load from the cache) every kernel of ``group`` for its signature."""
    with fewer_collections():
        for name, sig in signatures(group).items():
            dispatcher = _dispatcher(name)
            with _light_refresh(dispatcher):
                dispatcher.compile(sig)


@contextlib.contextmanager
def _light_refresh(dispatcher: Any) -> Iterator[None]:
    """numba refreshes its target context before it loads a kernel from the cache: the first
    refresh of a process imports and installs every implementation numba has (arrays, unicode,
    random generators, typed containers, ...: about 0.3 CPU-s, 4 % of ``lodbuilder build`` of 1M
    points), which only compiling needs; running compiled code needs numba's runtime only. Within
    the block, ``dispatcher``'s cache loads after starting the runtime alone; compiling (when the
    cache misses) still refreshes in full."""
    cache: Any = getattr(dispatcher, "_cache", None)
    load = getattr(cache, "_load_overload", None)
    guard = getattr(cache, "_guard_against_spurious_io_errors", None)
    if load is None or guard is None:  # (no cache, or another numba's internals)
        yield
        return

    def light_load(sig: Any, target_context: Any) -> Any:
        from numba.core.runtime import rtsys

        rtsys.initialize(target_context)
        with guard():
            return load(sig, target_context)
        return None  # (the guard swallowed an I/O error: compile instead)

    cache.load_overload = light_load
    try:
        yield
    finally:
        vars(cache).pop("load_overload", None)


def is_cold() -> bool:
    """Whether some engine kernel has no valid cache entry (numba's cache index for the current
    source is missing). Errs on the side of "warm" if numba's cache layout is not the expected one."""
    try:
        for group in ("band", "ordering"):
            for name in _prototypes()[group]:
                cache = _dispatcher(name)._cache
                if not cache._cache_file._load_index():  # {} when missing or stale
                    return True
    except Exception:  # pragma: no cover - another numba's internals
        return False
    return False


def _child_helps() -> bool:
    """Whether a second process would compile on a free core: at least two cores for this process
    and a load average below their count minus one. On a busy machine the child only competes
    with this process and adds its own start-up and the helpers both compile (about 2 s of CPU).
    ``LODBUILDER_COMPILE_CHILD=0`` or ``1`` decides instead (benchmarks)."""
    forced = os.environ.get("LODBUILDER_COMPILE_CHILD", "")
    if forced in ("0", "1"):
        return forced == "1"
    try:
        cores = len(os.sched_getaffinity(0))
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        cores, load = os.cpu_count() or 1, 0.0
    return cores >= 2 and load <= cores - 1


def start_ordering_compile() -> subprocess.Popen | None:
    """Compile the marching kernel in a child process (into numba's cache); None if it cannot start
    or would not help (see :func:`_child_helps`)."""
    if not _child_helps():
        return None
    root = str(Path(__file__).resolve().parents[2])
    code = (
        f"import sys; sys.path.insert(0, {root!r}); "
        "from lodbuilder._kernels.warm import compile_group; compile_group('ordering')"
    )
    try:
        return subprocess.Popen(
            [sys.executable, "-c", code],
            env=dict(os.environ),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    except OSError:  # pragma: no cover - no processes allowed
        return None


def ensure_compiled(progress: Any = None) -> bool:
    """Compile the engine's kernels if the cache is cold (the two groups at once on two processes
    when a core is free, else one after the other here), reporting MESSAGE as the progress stage
    meanwhile. Returns whether anything was compiled."""
    global _WARM
    from ..progress import report

    if _WARM:
        return False
    if not is_cold():
        for group in ("band", "ordering"):  # loaded now, without numba's full refresh (_light_refresh)
            compile_group(group)
        _WARM = True  # checked once per process: the check reads every kernel's cache index
        return False
    report(progress, MESSAGE, 0, 1)
    child = start_ordering_compile()
    compile_group("band")
    if child is not None:
        child.wait()
    compile_group("ordering")  # loads what the child cached (or compiles it, if the child failed)
    report(progress, MESSAGE, 1, 1)
    _WARM = True
    return True
