"""This machine's resources: cores, physical memory, memory budgets given as text, and giving freed
heap memory back. A leaf module (no lodbuilder import but the errors), so that the engine, the build
pipeline and the CLI ask one place."""

from __future__ import annotations

import functools
import math
import mmap
import os
from typing import Any

from .errors import InputError

_LIBC: Any = None

TRIM_MIN_POINTS = 200_000  # below this the phases free a few MB: trimming costs more than it returns


def cores() -> int:
    """The cores this process may run on (its CPU affinity, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def physical_memory() -> int:
    """Bytes of physical memory (8 GiB where the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 8 << 30


def default_max_memory() -> int:
    """The default memory budget of a build: 60 % of the physical memory."""
    return int(0.6 * physical_memory())


def parse_bytes(text: Any, what: str = "--max-memory") -> int:
    """``3GB``, ``512MiB``, ``2e9`` or a plain number of bytes -> int (decimal and binary units)."""
    import numpy as np

    if isinstance(text, (int, np.integer)) and not isinstance(text, bool):
        value = float(text)
    else:
        s = str(text).strip().replace("_", "")
        units = {"": 1, "b": 1, "k": 1e3, "kb": 1e3, "m": 1e6, "mb": 1e6, "g": 1e9, "gb": 1e9, "t": 1e12, "tb": 1e12,
                 "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40}
        num = s.rstrip("kmgtibKMGTIB")
        unit = s[len(num):].lower()
        try:
            value = float(num) * units[unit]
        except (ValueError, KeyError):
            raise InputError(f"{what} must be a number of bytes such as 3GB, 512MiB or 2e9, got {text!r}") from None
    if not math.isfinite(value) or value < 64 << 20:
        raise InputError(f"{what} must be at least 64 MiB, got {text!r}")
    return int(value)


def release_freed_memory(n_points: int | None = None) -> None:
    """Give freed heap memory back to the system (glibc's malloc_trim; a no-op elsewhere).

    The kernels allocate and free hundreds of MB per phase through malloc; glibc keeps much of it
    (its mmap threshold grows with the blocks freed), so without this the process's resident size
    after a phase stays near that phase's peak and the next phase stacks on top of it. For an
    ordering of fewer than TRIM_MIN_POINTS points (``n_points``) it does nothing: a trim walks the
    heap and the next phase faults the returned pages in again (about 6 ms of a 40k-point scan's
    270 ms)."""
    global _LIBC
    if n_points is not None and n_points < TRIM_MIN_POINTS:
        return
    if _LIBC is None:
        try:
            import ctypes

            _LIBC = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):  # not glibc
            _LIBC = False
    if _LIBC:
        _LIBC(0)
    drop_compiler_pages()


MMAP_THRESHOLD = 4 << 20  # bytes: blocks at least this large are mapped on their own (glibc)
M_MMAP_THRESHOLD = -3  # (glibc's mallopt parameter)


def map_large_blocks() -> None:
    """Have glibc's malloc map every block of at least MMAP_THRESHOLD bytes on its own (a no-op
    elsewhere). Its default threshold starts at 128 KiB and rises with every large block freed, up
    to 32 MiB: the engine's temporaries of a few MB to 32 MB then come from the heap, and once freed
    stay in the process (another phase's arrays are larger and mapped anew) until the next trim.
    Mapped on their own, they go back to the system when freed: 8-15 MiB less at the band's and
    the ordering's peak of a 1M-point scan (a fixed threshold stops the rise)."""
    global _MALLOPT
    if _MALLOPT is None:
        try:
            import ctypes

            _MALLOPT = ctypes.CDLL("libc.so.6").mallopt
        except (OSError, AttributeError):  # not glibc
            _MALLOPT = False
    if _MALLOPT:
        _MALLOPT(M_MMAP_THRESHOLD, MMAP_THRESHOLD)


_MALLOPT: Any = None
_CLEAN: Any = None  # (the compiler's clean mappings, madvise) once found
COMPILER_LIBRARY = "libllvmlite"  # numba's compiler: LLVM, one shared library of about 180 MB
MADV_DONTNEED = 4  # (Linux)


def drop_compiler_pages() -> int:
    """Drop the resident pages of the JIT compiler's code (llvmlite's LLVM library) from this
    process; returns the bytes of the mappings advised (0 where there is nothing to drop or this is
    not Linux).

    Loading the kernels from numba's cache runs LLVM (its start-up and its object loader), and the
    pages of LLVM's code it touched stay in the process's resident size: about 69 MiB, more than
    the rest of numba, numpy and h5py together, and none of it is used while the kernels run.
    These pages are clean copies of the library file, so the kernel drops them from the process on
    MADV_DONTNEED and maps them again from the page cache when LLVM runs again (a kernel loaded
    later, a compile: minor page faults, about 10 MiB for the rest of the engine's kernels). Only
    mappings that cannot hold data of their own are advised: not writable and with no anonymous
    (copied-on-write) page; a writable or relocated mapping would lose its contents. They are
    found once (reading smaps costs about 20 ms; a loaded library's mappings do not change)."""
    global _CLEAN
    import sys

    if "llvmlite" not in sys.modules:  # never loaded: nothing resident
        return 0
    try:
        if _CLEAN is None:
            import ctypes

            with open("/proc/self/smaps") as f:
                ranges = clean_mappings(f.read(), COMPILER_LIBRARY)
            madvise = ctypes.CDLL("libc.so.6").madvise
            madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
            if not ranges:  # (the library is not mapped yet: look again next time)
                return 0
            _CLEAN = (ranges, madvise)
    except (OSError, AttributeError):  # not Linux, or no glibc
        _CLEAN = ([], None)
    ranges, madvise = _CLEAN
    done = 0
    for start, end in ranges:
        if madvise(start, end - start, MADV_DONTNEED) == 0:
            done += end - start
    return done


def drop_library_pages() -> int:
    """Drop the resident pages of every loaded file's clean mappings from this process (read-only,
    no anonymous page: see :func:`clean_mappings`); returns the bytes of the mappings advised (0
    where this is not Linux).

    Besides the compiler (:func:`drop_compiler_pages`), start-up and reading leave code pages of
    libraries the ordering never calls in the resident size: the readers' (lazrs, pyproj's
    libproj and its SQLite, OpenSSL for laspy's HTTP client), Python's and numpy's start-up code:
    about 29 MiB after reading a LAZ file, 12 MiB after a PLY file. They are clean copies of their
    files: the kernel maps a page again from the page cache when it is used again (a minor fault;
    the interpreter's and numpy's hot pages come back within milliseconds). smaps is read on every
    call: a mapping found earlier could have been replaced by a writable one since."""
    if _madvise() is None:
        return 0
    try:
        with open("/proc/self/smaps") as f:
            ranges = clean_mappings(f.read(), "/")  # every mapping of a file (not [vdso], [heap], ...)
    except OSError:
        return 0
    done = 0
    for start, end in ranges:
        if _madvise()(start, end - start, MADV_DONTNEED) == 0:
            done += end - start
    return done


@functools.lru_cache(maxsize=1)
def _madvise() -> Any:
    """libc's madvise (None where there is no glibc)."""
    try:
        import ctypes

        madvise = ctypes.CDLL("libc.so.6").madvise
    except (OSError, AttributeError):
        return None
    madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    return madvise


def clean_mappings(smaps: str, name: str) -> list[tuple[int, int]]:
    """The address ranges, in the text of ``/proc/<pid>/smaps``, of the mappings of a file whose
    path contains ``name`` that are not writable and hold no anonymous page (clean copies of the
    file only: dropping their pages loses nothing)."""
    out = []
    cur: tuple[int, int] | None = None
    for line in smaps.splitlines():
        f = line.split()
        if len(f) >= 5 and "-" in f[0] and not f[0].endswith(":"):  # a mapping's header line
            start, end = (int(x, 16) for x in f[0].split("-"))
            cur = (start, end) if len(f) >= 6 and name in f[5] and "w" not in f[1] else None
        elif cur is not None and f[:1] == ["Anonymous:"]:
            if f[1] == "0":
                out.append(cur)
            cur = None
    return out


class PassMap(mmap.mmap):
    """A private (copy-on-write) map of a file written only to hold an array while the engine
    orders a scan (:func:`lodbuilder.build.jobs.set_aside`): nobody writes to it, so the pages an
    engine pass read can be given back as soon as the pass ends (:func:`release_pages`) and are
    read from the file again by the next one."""


def release_pages(arr: Any) -> None:
    """Give back the resident pages of ``arr`` when it is an array over a :class:`PassMap` (a scan
    set aside); nothing for any other array."""
    base = getattr(arr, "base", None)
    if isinstance(base, PassMap) and len(base) > 1:
        try:
            base.madvise(mmap.MADV_DONTNEED)
        except (AttributeError, OSError, ValueError):  # not Linux, or closed
            pass
