"""Running a phase's tasks on the executor: submit, wait, and fail the scan naming the task."""

from __future__ import annotations

import concurrent.futures as cf
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from ...errors import BuildError, LodbuilderError
from ...progress import ProgressCallback, TaskCounts, report, report_tasks
from .timing import failure_note


def submit(ex: cf.Executor, calls: list[tuple[int, Any, tuple]]) -> dict[cf.Future, int]:
    """``calls``: (task id, function, arguments); returns future -> task id."""
    return {ex.submit(fn, *args): t for t, fn, args in calls}


def result(fut: cf.Future, name: str, where: str) -> Any:
    """A finished task's result; its failure fails the scan, naming the task."""
    try:
        return fut.result()
    except BuildError:
        raise  # a task's own failure of the scan (it names the scan and the fix)
    except LodbuilderError as exc:
        raise BuildError(f"scan {name!r}: {where} failed: {exc}") from exc  # (names the input and its fix)
    except BrokenProcessPool:
        raise BuildError(f"scan {name!r}: {where} failed: its worker process "
                         "died (killed or out of memory: lower --max-memory per worker or use fewer "
                         "workers)") from None
    except Exception as exc:
        text = " ".join(str(exc).split())
        raise BuildError(f"scan {name!r}: {where} failed: {type(exc).__name__}: {text}{failure_note(exc, where)}") from exc


def collect(futs: dict[cf.Future, int], where: Any, name: str, n_total: int, progress: ProgressCallback,
            stage: str, on_result: Any = None, count: Any = None, start: int | None = None,
            points: list[int] | None = None) -> list[dict[str, Any]]:
    """Wait for submitted tasks; a failure fails the scan, naming the task (``where(task id)``).
    ``on_result(result)`` is called as each task finishes (to record it for a resume); progress
    counts tasks (those not submitted are done), or ``count(result)`` units per task from ``start``,
    or with ``points`` (the points of each of the ``n_total`` tasks, by task id) tasks and points
    (:func:`lodbuilder.progress.report_tasks`)."""
    done = n_total - len(futs) if start is None else start
    left = sum(points[t] for t in futs.values()) if points is not None else 0

    def tell() -> None:
        if points is None:
            report(progress, stage, done, n_total)
        else:
            report_tasks(progress, stage, TaskCounts(done, n_total, sum(points) - left, sum(points), n_total - done))

    tell()
    out = []
    try:
        for fut in cf.as_completed(futs):
            out.append(result(fut, name, where(futs[fut])))
            if on_result is not None:
                on_result(out[-1])
            done += 1 if count is None else count(out[-1])
            left -= points[futs[fut]] if points is not None else 0
            tell()
    except BaseException:
        for f in futs:
            f.cancel()
        raise
    return out


def bottom_levels(deps: dict[Any, list[Any]], cost: dict[Any, float]) -> dict[Any, float]:
    """Each task's bottom level: its ``cost`` plus the largest bottom level of the tasks that wait
    for it (``deps``: task -> the tasks it waits for; those not in ``deps`` count as done). On
    enough workers a task cannot finish the phase sooner than its bottom level after it starts, so
    a scheduler that starts the ready task of the largest one first follows the critical path
    (list scheduling by bottom level, which is the largest first among independent tasks)."""
    users: dict[Any, list[Any]] = {}
    for t, ds in deps.items():
        for d in ds:
            if d in deps:
                users.setdefault(d, []).append(t)
    level: dict[Any, float] = {}
    opened: set[Any] = set()
    for t in deps:  # (depth first, iterative: every user's level before its task's)
        stack = [(t, False)]
        while stack:
            x, expanded = stack.pop()
            if expanded:
                level[x] = cost[x] + max((level[u] for u in users.get(x, [])), default=0.0)
            elif x not in level:
                if x in opened:
                    raise ValueError("the task dependencies have a cycle")
                opened.add(x)
                stack.append((x, True))
                stack.extend((u, False) for u in users.get(x, []) if u not in level)
    return level
