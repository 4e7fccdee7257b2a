"""One progress hook for long work.

Library functions accept ``progress``: a callable ``progress(stage, done, total)``; the CLI turns it
into a progress bar. ``None`` means silent.
"""

from __future__ import annotations

from collections.abc import Callable

ProgressCallback = Callable[[str, int, int], None] | None


def report(progress: ProgressCallback, stage: str, done: int, total: int) -> None:
    """Call ``progress`` if it is set."""
    if progress is not None:
        progress(stage, done, total)
