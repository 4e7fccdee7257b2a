"""Loading the engine's kernels from numba's cache (lodbuilder._kernels.warm): what a build's
fixed cost is made of."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_COUNT_REFRESHES = r"""
import numpy as np
import numba.core.base as base
full = []
refresh = base.BaseContext.refresh
def counted(self):
    full.append(1)
    return refresh(self)
base.BaseContext.refresh = counted
"""


def _run(code: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          check=True).stdout.strip()


def test_cached_kernels_load_without_numbas_full_refresh():
    # the first full refresh of numba's target context imports and installs every implementation
    # numba has (about 0.4 CPU-s); loading and running cached kernels needs none of it
    code = _COUNT_REFRESHES + (
        "from lodbuilder._kernels.warm import compile_group, ensure_compiled\n"
        "ensure_compiled()\n"  # (compiles first when the cache is cold: not counted below)
        "full.clear()\n"
        "for group in ('band', 'thin', 'ordering'):\n"
        "    compile_group(group)\n"
        "from lodbuilder import fastfps\n"
        "rng = np.random.default_rng(1)\n"
        "t = rng.random(3000) * 6.283\n"
        "o = fastfps(np.stack([np.cos(t), np.sin(t), rng.random(3000)], axis=1))\n"
        "print(len(full), len(o.order))\n"
    )
    # (in a fresh process: this one may have compiled something already; the first run fills a
    # cold cache, e.g. on a fresh clone, where kernels outside ensure_compiled's groups compile)
    _run(code)
    assert _run(code) == "0 3000"


def test_a_kernel_missing_from_the_cache_still_compiles_under_the_light_refresh():
    # the light refresh is the cache's only: when the cache misses (or there is none), the
    # compiler's own refresh is numba's full one
    code = _COUNT_REFRESHES + (
        "import numba\n"
        "from lodbuilder._kernels.warm import _light_refresh\n"
        "f = numba.njit(lambda a: np.sort(a)[-1] * 2.0)\n"  # (not cached)
        "with _light_refresh(f):\n"
        "    f.compile((numba.float64[::1],))\n"
        "print(len(full) > 0, f(np.array([3.0, 1.0])))\n"
    )
    assert _run(code) == "True 6.0"


def test_nested_fewer_collections_do_not_count_the_frozen_objects(monkeypatch):
    # gc.get_freeze_count walks every frozen object (6 ms a call in a build, once per kernel
    # group): inside an outer block the inner ones know they are inner without it
    import gc

    from lodbuilder._kernels.warm import fewer_collections

    before = gc.get_freeze_count()
    with fewer_collections():
        calls = []
        count = gc.get_freeze_count
        monkeypatch.setattr(gc, "get_freeze_count", lambda: calls.append(1) or count())
        for _ in range(3):
            with fewer_collections():
                pass
        monkeypatch.undo()
        assert calls == [] and gc.get_freeze_count() > 0
    assert gc.get_freeze_count() == before
