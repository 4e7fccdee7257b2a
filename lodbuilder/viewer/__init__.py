"""The level viewer: a PyVista window over the levels of an archive.

Importing this package imports neither PyVista nor VTK; :mod:`lodbuilder.viewer.app` does, and is
imported only when a window, a screenshot or an animation is asked for.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_LAZY = {
    "ViewData": "lodbuilder.viewer.data",
    "from_arrays": "lodbuilder.viewer.data",
    "LevelViewer": "lodbuilder.viewer.app",
    "write_movie": "lodbuilder.viewer.movie",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'lodbuilder.viewer' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value
    return value
