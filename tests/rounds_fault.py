"""A rounds step that fails for one tile, for tests/test_rounds_parallel.py. Its own module, importing
lodbuilder only: the workers unpickle it by reference, and a worker's import path may find another
module first for the test modules' own imports (tools/surfaces.py before tests/surfaces.py)."""

from __future__ import annotations

from lodbuilder.build.tiled import rounds

STEP = rounds.round_step  # (the real step, kept before a test replaces it)


def failing_step(work, t, *a, **k):
    """A step that fails for tile 3."""
    if t == 3:
        raise RuntimeError("boom in the rounds")
    return STEP(work, t, *a, **k)
