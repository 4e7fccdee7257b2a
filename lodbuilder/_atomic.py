"""The one way lodbuilder replaces a file: write a temporary beside it, then :func:`publish` it.

**Guarantee** (what every caller relies on): :func:`publish` fsyncs the temporary's data, renames it
onto the destination (``os.replace``: atomic on POSIX file systems) and fsyncs the directory. A
reader sees the old file or the new one, never a mix; once it returns, the new file survives a
crash or a power cut; if the process dies before the rename, the destination is untouched and only
the temporary is left (its name starts with a dot, so the owner's tidy-up finds it).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any


def fsync_file(path: Path) -> None:
    """Flush the file's data and metadata to the device."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(directory: Path) -> None:
    """Flush a directory's entries (a rename in it) to the device, where the system allows it."""
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def publish(tmp: Path, path: Path) -> None:
    """fsync ``tmp``, rename it onto ``path`` and fsync the directory (the atomic step)."""
    fsync_file(tmp)
    os.replace(tmp, path)
    fsync_dir(Path(path).parent)


def temporary(path: Path) -> Path:
    """The temporary name of this process for ``path`` (hidden, in the same directory)."""
    path = Path(path)
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def replace_with(path: Path, write: Callable[[Path], Any]) -> None:
    """Replace the file at ``path`` by what ``write(tmp)`` writes to a temporary beside it,
    atomically (see the module's guarantee); on any error the temporary is removed."""
    tmp = temporary(path)
    try:
        write(tmp)
        publish(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_bytes(path: Path, data: bytes) -> None:
    """Replace the file at ``path`` by ``data``, atomically."""
    replace_with(path, lambda tmp: tmp.write_bytes(data))
