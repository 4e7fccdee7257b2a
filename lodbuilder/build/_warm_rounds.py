"""Preloaded by the forkserver after :mod:`._warm` for a build with radius rounds (the option
``seam_rounds``): one tiny resumable ordering, so that the rounds' owners, forked
from the server, find the resumable engine's kernels loaded (each would load them from numba's cache
on its first step, inside the order phase: about 0.4 CPU-s an owner). Builds without rounds skip it."""

from __future__ import annotations

import contextlib


def warm() -> None:
    import numpy as np

    with contextlib.suppress(Exception):  # warming is an optimisation only
        from ..sampling.resumable import resume_fastfps, start_fastfps

        t = np.random.default_rng(0).random(400) * 6.283
        pts = np.stack([np.cos(t), np.sin(t), t / 6.283], axis=1)
        state = start_fastfps(pts, timed_seeds=(np.arange(8), np.zeros(8)))
        resume_fastfps(state, rho=0.3, sources=np.arange(4), bulk=True)
        resume_fastfps(state, sources=(np.arange(4, 8), np.full(4, 0.01)))


warm()
