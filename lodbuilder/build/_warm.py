"""Imported once by the forkserver that forks the build workers (never by ``import lodbuilder``).

Importing it makes the server die with the build's process (so a killed build leaves no server
and, through the workers' own request, no workers), loads the libraries a scan build uses and
runs one tiny build (and one tiny resumable ordering), so that the compiled kernels are loaded from numba's cache once, in the
server; every worker forked from it starts warm instead of paying the imports and the cache
loading again.
"""

from __future__ import annotations

import contextlib


def warm() -> None:
    import numpy as np

    from .executors import die_with_parent

    die_with_parent()
    with contextlib.suppress(Exception):  # warming is an optimisation only
        import h5py  # noqa: F401
        import scipy.spatial  # noqa: F401
        with contextlib.suppress(ImportError):  # (the LAS/LAZ reader: an optional dependency)
            import laspy  # noqa: F401
            import lazrs  # noqa: F401

        from ..archive import writer  # noqa: F401
        from ..sampling.fastfps import fastfps

        rng = np.random.default_rng(0)
        t = rng.random(400) * 6.283
        pts = np.stack([np.cos(t), np.sin(t), rng.random(400)], axis=1)
        fastfps(pts)
        # the resumable engine's kernels too (the radius rounds' owners, forked from here, would
        # each load them from the cache on their first step: about 0.4 CPU-s an owner)
        from ..sampling.resumable import resume_fastfps, start_fastfps

        state = start_fastfps(pts, timed_seeds=(np.arange(8), np.zeros(8)))
        resume_fastfps(state, rho=0.3, sources=np.arange(4), bulk=True)
        resume_fastfps(state, sources=(np.arange(4, 8), np.full(4, 0.01)))


warm()
