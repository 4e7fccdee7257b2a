"""Turn the library's progress callback into tqdm progress bars (on stderr, only on a terminal
unless forced)."""

from __future__ import annotations

import sys
from typing import Any

NOTES = ("compiling kernels, first run only",)  # stages worth a line even without a terminal


class ProgressBars:
    """A ``progress(stage, done, total)`` callable that shows one bar per stage. Without a terminal
    (and unless disabled on purpose) the stages in NOTES are still printed once, as a line."""

    def __init__(self, enabled: bool | None = None) -> None:
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._notes = enabled is None
        self._noted: set[str] = set()
        self._bar: Any = None
        self._stage: str | None = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not self.enabled:
            if self._notes and stage in NOTES and stage not in self._noted:
                self._noted.add(stage)
                print(f"{stage} ...", file=sys.stderr, flush=True)
            return
        from tqdm import tqdm

        if stage != self._stage:
            self.close()
            self._stage = stage
            self._bar = tqdm(total=total, desc=stage, unit="pt", leave=False, file=sys.stderr)
        bar = self._bar
        if bar.total != total:
            bar.total = total
        bar.update(done - bar.n)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
            self._stage = None

    def __enter__(self) -> ProgressBars:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
