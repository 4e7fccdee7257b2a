"""lodbuilder: multiresolution point-set archives from dense 3D scans.

The public API is imported lazily, so ``import lodbuilder`` stays light: it imports neither numba,
pyvista nor dask.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "fastfps": "lodbuilder.sampling.fastfps",
    "euclidean_fps": "lodbuilder.sampling.fastfps",
    "Ordering": "lodbuilder.sampling.ordering",
    "Scan": "lodbuilder.io.base",
    "errors": "lodbuilder.errors",
    "build_archive": "lodbuilder.api",
    "BuildResult": "lodbuilder.api",
    "open_archive": "lodbuilder.api",
    "Archive": "lodbuilder.api",
    "Level": "lodbuilder.levels",
}

__all__ = sorted(_LAZY) + ["__version__"]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'lodbuilder' has no attribute {name!r}")
    mod = import_module(module)
    value = mod if name == "errors" else getattr(mod, name)
    globals()[name] = value
    return value
