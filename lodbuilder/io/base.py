"""The in-memory scan every reader returns and every writer takes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validate import strict_methods


@strict_methods
@dataclass
class Scan:
    """A point cloud read from a file.

    Attributes:
        points: (N, 3) float64 coordinates (poses already applied).
        attributes: per-point arrays keyed by name, each with first dimension N, in the file's own
            dtype (colours as uint8 ``red``/``green``/``blue``, ``nx``/``ny``/``nz``, ``intensity``, ...).
        name: a short scan name (by default the file stem).
        source: path of the file it was read from, or None.
        reader: which reader produced it (``"ply"``, ``"las"``, ...).
        metadata: format details a writer needs to write the same format back
            (LAS scale/offset/point format/CRS WKT, PLY comments, E57 pose, ...). JSON-serialisable.
    """

    points: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    name: str = "scan"
    source: str | None = None
    reader: str = "array"
    metadata: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.points.shape[0])
