"""File helpers shared by the readers and writers: input checks, atomic output, hashing."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import signal
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from .._atomic import publish
from .._validate import strict_keywords
from ..errors import LodbuilderError, ScanFileError


def check_input_file(path: str | os.PathLike[str]) -> Path:
    """Return ``path`` as a Path if it names a readable regular file, else raise ScanFileError.

    Non-regular files (FIFOs, sockets, devices) are refused before they are opened: reading a
    FIFO would wait forever for a writer. A symbolic-link loop is named as such."""
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ScanFileError(f"{p}: symbolic link loop (the link points back to itself); fix the link") from None
        if exc.errno == errno.ENOENT:
            if os.path.islink(p):
                raise ScanFileError(f"{p}: broken symbolic link (its target does not exist); fix the link") from None
            raise ScanFileError(f"{p}: no such file; check the path") from None
        if exc.errno == errno.EACCES:
            raise ScanFileError(f"{p}: cannot be read (permission denied); fix its permissions") from None
        raise ScanFileError(f"{p}: cannot be read ({exc.strerror}); check the path") from None
    if stat.S_ISDIR(st.st_mode):
        raise ScanFileError(f"{p}: is a directory, not a scan file; pass a file (or a collection)")
    if not stat.S_ISREG(st.st_mode):
        raise ScanFileError(f"{p}: is {_kind(st.st_mode)}, not a regular file; save the scan to a file first")
    if not os.access(p, os.R_OK):
        raise ScanFileError(f"{p}: cannot be read (permission denied); fix its permissions")
    return p


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "a special file"


def output_dir_problem(path: str | os.PathLike[str]) -> tuple[Path, str | None]:
    """``(directory, problem)`` of an output ``path``: what is wrong with the directory a new file
    would go in ("does not exist; create it first", "is not writable; ...") or None. The one
    check of output directories; the callers add their own subject and exception class."""
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        return parent, "does not exist; create it first"
    if not os.access(parent, os.W_OK | os.X_OK):
        return parent, "is not writable; choose another output path"
    return parent, None


def check_output_path(path: str | os.PathLike[str]) -> Path:
    """Return ``path`` as a Path if its directory exists and is writable, else raise ScanFileError."""
    p = Path(path)
    parent, problem = output_dir_problem(p)
    if problem:
        raise ScanFileError(f"{p}: output directory {parent} {problem}")
    if p.is_dir():
        raise ScanFileError(f"{p}: is a directory; give an output file name")
    return p


def _default_mode() -> int:
    """The mode a new file gets from the process umask (0o644 under the usual umask 022)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path in the destination directory; rename it onto ``path`` on success.

    The temporary file keeps the destination's suffix (some libraries choose the encoding from it)
    and gets the permissions a plain new file would. On any error the temporary file is removed and
    ``path`` is left untouched. A missing directory is an error (:func:`check_output_path`),
    never created.
    """
    p = check_output_path(path)
    parent = p.parent if str(p.parent) else Path(".")
    try:
        fd, tmp = tempfile.mkstemp(dir=parent, prefix=f".{p.name}.", suffix=".part" + "".join(p.suffixes[-1:]))
    except OSError as exc:
        raise write_error(p, exc) or exc from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, _default_mode())
        publish(tmp_path, p)
    except BaseException as exc:
        problem = write_error(p, exc, parent) if isinstance(exc, Exception) else None
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        if problem is not None:
            raise problem from None
        raise


#: a write that failed with this little space left on its device failed for want of space (a
#: library that reports no errno: lazrs' "IoError: Failed to call write", NumPy's "N requested
#: and M written", copclib's abort)
NEARLY_FULL = 1 << 20


def write_error(path: Path, exc: BaseException, parent: Path | None = None) -> ScanFileError | None:
    """The one-line error for a failed write of the output ``path``, or None when ``exc`` is not
    a failed write (a bug, or an error of ours that already says what to do). A full disk (ENOSPC,
    a quota, or any library error while the device has under :data:`NEARLY_FULL` bytes free) is
    named as such; another OSError keeps its reason. Called while the partial file still takes its
    space."""
    if isinstance(exc, LodbuilderError):
        return None
    no = getattr(exc, "errno", None)
    if no in (errno.ENOSPC, errno.EDQUOT) or (no is None and _nearly_full(parent or path.parent)):
        return ScanFileError(f"{path}: no space left on the device; free some space or choose "
                             "another location (nothing was written)")
    if isinstance(exc, OSError) or library_io_error(exc):
        reason = getattr(exc, "strerror", None) or exc_line(exc)
        return ScanFileError(f"{path}: cannot be written ({reason}); check the disk and "
                             "permissions (nothing was written)")
    return None


def _nearly_full(directory: Path) -> bool:
    try:
        st = os.statvfs(directory)
    except (OSError, AttributeError):  # (no statvfs on Windows)
        return False
    return st.f_bavail * st.f_frsize < NEARLY_FULL


def library_io_error(exc: BaseException) -> bool:
    """Whether ``exc`` is an I/O failure reported by a native library without an errno (lazrs:
    ``LazrsError: IoError: ...``)."""
    return type(exc).__name__ == "LazrsError" and "IoError" in str(exc)


def run_isolated(write: Callable[[Path], object], path: Path, library: str) -> None:
    """``write(path)`` in a forked child process, for a native library that may abort the process
    instead of raising (copclib calls std::terminate when a write fails, e.g. on a full disk):
    an abort then ends the child only, and its failure is raised here as an OSError without
    errno naming ``library`` and what it printed (which :func:`atomic_output` turns into one line). Where there is no
    fork (Windows) ``write`` runs in this process."""
    if not hasattr(os, "fork"):
        write(path)
        return
    with tempfile.TemporaryFile() as err:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        pid = os.fork()
        if pid == 0:  # pragma: no cover (the child; coverage does not follow it)
            code = 0
            try:
                os.dup2(err.fileno(), 2)
                import faulthandler

                faulthandler.disable()  # (an abort here is reported by the parent, in one line)
                write(path)
            except BaseException as exc:  # noqa: BLE001 (reported to the parent)
                with contextlib.suppress(Exception):
                    os.write(2, f"\n{type(exc).__name__}: {exc_line(exc)}\n".encode())
                code = 1
            finally:
                os._exit(code)
        _, status = os.waitpid(pid, 0)
        if os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0:
            return
        err.seek(0)
        lines = [ln.strip() for ln in err.read().decode("utf-8", "replace").splitlines()]
        said = next((ln for ln in reversed(lines) if ln and not ln.startswith("what():")), "")
        said = next((ln for ln in lines if ln.startswith("terminate called")), said)
    how = (f"was killed by {signal.Signals(os.WTERMSIG(status)).name}" if os.WIFSIGNALED(status)
           else f"stopped with exit status {os.WEXITSTATUS(status)}")
    raise OSError(f"{library} {how}{': ' + said if said else ''}")


def exc_line(exc: BaseException) -> str:
    """An exception's message on one line (white space folded), or its class name when it has
    none: the ``(...)`` part of the errors and warnings of lodbuilder.io."""
    return " ".join(str(exc).split()) or type(exc).__name__


def library_panic(exc: BaseException) -> bool:
    """Whether ``exc`` is a Rust library's panic reaching Python: pyo3's PanicException derives from
    BaseException, not Exception, and lazrs reports some damaged LAZ files this way (a point size of 0)."""
    return type(exc).__name__ == "PanicException"


@strict_keywords
def file_sha256(path: str | os.PathLike[str], chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()
