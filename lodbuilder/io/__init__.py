"""Scan input and output: one module per format, chosen by file suffix (see ``registry``).

    from lodbuilder.io import read_scan, read_scans, write_points
    scan = read_scan("bun000.ply")          # Scan(points float64 (N,3), attributes, metadata)
    write_points("level.ply", pts, {"red": r})

Optional formats need extras: LAS/LAZ ``pip install lodbuilder[las]``, E57 ``pip install lodbuilder[e57]``.
"""

from __future__ import annotations

from ._files import file_sha256
from .api import read_scan, read_scans, write_points, write_scan
from .base import Scan
from .registry import READERS, WRITERS, register

__all__ = ["READERS", "WRITERS", "Scan", "file_sha256", "read_scan", "read_scans", "register", "write_points", "write_scan"]
