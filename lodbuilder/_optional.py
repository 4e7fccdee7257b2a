"""Optional dependencies: which extra installs each, and one message when one is missing.

``require("pyvista", "lodbuilder view")`` imports and returns the module, or raises
:class:`~lodbuilder.errors.MissingDependencyError` with one line naming the feature, the package
and the ``pip install 'lodbuilder[EXTRA]'`` that brings it. The command line turns any
``ImportError`` of these modules that escapes a command into the same line.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import MissingDependencyError

# top-level module -> (package name on PyPI, extra of pyproject.toml that installs it)
EXTRAS: dict[str, tuple[str, str]] = {
    "pyvista": ("pyvista", "viz"),
    "vtk": ("vtk", "viz"),
    "vtkmodules": ("vtk", "viz"),
    "matplotlib": ("matplotlib", "viz"),
    "imageio": ("imageio", "viz"),
    "imageio_ffmpeg": ("imageio-ffmpeg", "viz"),
    "laspy": ("laspy", "las"),
    "lazrs": ("lazrs", "las"),
    "pye57": ("pye57", "e57"),
    "copclib": ("copclib", "dev"),
    "dask": ("dask", "distributed"),
    "distributed": ("distributed", "distributed"),
}


def extra_for(module: str | None) -> tuple[str, str] | None:
    """``(package, extra)`` of a module name (or a dotted submodule), None when not optional."""
    if not module:
        return None
    return EXTRAS.get(module.split(".")[0])


def missing_message(module: str, feature: str) -> str:
    """One line: what needs ``module``, and how to install it."""
    found = extra_for(module)
    if found is None:
        return f"{feature} needs the Python package {module!r}, which is not installed"
    package, extra = found
    return (
        f"{feature} needs {package}, which is not installed; install it with: "
        f"pip install 'lodbuilder[{extra}]'"
    )


def require(module: str, feature: str) -> ModuleType:
    """Import ``module`` or raise MissingDependencyError naming ``feature`` and the extra."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        missing = getattr(exc, "name", None) or module
        if extra_for(missing) is None:
            missing = module
        raise MissingDependencyError(missing_message(missing, feature)) from None
