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
import shutil
import stat
import threading
import time
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


#: this thread's held archive locks: lock file -> (descriptor, depth); a writer that holds an
#: archive (a build) may call writers of that archive (its merges) without waiting for itself
_held = threading.local()


def _held_locks() -> dict[str, list[int]]:
    if not hasattr(_held, "locks"):
        _held.locks = {}
    return _held.locks


@contextlib.contextmanager
def lock(path: Path, *, wait: float | None = None, what: str = "an update") -> Iterator[None]:
    """Hold the advisory lock of archive ``path``; the lock file is removed when released.

    Every writer of an archive (a whole build, an update, a merge) holds it while it changes
    anything under the archive's directory. Another process that holds it makes this one wait:
    with a warning naming that process, for at most ``wait`` seconds (None: until it finishes;
    0: not at all), then ArchiveBusyError. ``what`` is how this writer is named to the others
    ("a build"). The same thread may take the lock again (its depth is counted).

    Removing a lock file is safe because a waiter that wakes up on a removed (or replaced) file
    sees that the name no longer refers to the file it locked, and tries again."""
    lp = lock_name(path)
    held = _held_locks()
    key = os.path.abspath(lp)
    if key in held:
        held[key][1] += 1
        try:
            yield
        finally:
            held[key][1] -= 1
        return
    fd = _acquire(path, lp, wait)
    with contextlib.suppress(OSError):  # who holds it, for the messages of those who wait
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {what}\n".encode(), 0)
    held[key] = [fd, 1]
    try:
        yield
    finally:
        del held[key]
        with contextlib.suppress(OSError):
            os.unlink(lp)
        os.close(fd)


def _acquire(path: Path, lp: Path, wait: float | None) -> int:
    """Open and lock ``lp`` (see :func:`lock`); returns the locked descriptor."""
    import fcntl

    t0 = time.monotonic()
    told = False
    while True:
        try:
            fd = os.open(lp, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise _foreign(lp, "is a symbolic link") from None
            raise disk_error(exc, path) from None
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1:
            os.close(fd)
            raise _foreign(lp, "is not a plain file of its own (a hard link or a special file)")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            left = None if wait is None else wait - (time.monotonic() - t0)
            if left is not None and left <= 0:
                os.close(fd)
                raise _busy(path, holder, wait) from None
            if not told:
                limit = "for it (--wait SECONDS limits the wait)" if wait is None else \
                    f"for it (at most {_seconds(wait)} s)"
                log.warning("archive %s is being written by another process (%s); waiting %s", path, holder, limit)
                told = True
            if left is None:
                fcntl.flock(fd, fcntl.LOCK_EX)
            else:
                os.close(fd)
                time.sleep(min(0.05, left))
                continue
        try:
            same = os.stat(lp).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


def _holder(fd: int) -> str:
    """Who holds the lock file ``fd``, as its holder wrote it ("pid 12, a build")."""
    try:
        pid, _, what = os.pread(fd, 200, 0).decode("utf-8", "replace").strip().partition(" ")
        return f"pid {int(pid)}, {what or 'a writer'}"
    except (OSError, ValueError):
        return "a writer"


def _seconds(s: float) -> str:
    return f"{s:g}"


def _busy(path: Path, holder: str, wait: float | None) -> ArchiveError:
    from ..errors import ArchiveBusyError

    held = f"archive {path} is being written by another process ({holder})"
    if not wait:
        return ArchiveBusyError(f"{held}; run again when it has finished, or pass --wait SECONDS to wait for it")
    return ArchiveBusyError(f"{held} and did not finish within --wait {_seconds(wait)} s; run again later "
                            "or wait longer")


def _foreign(path: Path, why: str) -> ArchiveError:
    return ArchiveError(f"{path} {why}; lodbuilder uses and cleans only the files and directories it made "
                        "beside an archive: move it away (or delete it yourself) and run again")


# ------------------------------------------------------------------------------ own directories

#: the file that marks a directory lodbuilder made beside an archive (holding the archive's name)
MARKER = ".lodbuilder-work"


def _marker_text(owner: str) -> str:
    return f"lodbuilder work directory of {owner}\n"


def dir_problem(directory: Path) -> str | None:
    """Why ``directory`` is not a plain directory lodbuilder may write and clean (a symbolic
    link, a file, a mount point), or None."""
    try:
        st = os.lstat(directory)
    except FileNotFoundError:
        return "does not exist"
    if stat.S_ISLNK(st.st_mode):
        return "is a symbolic link"
    if not stat.S_ISDIR(st.st_mode):
        return "is not a directory"
    if os.path.ismount(directory):
        return "is a mount point"
    return None


def check_plain_dir(directory: Path) -> None:
    """Raise ArchiveError when ``directory`` exists and is not a plain directory (see
    :func:`dir_problem`)."""
    if os.path.lexists(directory):
        problem = dir_problem(directory)
        if problem is not None:
            raise _foreign(directory, problem)


def own_dir_problem(directory: Path, owner: str) -> str | None:
    """Why ``directory`` is not a work directory lodbuilder made for ``owner`` (an archive's file
    name), or None when it is: a plain directory (not a symbolic link, not a mount point) holding
    the marker file naming ``owner``."""
    problem = dir_problem(directory)
    if problem is not None:
        return problem
    marker = directory / MARKER
    try:
        mst = os.lstat(marker)
        ok = stat.S_ISREG(mst.st_mode) and mst.st_size < 4096 and marker.read_text("utf-8") == _marker_text(owner)
    except (OSError, UnicodeDecodeError):
        ok = False
    if not ok:
        return f"was not made by lodbuilder for {owner} (it has no {MARKER} file naming it)"
    return None


def check_own_dir(directory: Path, owner: str) -> None:
    """Raise ArchiveError unless ``directory`` is a work directory lodbuilder made for ``owner``."""
    problem = own_dir_problem(directory, owner)
    if problem is not None:
        raise _foreign(directory, problem)


def make_own_dir(directory: Path, owner: str) -> Path:
    """Create the work directory ``directory`` for ``owner`` with its marker, or check that the one
    there is lodbuilder's (see :func:`own_dir_problem`)."""
    try:
        directory.mkdir()
    except FileExistsError:
        check_own_dir(directory, owner)
        return directory
    except OSError as exc:
        raise disk_error(exc, directory) from None
    try:
        (directory / MARKER).write_text(_marker_text(owner), "utf-8")
    except OSError as exc:
        with contextlib.suppress(OSError):
            directory.rmdir()
        raise disk_error(exc, directory) from None
    return directory


def remove_own_dir(directory: Path, owner: str) -> None:
    """Delete the work directory ``directory`` and what it holds, once checked to be lodbuilder's
    (a directory that is not is refused, never followed or emptied). Nothing to do if missing."""
    if not os.path.lexists(directory):
        return
    check_own_dir(directory, owner)
    shutil.rmtree(directory, ignore_errors=True)  # never follows the links it holds


def remove_own_dir_if_empty(directory: Path, owner: str) -> None:
    """Delete the work directory ``directory`` of ``owner`` when it holds nothing but its marker."""
    if own_dir_problem(directory, owner) is not None:
        return
    try:
        if {e.name for e in os.scandir(directory)} == {MARKER}:
            (directory / MARKER).unlink()
            directory.rmdir()
    except OSError:
        pass


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

    global _libc
    if _libc is None:  # the process's own symbols, libc's among them (find_library("c") would run
        _libc = ctypes.CDLL(None, use_errno=True)  # ldconfig and uname: two forks of this process)
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
