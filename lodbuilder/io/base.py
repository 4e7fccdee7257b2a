"""The in-memory scan every reader returns and every writer takes."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
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


#: what a format's chunked read yields: (first row, float64 (m, 3) points, attributes of those rows)
Rows = tuple[int, np.ndarray, dict[str, np.ndarray]]


def whole(rows: Iterable[Rows]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The points and attributes of every chunk of a chunked read, concatenated (a single chunk,
    as a whole read asks for, is returned as it is: no copy)."""
    chunks = list(rows)
    if len(chunks) == 1:
        return chunks[0][1], chunks[0][2]
    if not chunks:
        return np.empty((0, 3), dtype=np.float64), {}
    pts = np.concatenate([c[1] for c in chunks])
    return pts, {k: np.concatenate([c[2][k] for c in chunks]) for k in chunks[0][2]}


def file_stem(path: Path) -> str:
    """A scan file's name without its suffix (``.copc.laz`` counts as one suffix): the one rule
    by which the readers, the stream and the build name a scan after its file."""
    name = Path(path).name
    return name[: -len(".copc.laz")] if name.lower().endswith(".copc.laz") else Path(path).stem
