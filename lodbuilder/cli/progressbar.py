"""Turn the library's progress callback into tqdm progress bars (on stderr, only on a terminal
unless forced).

Stages of one scan (``read``, ``tiles``, ``band``, ``ordering``/``marching``, ``merge``,
``write``, ...) each get a bar in turn, counting points (tiles for ``tiles``, steps for a stage
reported as one step, such as the in-memory build's ``read``, ``band`` and ``write``) with their rate; the
collection stages ``scans`` and ``points`` stay on screen above them for the whole build.

A phase of tasks (:func:`lodbuilder.progress.report_tasks`: the tiles of a tiled build) is a bar of
points done over all workers, with the tasks done beside it; without a terminal (with
``stage_lines``) it is a line every ``LINE_SECONDS`` and one when it ends
(:func:`lodbuilder.progress.task_line`: points per second and the time left).
"""

from __future__ import annotations

import sys
import time
from typing import Any

from ..progress import Rate, TaskCounts, task_line

NOTES = ("compiling kernels, first run only",)  # stages worth a line even without a terminal
#: stages whose bar stays while the per-scan phases come and go
PERSISTENT = ("scans", "points")
UNITS = {"scans": "scan", "tiles": "tile", "covering": "tile", "pieces": "tile", "coarse": "task"}
#: seconds between two lines of a phase of tasks without a terminal
LINE_SECONDS = 30.0


class ProgressBars:
    """A ``progress(stage, done, total)`` callable that shows one bar per stage (``total`` 0: a
    counter with a rate and no end). Without a terminal (and unless disabled on purpose) the
    stages in NOTES are still printed once, as a line (every stage with ``stage_lines``)."""

    def __init__(self, enabled: bool | None = None, *, stage_lines: bool = False) -> None:
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._notes = enabled is None
        # without a terminal: a line as each stage starts (a joint build is one long scan, with
        # no per-scan lines to show that it moves)
        self._stage_lines = stage_lines and enabled is None
        self._noted: set[str] = set()
        self._bars: dict[str, Any] = {}
        self._stage: str | None = None
        self._rates: dict[str, Rate] = {}
        self._lined: dict[str, float] = {}  # stage -> when its last line was printed
        self.clock = time.monotonic

    @property
    def active(self) -> bool:
        return bool(self._bars)

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not self.enabled:
            wanted = stage in NOTES or (self._stage_lines and stage not in PERSISTENT)
            if self._notes and wanted and stage not in self._noted:
                self._noted.add(stage)
                print(f"{stage} ...", file=sys.stderr, flush=True)
            return
        from tqdm import tqdm

        bar = self._bars.get(stage)
        if bar is None:
            if stage not in PERSISTENT:
                self._close_phase()
                self._stage = stage
            # a stage counted in points, or one step (total 1: read a whole file, build the band)
            unit = UNITS.get(stage, "step" if total == 1 else "pt")
            bar = tqdm(total=total or None, desc=stage, unit=unit, unit_scale=unit == "pt", leave=False,
                       file=sys.stderr, position=len(self._bars), dynamic_ncols=True)
            self._bars[stage] = bar
        if total and bar.total != total:
            bar.total = total
        bar.update(done - bar.n)

    def tasks(self, stage: str, counts: TaskCounts) -> None:
        """A phase of tasks (see the module)."""
        rate = self._rates.get(stage)
        if rate is None:
            rate = self._rates[stage] = Rate(clock=self.clock)
        rate.add(counts.points_done)
        if not self.enabled:
            now, last = self.clock(), self._lined.get(stage)
            finished = counts.done >= counts.total
            if self._notes and self._stage_lines and (last is None or finished or now - last >= LINE_SECONDS):
                if last is None or last >= 0:  # (-1: the final line was printed)
                    print(task_line(stage, counts, rate), file=sys.stderr, flush=True)
                self._lined[stage] = -1.0 if finished else now
            return
        from tqdm import tqdm

        bar = self._bars.get(stage)
        if bar is None:
            self._close_phase()
            self._stage = stage
            bar = tqdm(total=counts.points_total or None, desc=stage, unit="pt", unit_scale=True, leave=False,
                       file=sys.stderr, position=len(self._bars), dynamic_ncols=True,
                       postfix=f"{counts.done}/{counts.total} {counts.unit}s")
            self._bars[stage] = bar
        unit = counts.unit if counts.total == 1 else f"{counts.unit}s"
        bar.set_postfix_str(f"{counts.done}/{counts.total} {unit}", refresh=False)
        bar.update(counts.points_done - bar.n)

    def write(self, line: str) -> None:
        """Print a line above the bars."""
        from tqdm import tqdm

        tqdm.write(line, file=sys.stderr)

    def _close_phase(self) -> None:
        if self._stage is not None and self._stage in self._bars:
            self._bars.pop(self._stage).close()
        self._stage = None

    def close(self) -> None:
        for bar in reversed(list(self._bars.values())):
            bar.close()
        self._bars.clear()
        self._stage = None

    def __enter__(self) -> ProgressBars:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
