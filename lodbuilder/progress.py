"""One progress hook for long work.

Library functions accept ``progress``: a callable ``progress(stage, done, total)``; the CLI turns it
into a progress bar. ``None`` means silent.

A phase that runs tasks on workers (the tiles of a tiled build) reports :class:`TaskCounts` with
:func:`report_tasks`: tasks done and points done, summed over the workers. A ``progress`` that has a
``tasks(stage, counts)`` method receives them whole (the CLI shows points per second and an estimate
of the time left); any other callable gets ``progress(stage, tasks_done, tasks_total)`` as before.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

ProgressCallback = Callable[[str, int, int], None] | None


def report(progress: ProgressCallback, stage: str, done: int, total: int) -> None:
    """Call ``progress`` if it is set."""
    if progress is not None:
        progress(stage, done, total)


class TaskCounts(NamedTuple):
    """How far a phase of tasks is: tasks and their points, done and in all (points of finished
    tasks only: a running task counts when it finishes), and how many tasks are submitted and not
    finished (queued on the executor or running)."""

    done: int
    total: int
    points_done: int
    points_total: int
    running: int = 0
    unit: str = "tile"


def report_tasks(progress: ProgressCallback, stage: str, counts: TaskCounts) -> None:
    """Report a phase of tasks (see the module): ``progress.tasks(stage, counts)`` when it has it,
    else ``progress(stage, counts.done, counts.total)``."""
    if progress is None:
        return
    tasks = getattr(progress, "tasks", None)
    if callable(tasks):
        tasks(stage, counts)
    else:
        progress(stage, counts.done, counts.total)


class Rate:
    """Points per second of one phase and the time it has left, from the points done so far.

    The rate is taken over the last ``window`` seconds (at least two reports apart), so that a
    phase whose first tasks are slower (compiling, reading cold files) or faster (largest tasks
    first: the last ones are small) is estimated from how it goes now."""

    def __init__(self, window: float = 60.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.window, self.clock = window, clock
        self.start = clock()
        self.samples: list[tuple[float, int]] = [(self.start, 0)]

    def add(self, points_done: int) -> None:
        now = self.clock()
        self.samples.append((now, points_done))
        while len(self.samples) > 2 and now - self.samples[1][0] >= self.window:
            self.samples.pop(0)

    def per_second(self) -> float | None:
        """Points per second over the window (None before any point is done)."""
        (t0, p0), (t1, p1) = self.samples[0], self.samples[-1]
        return (p1 - p0) / (t1 - t0) if t1 > t0 and p1 > p0 else None

    def seconds_left(self, points_total: int) -> float | None:
        r = self.per_second()
        return None if r is None else max(0, points_total - self.samples[-1][1]) / r

    def elapsed(self) -> float:
        return self.samples[-1][0] - self.start


def _points(n: float) -> str:
    return f"{n / 1e6:.2f} M" if n >= 1e5 else f"{n:,.0f}"


def _duration(s: float) -> str:
    s = int(round(s))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def task_line(stage: str, counts: TaskCounts, rate: Rate) -> str:
    """One line of a phase of tasks, for logs and non-terminal output: tasks and points done, the
    points per second summed over the workers, and the time left (or the time taken when done)."""
    c = counts
    unit = c.unit if c.total == 1 else f"{c.unit}s"
    head = f"{stage}: {c.done} of {c.total} {unit}, {_points(c.points_done)} of {_points(c.points_total)} points"
    r = rate.per_second()
    if c.done >= c.total:
        speed = f" ({_points(c.points_total / rate.elapsed())} points/s)" if rate.elapsed() > 0 else ""
        return f"{head} in {_duration(rate.elapsed())}{speed}"
    running = f", {c.running} queued or running" if c.running else ""
    if r is None:
        return f"{head}{running}"
    left = rate.seconds_left(c.points_total)
    return f"{head}{running}, {_points(r)} points/s, about {_duration(left or 0.0)} left"
