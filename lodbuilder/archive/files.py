"""The file-system side of archive writes: temporaries, locks, atomic renames, disk space.

Every archive file (a single-scan archive, a part, an index) is written to a hidden temporary
beside its final name (``.<name>.tmp-<pid>-<random>``), flushed, fsync'ed and renamed into place
(``os.replace``), so a reader or a ``kill -9`` never sees half a file. Writers of one archive are
serialised by an advisory lock on ``.<archive>.lock``, which exists only while a writer runs.

Disk space is reserved before HDF5 writes anything (``fallocate`` with ``FALLOC_FL_KEEP_SIZE`` on
Linux, a free-space check elsewhere): HDF5 does not survive ``ENOSPC`` during a flush (the library
is left in a state that crashes the process when it exits), so a full disk must be found before
HDF5 sees it.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

from .._atomic import fsync_dir, fsync_file, publish  # noqa: F401 - the archive writer publishes through F
from ..errors import ArchiveError
from ..io._files import output_dir_problem
from .index import is_url, url_text

log = logging.getLogger(__name__)


def tmp_name(path: Path) -> Path:
    """A hidden temporary beside ``path``, named after it and this process."""
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")


def lock_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.lock")


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def temp_owner(name: str, final: str | None = None) -> int | None:
    """The pid in a temporary's name ``.<final>.tmp-<pid>-<hex>``, or None if it is not one."""
    if not name.startswith("."):
        return None
    base, sep, rest = name[1:].rpartition(".tmp-")
    if not sep or (final is not None and base != final):
        return None
    try:
        return int(rest.split("-")[0])
    except ValueError:
        return None


def remove_stale_temps(path: Path) -> list[Path]:
    """Delete temporaries of ``path`` left by writers that were killed (their pid is gone)."""
    removed: list[Path] = []
    try:
        entries = list(path.parent.iterdir())
    except OSError:
        return removed
    for p in entries:
        pid = temp_owner(p.name, path.name)
        if pid is not None and pid != os.getpid() and not pid_alive(pid):
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
                log.info("removed stale temporary %s", p)
    return removed


@contextlib.contextmanager
def lock(path: Path) -> Iterator[None]:
    """Hold the advisory lock of archive ``path``; the lock file is removed when released.

    Removing a lock file is safe because a waiter that wakes up on a removed (or replaced) file
    sees that the name no longer refers to the file it locked, and tries again."""
    import fcntl

    lp = lock_name(path)
    while True:
        try:
            fd = os.open(lp, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise disk_error(exc, path) from None
        fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            same = os.stat(lp).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lp)
        os.close(fd)


def check_writable_dir(path: str | os.PathLike[str], what: str = "output") -> None:
    path = Path(path)
    if is_url(path):
        raise ArchiveError(
            f"{what} {url_text(path)} is a URL; archives are read-only over HTTP/S3: build into "
            "a local file and upload it (the file and its .scans directory)"
        )
    parent, problem = output_dir_problem(path)
    if problem:
        raise ArchiveError(f"{what} directory {parent} {problem}")


def unlink_quietly(path: Path) -> None:
    with contextlib.suppress(OSError):
        path.unlink()


# ------------------------------------------------------------------------------------ disk space

_FALLOC_FL_KEEP_SIZE = 0x01
_FALLOC_FL_PUNCH_HOLE = 0x02
_libc = None


def _fallocate(fd: int, mode: int, offset: int, length: int) -> None:
    import ctypes
    import ctypes.util

    global _libc
    if _libc is None:
        _libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
    fn = getattr(_libc, "fallocate", None)
    if fn is None:
        raise OSError(errno.EOPNOTSUPP, "fallocate is not available")
    fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]
    if fn(fd, mode, offset, length) != 0:
        e = ctypes.get_errno()
        raise OSError(e, os.strerror(e))


def reserve(path: Path, nbytes: int, what: str) -> None:
    """Make sure ``nbytes`` more bytes can be written to the file at ``path`` (which exists).

    On Linux the blocks are allocated beyond the end of the file without changing its size, so the
    writes that follow cannot fail for lack of space; elsewhere the free space is checked. Raises
    a one-line ArchiveError naming ``what`` when the space is not there."""
    nbytes = max(0, int(nbytes))
    fd = os.open(path, os.O_RDWR)
    try:
        size = os.fstat(fd).st_size
        try:
            _fallocate(fd, _FALLOC_FL_KEEP_SIZE, size, nbytes)
            return
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise no_space(path, what, nbytes) from None
            if exc.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                raise disk_error(exc, path) from None
        st = os.fstatvfs(fd)
        if st.f_bavail * st.f_frsize < nbytes:
            raise no_space(path, what, nbytes)
    finally:
        os.close(fd)


def release(path: Path) -> None:
    """Free the blocks reserved beyond the end of ``path`` (see :func:`reserve`)."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDWR)
        try:
            size = os.fstat(fd).st_size
            _fallocate(fd, _FALLOC_FL_PUNCH_HOLE | _FALLOC_FL_KEEP_SIZE, size, 1 << 50)
        finally:
            os.close(fd)


def no_space(path: Path, what: str, nbytes: int) -> ArchiveError:
    return ArchiveError(
        f"no space left on the device of {path.parent} for {what} (needs up to "
        f"{_mb(nbytes)}); free some space or choose another location; nothing was changed"
    )


def _mb(nbytes: int) -> str:
    return f"{nbytes / 1e6:.1f} MB" if nbytes >= 100_000 else f"{nbytes / 1e3:.0f} kB"


def disk_error(exc: BaseException, path: Path) -> BaseException:
    """A one-line ArchiveError for a full disk or a failed file operation on ``path``."""
    no = getattr(exc, "errno", None)
    text = str(exc)
    if no in (errno.ENOSPC, errno.EDQUOT) or "No space left" in text or "quota" in text.lower():
        return ArchiveError(
            f"no space left on the device of {path.parent} while writing {path.name}; free some "
            "space or choose another location; nothing was changed"
        )
    if isinstance(exc, OSError) and getattr(exc, "strerror", None):
        return ArchiveError(f"cannot write {path}: {exc.strerror}; nothing was changed")
    return exc
