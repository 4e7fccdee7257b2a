"""Writing LAS/LAZ files through :func:`lodbuilder.io.las.layout.las_layout`."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from .common import check_laz_backend, laspy_module
from .layout import las_layout

log = logging.getLogger(__name__)


def check_output(path: Path) -> None:
    """Refuse, before any work, a LAS/LAZ output this installation cannot write (no laspy, or
    no LAZ backend for .laz); see ``registry.writer_for``."""
    check_laz_backend(laspy_module(path), path)


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], metadata: dict[str, Any] | None) -> list[str]:
    """Write through :func:`las_layout` (``check_output`` has run); returns its notes (what was
    changed)."""
    compress = path.suffix.lower() == ".laz"
    layout = las_layout(points, attributes, metadata)
    las = layout.las_data(points)
    with open(path, "wb") as f:
        las.write(f, do_compress=compress)
    return layout.notes
