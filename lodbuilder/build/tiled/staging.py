"""The merge, bucket and write tasks on an object store, through a local copy (a stopgap).

Those tasks still read and write a local work directory (memory maps, a part file written in
place; they are being rewritten as banded write tasks). With a work store that is not a local
directory, :class:`Staging` wraps the executor: each such task runs on its worker in a temporary
directory (``$TMPDIR``) that first receives the objects it reads (:data:`INPUTS`), and whose files
it lists in its result (``"files"``) are uploaded whole to the store when it returns; the write
task's part file is uploaded as the object ``part.h5`` and the parent downloads it beside the
archive (:func:`fetch_part`). Other tasks (and everything on a local store) are submitted as they
are. What it costs: each task downloads its inputs (a bucket task its raw block and its range of
``rank.i8``; the merge every tile stream; the write every bucket and band), uploads its outputs
whole, and the parent downloads the part: each byte crosses the network about twice more than a
task that reads the store directly.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from . import layout as WL
from .store import LocalStore, Store

#: the object a remote write task's part file is uploaded as
PART = "part.h5"


def _merge_inputs(n: int, n_tiles: int, *_: Any) -> list[str]:
    return [WL.HEAD_FILE, *(WL.stream(t) for t in range(n_tiles))]


def _bucket_inputs(b: int, g0: int, m: int, *_: Any) -> list[Any]:
    return [WL.raw_xyz(b), WL.raw_attr(b), (WL.RANK, 8 * g0, 8 * (g0 + m))]  # (the block's ranks only)


def _write_inputs(part: str, name: str, n: int, fields: Any, metadata: Any, encoding: str, seeds: Any, build: Any,
                  provenance: Any, buckets: dict[str, Any], radii: dict[str, Any]) -> list[str]:
    pieces = [p for ps in buckets["pieces"] for p in ps]
    bands = range(len(radii["bands"]))
    return [*pieces, *(WL.radius(b) for b in bands), *(WL.parent(b) for b in bands), WL.ORDER]


#: the tasks that need a local copy, by name: the objects each reads (from its arguments after the
#: work), each a name or (name, first byte, end byte) of which the task reads that range only
INPUTS: dict[str, Callable[..., list[Any]]] = {
    "merge_task": _merge_inputs, "bucket_block": _bucket_inputs, "write_task": _write_inputs,
}


def run_staged(fn: Callable[..., Any], store: Store, *args: Any) -> Any:
    """Run the task ``fn(work, *args)`` in a temporary directory holding its inputs from
    ``store``; upload the files its result lists (and a write task's part, as :data:`PART`)."""
    with tempfile.TemporaryDirectory(prefix="lodbuilder-work-") as tmp:
        d = Path(tmp)
        for item in INPUTS[fn.__name__](*args):
            _download(store, item, d)
        if fn.__name__ == "write_task":
            args = (str(d / PART), *args[1:])
        res = fn(str(d), *args)
        for name in (res.get("files") or {}) if isinstance(res, dict) else {}:
            _upload(store, d / name, name)
        if fn.__name__ == "write_task":
            _upload(store, d / PART, PART)
        for log in d.glob(WL.task_log("*")):  # the task table's rows
            for line in log.read_text().splitlines():
                store.log(log.name, line)
    return res


def _download(store: Store, item: Any, d: Path) -> None:
    """An input of a staged task into the directory ``d`` (a range: at its offset, the rest a hole)."""
    name, start, end = (item, -1, -1) if isinstance(item, str) else item
    if store.size(name) is None:  # (a scan without attributes has no raw.<b>.attr)
        return
    with open(d / name, "wb") as dst:
        if start >= 0:
            dst.seek(start)
            dst.write(store.read_ranges(name, [start], [end])[0])
            return
        with store.open(name) as src:
            while chunk := src.read(1 << 23):
                dst.write(chunk)


def _upload(store: Store, path: Path, name: str) -> None:
    with store.writer(name) as w, open(path, "rb") as f:
        while chunk := f.read(1 << 23):
            w.write(chunk)


def fetch_part(store: Store, info: Any, part: Path) -> Any:
    """Download the part a remote write task uploaded to ``part`` (a temporary renamed into
    place); returns its PartInfo with that path."""
    from ..._atomic import replace_with

    def write(tmp: Path) -> None:
        with store.open(PART) as src, open(tmp, "wb") as dst:
            while chunk := src.read(1 << 23):
                dst.write(chunk)

    replace_with(part, write)
    with contextlib.suppress(OSError):
        store.delete(PART)
    return dataclasses.replace(info, path=part)


class Staging(cf.Executor):
    """``executor`` with the tasks of :data:`INPUTS` run through :func:`run_staged` when the store
    is not a local directory (on a local store: the executor itself, each task given the directory)."""

    def __init__(self, executor: cf.Executor, store: Store) -> None:
        self.executor, self.store = executor, store

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> cf.Future:
        if getattr(fn, "__name__", None) not in INPUTS or not args or not isinstance(args[0], Store):
            return self.executor.submit(fn, *args, **kwargs)
        if isinstance(self.store, LocalStore):
            return self.executor.submit(fn, os.fspath(self.store.root), *args[1:], **kwargs)
        return self.executor.submit(run_staged, fn, self.store, *args[1:], **kwargs)
