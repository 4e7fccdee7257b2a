"""Where a tiled build's time goes: every task's wall and CPU seconds and worker, and the parent's
CPU seconds per phase (the build record's ``tasks`` and ``phase_cpu_seconds``).

A task function decorated with :func:`timed_task` adds ``timing`` to the dict it returns: its kind
(the function's name), when it started (seconds since the epoch), its wall and CPU seconds (CPU of
the worker process while it ran, every thread counted) and the worker's pid. The driver keeps each
finished task's result as its marker (``<piece>.json``), so :func:`task_table` gathers them from the
work directory, whatever the task kinds and however the build was resumed: tools/simulate_schedule.py
replays them on any number of workers, tools/bench_survey.py reports them.
"""

from __future__ import annotations

import functools
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
    """Decorate a task that returns a dict: the dict gains ``timing`` (see the module)."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        start, t0, c0 = time.time(), time.perf_counter(), time.process_time()
        res = fn(*args, **kwargs)
        if isinstance(res, dict):
            res["timing"] = {"kind": fn.__name__, "start": start, "seconds": time.perf_counter() - t0,
                             "cpu_seconds": time.process_time() - c0, "pid": os.getpid()}
        return res

    return run  # type: ignore[return-value]


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
