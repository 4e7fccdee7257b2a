"""Levels written for other tools: a COPC file (``export/copc.py``: QGIS, Potree, viewer.copc.io,
CloudCompare) and a standalone web page (``export/web.py``). The flow is archive -> level ->
export: each exporter takes an archive scan and a level size; nothing heavy is imported here."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import InputError


def joint_member_names(view: object) -> list[str] | None:
    """The member scan names of a joint scan (``build --joint``; its points carry ``scan_id``),
    else None. (The same rule as :func:`lodbuilder.collection.query.joint_members`, which lives
    a room above the exporters and the viewer.)"""
    build = getattr(view, "build", None)
    joint = build.get("joint") if isinstance(build, dict) else None
    if not joint:
        return None
    return [str(m.get("name")) for m in joint.get("scans", [])]


def check_level_output(
    out: str | os.PathLike, kind: str, suffixes: tuple[str, ...], points: object, radius: object
) -> tuple[Path, np.ndarray, np.ndarray]:
    """What every exporter checks before it writes: ``out`` ends in one of ``suffixes`` (the
    first one named in the message) and can be written, ``points`` is (K, 3) with K >= 1 and
    ``radius`` (K,). Returns (out, points as contiguous float64, radius as float64)."""
    from ..io._files import check_output_path

    out = Path(out)
    if not out.name.lower().endswith(suffixes):
        raise InputError(f"{kind} {out} must end in {suffixes[0]}")
    check_output_path(out)
    pts = np.ascontiguousarray(points, dtype=np.float64)
    k = pts.shape[0]
    if pts.ndim != 2 or pts.shape[1] != 3 or k == 0:
        raise InputError(f"points must have shape (K, 3) with K >= 1, got {pts.shape}")
    rad = np.asarray(radius, dtype=np.float64)
    if rad.shape != (k,):
        raise InputError(f"radius must have shape ({k},) like the points, got {rad.shape}")
    return out, pts, rad

