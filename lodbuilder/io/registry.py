"""Which module reads and writes which file suffix.

A format module ``lodbuilder.io.<name>`` defines ``read(path: Path) -> list[Scan]`` (one Scan per scan
in the file; the points already in world coordinates) and, when it can write,
``write(path: Path, points, attributes, metadata) -> list[str] | None`` (``path`` is a temporary
file that the caller renames into place; the list holds one line per change the format forced,
which the caller logs as warnings; ``metadata["crs_wkt"]`` is the CRS to write), and optionally
``check_output(path: Path) -> None``, which :func:`writer_for` calls with the real output path to
refuse what the module cannot write (a missing library) before any work. Modules are imported
only when a file of their kind is used, so optional dependencies (laspy, pye57) are needed only
for their formats.
"""

from __future__ import annotations

import os
from importlib import import_module
from pathlib import Path
from types import ModuleType

from .._validate import strict_keywords
from ..errors import UnsupportedFormatError

#: suffix -> format module name, for reading
READERS: dict[str, str] = {
    ".ply": "ply",
    ".las": "las",
    ".laz": "las",  # also COPC (.copc.laz): a COPC file is a valid LAZ file
    ".e57": "e57",
    ".xyz": "text",
    ".pts": "text",
    ".csv": "text",
    ".txt": "text",
    ".npy": "npy",
    ".npz": "npy",
}

#: suffix -> format module name, for writing
WRITERS: dict[str, str] = {
    ".ply": "ply",
    ".las": "las",
    ".laz": "las",  # not .copc.laz: see writer_for
    ".npy": "npy",
    ".npz": "npy",
    ".csv": "text",
    ".xyz": "text",
}


@strict_keywords
def register(suffix: str, module: str, *, read: bool = True, write: bool = False) -> None:
    """Register a format module (a full dotted module path, or a name under lodbuilder.io)."""
    suffix = suffix.lower() if suffix.startswith(".") else "." + suffix.lower()
    if read:
        READERS[suffix] = module
    if write:
        WRITERS[suffix] = module


def suffix_of(path: str | os.PathLike[str]) -> str:
    return Path(path).suffix.lower()


def _module(name: str) -> ModuleType:
    return import_module(name if "." in name else f"lodbuilder.io.{name}")


def _lookup(
    path: str | os.PathLike[str], table: dict[str, str], what: str, known: str
) -> tuple[str, ModuleType]:
    sfx = suffix_of(path)
    name = table.get(sfx)
    if name is None:
        raise UnsupportedFormatError(
            f"{path}: {what} suffix {sfx or '(none)'!r}; {known}: {' '.join(sorted(table))}"
        )
    return name.rsplit(".", 1)[-1], _module(name)


def reader_for(path: str | os.PathLike[str]) -> tuple[str, ModuleType]:
    """(format name, module) that reads ``path``, or UnsupportedFormatError."""
    return _lookup(path, READERS, "no reader for", "known suffixes")


def writer_for(path: str | os.PathLike[str]) -> tuple[str, ModuleType]:
    """(format name, module) that writes ``path``, or UnsupportedFormatError (or the error of
    the module's ``check_output``, e.g. MissingDependencyError).

    A ``.copc.laz`` name is refused: a COPC file is an octree of levels that only
    ``lodbuilder export`` (:func:`lodbuilder.export.copc.export_copc`) writes; the LAS writer
    would put a plain LAZ under that name."""
    if Path(path).name.lower().endswith(".copc.laz"):
        raise UnsupportedFormatError(
            f"{path}: cannot write a COPC file (only plain LAS/LAZ); use lodbuilder export ARCHIVE "
            f"-o {path} (in Python: lodbuilder.export.copc.export_copc)"
        )
    fmt, module = _lookup(path, WRITERS, "cannot write", "known output suffixes")
    check = getattr(module, "check_output", None)
    if check is not None:
        check(Path(path))
    return fmt, module
