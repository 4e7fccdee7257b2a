"""Checksums of a tiled build's work files, so that a resumed build never trusts a damaged one.

Every raw work file is written with its size and CRC-32, computed from the bytes as they are
written (:class:`SumFile`, :func:`publish`); the marker (a small JSON file) that records a finished
phase or tile task lists them under ``"files"``, and carries a CRC-32 of its own text on its last
line. On a resume, :func:`done` trusts a marker only when its text and every file it lists check
out; otherwise the marker is deleted and that phase or task is done again (each one is
deterministic, so what is rebuilt is the same bytes an uninterrupted build writes).

CRC-32 (zlib) runs at several GB/s; it finds every flipped bit in a block, and truncation or
zeroing changes the size or the sum. It is no defence against a forger (who can rewrite a marker
too): ``--force`` starts the scan's work afresh.
"""

from __future__ import annotations

import json
import logging
import os
import re
import stat
import zlib
from pathlib import Path
from typing import Any, cast

import numpy as np

from . import layout as WL

log = logging.getLogger(__name__)

CHUNK = 1 << 23  # bytes per read when a file is checked


def _nbytes(data: Any) -> int:
    return int(data.nbytes) if isinstance(data, np.ndarray) else memoryview(data).nbytes


class SumFile:
    """A work file opened for writing that keeps the size and CRC-32 of what is written."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._f = open(path, "wb")  # noqa: SIM115 - closed by close() / the context manager
        self.size = 0
        self.crc = 0

    def write(self, data: Any) -> None:
        if isinstance(data, np.ndarray):
            data = np.ascontiguousarray(data)
        self.crc = zlib.crc32(cast(Any, data), self.crc)
        self.size += _nbytes(data)
        self._f.write(data)

    def close(self) -> None:
        self._f.close()

    @property
    def sum(self) -> list[int]:
        return [self.size, self.crc]

    def __enter__(self) -> SumFile:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def sum_array(arr: np.ndarray) -> list[int]:
    """Size and CRC-32 of ``arr`` as :meth:`numpy.ndarray.tofile` writes it."""
    a = np.ascontiguousarray(arr)
    return [int(a.nbytes), zlib.crc32(cast(Any, a))]


def sum_file(path: Path) -> list[int]:
    """Size and CRC-32 of the file at ``path`` (read in chunks)."""
    crc = size = 0
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            crc = zlib.crc32(chunk, crc)
            size += len(chunk)
    return [size, crc]


def publish(arr: np.ndarray, path: Path) -> list[int]:
    """Replace the file at ``path`` by the raw bytes of ``arr``, atomically
    (:func:`lodbuilder._atomic.publish`); returns their size and CRC-32."""
    from ..._atomic import replace_with

    sums: list[list[int]] = []

    def write(tmp: Path) -> None:
        with SumFile(tmp) as f:
            f.write(arr)
        sums.append(f.sum)

    replace_with(path, write)
    return sums[0]


def check_sums(work: Path, files: dict[str, Any], skip: tuple[str, ...] = ()) -> str | None:
    """What is wrong with the first file of ``files`` (name -> [size, crc]) in ``work`` that does
    not match, or None when all do (names in ``skip`` are not checked)."""
    for name, want in files.items():
        if name in skip:
            continue
        path = work / name
        if "/" in name or name.startswith("."):
            return f"it lists a file {name!r} outside the work directory"
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            return f"{name} is missing"
        if not stat.S_ISREG(st.st_mode):
            return f"{name} is not a regular file"
        size, crc = int(want[0]), int(want[1])
        if st.st_size != size:
            return f"{name} has {st.st_size} bytes, {size} were written"
        if sum_file(path)[1] != crc:
            return f"{name} does not match its checksum"
    return None


_SEALED = re.compile(r'(\{.*?)(, )?"_crc32": "([0-9a-f]{8})"\}', re.S)


def write_json(path: Path, doc: dict[str, Any]) -> None:
    """Write a marker atomically: a JSON object (the one convention of :mod:`lodbuilder._json`)
    whose last member ``_crc32`` is the CRC-32 of the object's text without it."""
    from ..._atomic import write_bytes
    from ..._json import dumps

    body = dumps(doc)
    tail = f'"_crc32": "{zlib.crc32(body.encode()):08x}"}}'
    write_bytes(path, (body[:-1] + (", " if doc else "") + tail).encode())


def read_json(path: Path) -> dict[str, Any] | None:
    """The marker at ``path`` (without its ``_crc32``), or None when it is missing or damaged."""
    try:
        text = path.read_text("utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    m = _SEALED.fullmatch(text)
    if m is None:
        return None
    body = m[1] + "}"
    if m[3] != f"{zlib.crc32(body.encode()):08x}":
        return None
    try:
        doc = json.loads(body)
    except ValueError:
        return None
    return doc if isinstance(doc, dict) else None


def mark(work: Path, piece: str, doc: dict[str, Any]) -> dict[str, Any]:
    """Write the marker of a finished phase or task ``piece`` (its files listed in ``doc``), then
    pass the named moment of its kind (the piece's name up to the first dot: :func:`layout.moment`);
    returns ``doc``."""
    write_json(work / WL.marker(piece), doc)
    WL.moment(piece.split(".")[0])
    return doc


def done(work: Path, name: str, skip: tuple[str, ...] = ()) -> dict[str, Any] | None:
    """The marker ``<name>.json`` of a finished phase or task when it and every file it lists
    check out; else None, and a marker that is there but fails is deleted (the piece is redone)."""
    path = work / WL.marker(name)
    if not path.exists():
        return None
    doc = read_json(path)
    problem = "its record is damaged" if doc is None else check_sums(work, doc.get("files") or {}, skip)
    if problem is None:
        return doc
    log.warning("tiled build in %s: %s (%s); doing it again", work, _piece(name), problem)
    path.unlink(missing_ok=True)
    return None


def _piece(name: str) -> str:
    parts = name.split(".")
    if parts[0] == "order" and len(parts) == 3:
        return f"the ordering of tile {int(parts[1]) + 1} (pass {parts[2]})"
    if parts[0] == "cover" and len(parts) == 2:
        return f"the covering radii of tile {int(parts[1]) + 1}"
    return f"the {name} phase"
