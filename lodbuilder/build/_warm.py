"""Imported once by the forkserver that forks the build workers (never by ``import lodbuilder``).

Importing it makes the server die with the build's process (so a killed build leaves no server
and, through the workers' own request, no workers), loads the libraries a scan build uses and
runs one tiny build, so that the compiled kernels are loaded from numba's cache once, in the
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

warm()
