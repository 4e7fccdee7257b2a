"""What a tiled build's tasks tell about themselves: where the time goes (every task's wall and CPU
seconds and worker, and the parent's CPU seconds per phase: the build record's ``tasks`` and
``phase_cpu_seconds``), and which worker failed on which tile of which source files.

A task function decorated with :func:`timed_task` adds ``timing`` to the dict it returns: its kind
(the function's name), when it started (seconds since the epoch), its wall and CPU seconds (CPU of
the worker process while it ran, every thread counted) and the worker's pid. The driver keeps each
finished task's result as its marker (``<piece>.json``), so :func:`task_table` gathers them from the
work directory, whatever the task kinds and however the build was resumed: tools/simulate_schedule.py
replays them on any number of workers, tools/bench_survey.py reports them.

A decorated task that fails leaves ``lodbuilder_task`` on its exception (kind, worker pid, seconds,
and for a task of one tile, its parameter ``t``, the tile and the names of the source files its
points came from); :func:`failure_where` puts them in the build's error message.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

#: the columns of the build record's task table (``start``: seconds after the build started,
#: negative for a task a resumed build found done)
TASK_COLUMNS = ("kind", "piece", "tile", "start", "seconds", "cpu_seconds", "pid")


def timed_task(fn: F) -> F:
    """Decorate a task that returns a dict: the dict gains ``timing`` (see the module); a failure
    leaves ``lodbuilder_task`` on the exception."""
    params = list(inspect.signature(fn).parameters)
    tile_at = params.index("t") if "t" in params else None

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        start, t0, c0 = time.time(), time.perf_counter(), time.process_time()
        try:
            res = fn(*args, **kwargs)
        except Exception as exc:
            info: dict[str, Any] = {"kind": fn.__name__, "pid": os.getpid(), "seconds": time.perf_counter() - t0}
            tile = kwargs.get("t", args[tile_at] if tile_at is not None and len(args) > tile_at else None)
            if isinstance(tile, int) and args:
                info.update(tile=tile, files=tile_files(Path(args[0]), tile))
            with contextlib.suppress(Exception):  # (an exception that takes no attributes)
                exc.lodbuilder_task = info  # type: ignore[attr-defined]
            raise
        if isinstance(res, dict):
            res["timing"] = {"kind": fn.__name__, "start": start, "seconds": time.perf_counter() - t0,
                             "cpu_seconds": time.process_time() - c0, "pid": os.getpid()}
        return res

    return run  # type: ignore[return-value]


def tile_files(work: Path, t: int) -> list[str] | None:
    """The names of the source files that tile ``t``'s points came from (from the read phase's
    members and the tile's core file); None where that is not known."""
    import numpy as np

    from . import layout as WL

    with contextlib.suppress(Exception):
        members = json.loads((work / WL.marker("spill")).read_text()).get("members") or []
        if not members or any(not m.get("source") for m in members):
            return None
        if len(members) == 1:
            return [members[0]["source"]]
        g = np.memmap(work / WL.core(t), dtype=WL.REC, mode="r")["g"]
        first = np.asarray([m["first"] for m in members], np.int64)
        return [members[i]["source"] for i in np.unique(np.searchsorted(first, g, side="right") - 1).tolist()]
    return None


#: at most this many file names in a message (then "and N more")
FILES_NAMED = 4


def failure_where(where: str, exc: BaseException) -> str:
    """``where`` (the failed task, as the build names it: "ordering of tile 3 of 16") followed by
    what the task said of itself: its tile's source files and the worker's pid."""
    info = getattr(exc, "lodbuilder_task", None)
    if not isinstance(info, dict):
        return where
    parts = []
    files = info.get("files") or []
    if files:
        more = f" and {len(files) - FILES_NAMED} more" if len(files) > FILES_NAMED else ""
        parts.append(f"{'file' if len(files) == 1 else 'files'} {', '.join(files[:FILES_NAMED])}{more}")
    parts.append(f"worker {info.get('pid')}")
    return f"{where} ({'; '.join(parts)})"


def task_table(work: Path, started: float) -> dict[str, Any]:
    """The build record's table of the tasks whose markers are in ``work`` (one row per task, in
    order of start; ``started``: the build's start, seconds since the epoch)."""
    rows = []
    for f in sorted(work.glob("*.json")):
        try:
            doc = json.loads(f.read_text())
        except (OSError, ValueError):
            continue
        tm = doc.get("timing") if isinstance(doc, dict) else None
        if not isinstance(tm, dict):
            continue
        tile = doc.get("tile")
        rows.append([tm["kind"], f.name[: -len(".json")], tile if isinstance(tile, int) else None,
                     round(float(tm["start"]) - started, 3), round(float(tm["seconds"]), 4),
                     round(float(tm["cpu_seconds"]), 4), int(tm["pid"])])
    rows.sort(key=lambda r: (r[3], r[1]))
    return {"columns": list(TASK_COLUMNS), "rows": rows}


def parent_cpu() -> float:
    """CPU seconds of this process so far (every thread)."""
    return time.process_time()
