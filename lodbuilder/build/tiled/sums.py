"""Checksums of a tiled build's work files, so that a resumed build never trusts a damaged one.

Every raw work file is written with its size and CRC-32, computed from the bytes as they are
written (:meth:`.store.Store.writer`, :meth:`.store.Store.put`; :func:`publish`
for a local path); the marker (a small JSON file) that records a finished
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
import zlib
from pathlib import Path
from typing import Any, cast

import numpy as np

from . import layout as WL
from .store import LocalStore, Store, as_store

log = logging.getLogger(__name__)

CHUNK = 1 << 23  # bytes per read when a file is checked


def sum_array(arr: np.ndarray) -> list[int]:
    """Size and CRC-32 of ``arr`` as :meth:`numpy.ndarray.tofile` writes it."""
    a = np.ascontiguousarray(arr)
    return [int(a.nbytes), zlib.crc32(cast(Any, a))]


def sum_file(path: Path) -> list[int]:
    """Size and CRC-32 of the file at ``path`` (read in chunks)."""
    return LocalStore(Path(path).parent).sum(Path(path).name, CHUNK)


def publish(arr: np.ndarray, path: Path) -> list[int]:
    """Replace the file at ``path`` by the raw bytes of ``arr``, atomically
    (:func:`lodbuilder._atomic.publish`); returns their size and CRC-32."""
    return LocalStore(Path(path).parent).put(Path(path).name, arr)


def check_sums(work: Store | Path | str, files: dict[str, Any], skip: tuple[str, ...] = ()) -> str | None:
    """What is wrong with the first file of ``files`` (name -> [size, crc]) in the store ``work``
    that does not match, or None when all do (names in ``skip`` are not checked)."""
    store = as_store(work)
    for name, want in files.items():
        if name in skip:
            continue
        if "/" in name or name.startswith("."):
            return f"it lists a file {name!r} outside the work directory"
        have = store.size(name)
        if have is None:
            if isinstance(store, LocalStore) and os.path.lexists(store.path(name)):
                return f"{name} is not a regular file"
            if consumed(store, name):  # (deleted once read: see layout.PRUNE_AFTER)
                continue
            return f"{name} is missing"
        size, crc = int(want[0]), int(want[1])
        if have != size:
            return f"{name} has {have} bytes, {size} were written"
        if store.sum(name, CHUNK)[1] != crc:
            return f"{name} does not match its checksum"
    return None


_SEALED = re.compile(r'(\{.*?)(, )?"_crc32": "([0-9a-f]{8})"\}', re.S)


def sealed(doc: dict[str, Any]) -> bytes:
    """A marker's text: a JSON object (the one convention of :mod:`lodbuilder._json`) whose last
    member ``_crc32`` is the CRC-32 of the object's text without it."""
    from ..._json import fast_dumps

    body = fast_dumps(doc)
    tail = f'"_crc32": "{zlib.crc32(body.encode()):08x}"}}'
    return (body[:-1] + (", " if doc else "") + tail).encode()


def unseal(text: str) -> dict[str, Any] | None:
    """The marker whose text is ``text`` (without its ``_crc32``), None when it is damaged."""
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


def put_json(work: Store | Path | str, name: str, doc: dict[str, Any]) -> list[int]:
    """Write the marker object ``name`` of the store ``work`` whole (see :func:`sealed`); returns
    its size and CRC-32."""
    store = as_store(work)
    store.verified.discard(name)
    return store.put(name, sealed(doc))


def get_json(work: Store | Path | str, name: str) -> dict[str, Any] | None:
    """The marker object ``name`` (without its ``_crc32``), None when it is missing or damaged."""
    try:
        text = as_store(work).get(name).decode("utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    return unseal(text)


def write_json(path: Path, doc: dict[str, Any]) -> None:
    """Write the marker file ``path`` atomically (see :func:`sealed`)."""
    put_json(LocalStore(Path(path).parent), Path(path).name, doc)


def read_json(path: Path) -> dict[str, Any] | None:
    """The marker file at ``path`` (without its ``_crc32``), or None when it is missing or damaged."""
    return get_json(LocalStore(Path(path).parent), Path(path).name)


def mark(work: Store | Path | str, piece: str, doc: dict[str, Any]) -> dict[str, Any]:
    """Write the marker of a finished phase or task ``piece`` (its files listed in ``doc``), then
    pass the named moment of its kind (the piece's name up to the first dot: :func:`layout.moment`);
    returns ``doc``."""
    put_json(work, WL.marker(piece), doc)
    for prefix in WL.PRUNE_AFTER.get(piece, ()):  # (the files of the prefix that this piece reads last)
        prune(work, [n for n in as_store(work).names(prefix) if piece in (WL.consumers(n) or ())])
    WL.moment(piece.split(".")[0])
    return doc


def prune(work: Store | Path | str, names: list[str]) -> None:
    """Delete work files that every piece reading them has read (see :mod:`.layout`)."""
    as_store(work).delete_many(names)  # (in bulk on an object store)


def consumed(store: Store, name: str) -> bool:
    """True when the work file ``name`` may be missing: every piece that reads it is done
    (:func:`lodbuilder.build.tiled.layout.consumers`; each checked once per build)."""
    pieces = WL.consumers(name)
    if pieces is None:
        return False
    for piece in pieces:
        if piece == WL.EVERY_COVER:
            plan = get_json(store, WL.marker("plan"))
            if plan is None or not all(_verified(store, WL.cover_piece(t)) for t in range(len(plan["tiles"]))):
                return False
        elif piece.endswith(".*"):  # (every ordering pass of a tile: an earlier pass's stream was replaced)
            found = sorted((n[: -len(".json")] for n in store.names(piece[:-1]) if n.endswith(".json")),
                           key=lambda x: int(x.split(".")[-1]))
            stream = (WL.stream(int(piece.split(".")[1])), WL.seam(int(piece.split(".")[1])))
            if not found or not all(_verified(store, p, stream if p != found[-1] else ()) for p in found):
                return False
        elif not _verified(store, piece):
            return False
    return True


def _verified(store: Store, piece: str, skip: tuple[str, ...] = ()) -> bool:
    """:func:`done` of ``piece``, remembered by the store for the rest of the build."""
    if WL.marker(piece) in store.verified:
        return True
    ok = done(store, piece, skip) is not None
    if ok:
        store.verified.add(WL.marker(piece))
    return ok


def done(work: Store | Path | str, name: str, skip: tuple[str, ...] = ()) -> dict[str, Any] | None:
    """The marker ``<name>.json`` of a finished phase or task when it and every file it lists
    check out; else None, and a marker that is there but fails is deleted (the piece is redone)."""
    store = as_store(work)
    marker = WL.marker(name)
    raw = store.marker(marker)
    if raw is None:
        return None
    try:
        doc = unseal(raw.decode("utf-8"))
    except UnicodeDecodeError:
        doc = None
    problem = "its record is damaged" if doc is None else check_sums(store, doc.get("files") or {}, skip)
    if problem is None:
        return doc
    log.warning("tiled build in %s: %s (%s); doing it again", store.url, _piece(name), problem)
    store.verified.discard(marker)
    store.delete(marker)
    return None


def _piece(name: str) -> str:
    parts = name.split(".")
    if parts[0] == "order" and len(parts) == 3:
        return f"the ordering of tile {int(parts[1]) + 1} (pass {parts[2]})"
    if parts[0] == "cover" and len(parts) == 2:
        return f"the covering radii of tile {int(parts[1]) + 1}"
    return f"the {name} phase"
