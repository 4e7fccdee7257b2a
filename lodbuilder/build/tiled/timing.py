"""What a tiled build's tasks tell about themselves: where the time goes (every task's wall and CPU
seconds and worker: the build record's ``tasks``, beside the parent's ``parent_cpu_seconds`` per
phase), and which worker failed on which tile or block of which source files.

A task function decorated with :func:`timed_task` (its first parameter the work directory, and
``t`` a tile or ``b`` a read block if it works on one) adds ``timing`` to the dict it returns (its
kind, the function's name; when it started, seconds since the epoch; its wall and CPU seconds, CPU
of the worker process while it ran, every thread counted; the worker's pid; ``peak_rss``, the
worker process's peak resident bytes while the task ran, its own footprint included: on Linux the
peak is reset when the task starts, /proc/self/clear_refs, and read from VmHWM when it ends; None
elsewhere; a Dask worker running tasks in threads counts its other tasks too) and appends the same
as one line to the worker's log in the work store (``tasks.<pid>.jsonl``; one object per line on
an object store:
:func:`lodbuilder.build.tiled.layout.task_log`), so :func:`task_table` finds every task, whatever
its kind and whether or not its result is kept as a marker. tools/simulate_schedule.py replays the
table on any number of workers; tools/bench_survey.py reports it.

When a task whose process grew by :data:`TRIM_GROWTH` ends, the worker gives the heap memory it
freed back to the system (glibc keeps it otherwise: a worker that ran a large task would hold that
task's peak while it runs small ones, or waits, beside the other workers' tasks). After a smaller
task it keeps it: the next task reuses it instead of faulting the pages in again.

A decorated task that fails leaves ``lodbuilder_task`` on its exception (kind, worker pid, seconds,
its tile or block, and the names of the source files its points came from);
:func:`failure_note` ends the build's error message with them.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import json
import os
import time
from collections.abc import Callable
from typing import Any, TypeVar

from ..._resources import release_freed_memory

F = TypeVar("F", bound=Callable[..., Any])

#: the columns of the build record's task table (``start``: seconds after the build started,
#: negative for a task of an earlier, interrupted run; ``tile``/``block``: the task's, or None)
TASK_COLUMNS = ("kind", "piece", "tile", "block", "start", "seconds", "cpu_seconds", "pid", "peak_rss")
#: Linux: writing this to /proc/self/clear_refs resets the process's peak resident size (VmHWM)
RESET_PEAK = "5"


#: a task trims the heap after it (gives freed memory back to the system) only where its peak
#: resident size rose at least this much above its start: the 21.56M survey's 1,600 tasks in 197
#: tiles each rose less than 150 MB, and a trim after each returned 30-60 MB for 1.5-3 ms that the
#: next task faulted in again (its tasks but the orderings: 98.1 / 101.5 CPU-s with a trim after
#: every task, 90.1 / 93.0 without; peak RSS of the tree 0.85 -> 0.90 GB on 2 workers)
TRIM_GROWTH = 256 << 20


def resident_bytes() -> int | None:
    """This process's resident size in bytes (Linux: /proc/self/statm), None where not known."""
    with contextlib.suppress(OSError, ValueError, IndexError), open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    return None


def reset_peak_rss() -> None:
    """Reset this process's peak resident size to its current size (Linux; nothing elsewhere)."""
    with contextlib.suppress(OSError):
        with open("/proc/self/clear_refs", "w") as f:
            f.write(RESET_PEAK)


def peak_rss() -> int | None:
    """This process's peak resident size in bytes since the last :func:`reset_peak_rss` (VmHWM
    of /proc/self/status), None where that is not known."""
    with contextlib.suppress(OSError, ValueError, IndexError), open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    return None


def timed_task(fn: F) -> F:
    """Decorate a task that returns a dict (see the module)."""
    return _timed(fn, True)


def timed_step(fn: F) -> F:
    """:func:`timed_task` without giving the freed memory back to the system after the task: for
    the steps of the radius rounds (:mod:`.rounds`), whose process keeps its tile states and runs
    the next round at once (a trim per step walks the heap, and the next step faults the pages
    in again)."""
    return _timed(fn, False)


def _timed(fn: F, trim: bool) -> F:
    params = list(inspect.signature(fn).parameters)
    at = {k: params.index(k) for k in ("t", "b") if k in params}

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        reset_peak_rss()
        rss0 = resident_bytes()
        start, t0, c0 = time.time(), time.perf_counter(), time.process_time()
        ids = {k: kwargs.get(k, args[i] if i < len(args) else None) for k, i in at.items()}
        try:
            res = fn(*args, **kwargs)
        except Exception as exc:
            release_freed_memory()
            info: dict[str, Any] = {"kind": fn.__name__, "pid": os.getpid(), "seconds": time.perf_counter() - t0}
            t, b = ids.get("t"), ids.get("b")
            if args and isinstance(t, int):
                info.update(tile=t, files=tile_files(args[0], t))
            elif args and isinstance(b, int):
                info.update(block=b, files=block_files(args[0], b))
            with contextlib.suppress(Exception):  # (an exception that takes no attributes)
                exc.lodbuilder_task = info  # type: ignore[attr-defined]
            raise
        peak = peak_rss()
        timing = {"kind": fn.__name__, "start": start, "seconds": time.perf_counter() - t0,
                  "cpu_seconds": time.process_time() - c0, "pid": os.getpid(), "peak_rss": peak}
        if trim and _grew(rss0, peak):
            release_freed_memory()  # (the worker waits for its next task at its own size)
        if isinstance(res, dict):
            res["timing"] = timing
        if args:
            _log(args[0], {**timing, "tile": ids.get("t"), "block": ids.get("b")})
        return res

    return run  # type: ignore[return-value]


def _grew(rss0: int | None, peak: int | None) -> bool:
    """Whether a task whose process had ``rss0`` resident at its start and peaked at ``peak``
    grew by :data:`TRIM_GROWTH` (unknown sizes: yes)."""
    return rss0 is None or peak is None or peak - rss0 >= TRIM_GROWTH


def _log(work: Any, row: dict[str, Any]) -> None:
    from . import layout as WL
    from .store import as_store

    with contextlib.suppress(OSError):
        as_store(work).log(WL.task_log(os.getpid()), json.dumps(row))


def task_table(work: Any, started: float) -> dict[str, Any]:
    """The build record's table of every task the workers' logs in ``work`` hold, in order of
    start (``started``: the build's start, seconds since the epoch). A row's piece names the task
    (``<kind>.<tile or block>``; a task run again gets ``#2``, ...); a tile's orderings are its passes
    in order of start (``order.<t>.<p>``, as the driver names them)."""
    from . import layout as WL
    from .store import as_store

    rows = []
    for line in as_store(work).log_lines(WL.task_log("")[: -len(".jsonl")]):
        with contextlib.suppress(ValueError, KeyError, TypeError):
            r = json.loads(line)
            rows.append([r["kind"], None, r.get("tile"), r.get("block"), round(float(r["start"]) - started, 3),
                         round(float(r["seconds"]), 4), round(float(r["cpu_seconds"]), 4), int(r["pid"]),
                         None if r.get("peak_rss") is None else int(r["peak_rss"])])
    rows.sort(key=lambda r: (r[4], r[0], r[2] if r[2] is not None else -1, r[3] if r[3] is not None else -1))
    passes: dict[int, int] = {}
    seen: dict[str, int] = {}
    for r in rows:
        if r[0] == "order_tile" and r[2] is not None:
            passes[r[2]] = passes.get(r[2], 0) + 1
            r[1] = WL.order_piece(r[2], passes[r[2]])
        else:
            r[1] = ".".join([r[0], *(str(x) for x in (r[2], r[3]) if x is not None)])
        seen[r[1]] = seen.get(r[1], 0) + 1
        if seen[r[1]] > 1:  # the same task again (a plan's second pass over the blocks)
            r[1] = f"{r[1]}#{seen[r[1]]}"
    return {"columns": list(TASK_COLUMNS), "rows": rows}


def _marker(work: Any, piece: str) -> dict[str, Any]:
    from . import layout as WL
    from .sums import get_json

    doc = get_json(work, WL.marker(piece))
    if doc is None:
        raise FileNotFoundError(piece)
    return doc


def _spill_members(work: Any) -> list[dict[str, Any]] | None:
    members = _marker(work, "spill").get("members") or []
    return None if not members or any(not m.get("source") for m in members) else members


def tile_files(work: Any, t: int) -> list[str] | None:
    """The names of the source files that tile ``t``'s points came from (the read blocks of its
    core pieces); None where that is not known."""
    from . import layout as WL

    with contextlib.suppress(Exception):
        members = _spill_members(work)
        if members is None:
            return None
        blocks = _marker(work, "spill")["blocks"]
        mine = set(_marker(work, "distribute")["pieces"]["core"][t])
        inputs = sorted({int(blocks[b][0]) for b in range(len(blocks)) if WL.core(t, b) in mine})
        return [members[i]["source"] for i in inputs]
    return None


def block_files(work: Any, b: int) -> list[str] | None:
    """The name of the source file read block ``b`` came from; None where that is not known."""
    with contextlib.suppress(Exception):
        members = _spill_members(work)
        if members is None:
            return None
        doc = _marker(work, "spill")
        return [members[int(doc["blocks"][b][0])]["source"]]
    return None


#: at most this many file names in a message (then "and N more")
FILES_NAMED = 4


def failure_note(exc: BaseException, where: str = "") -> str:
    """What a failed task said of itself, to end the build's error message for an unexpected
    failure (a lodbuilder error names its input and its fix already): `` (files A, B; worker
    PID)``, its tile's or block's source files (those ``where`` does not name already) and its
    worker's pid; empty for an exception no task marked."""
    info = getattr(exc, "lodbuilder_task", None)
    if not isinstance(info, dict):
        return ""
    parts = []
    files = [f for f in info.get("files") or [] if f not in where]  # ("reading FILE" names it already)
    if files:
        more = f" and {len(files) - FILES_NAMED} more" if len(files) > FILES_NAMED else ""
        parts.append(f"{'file' if len(files) == 1 else 'files'} {', '.join(files[:FILES_NAMED])}{more}")
    parts.append(f"worker {info.get('pid')}")
    return f" ({'; '.join(parts)})"
