"""Load what the viewer shows from an archive (through the archive reader; no PyVista here)."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .data import ViewData

COLOUR_ATTRIBUTES = ("red", "green", "blue")


def view_data_from_scan(scan: Any) -> ViewData:
    """ViewData of one archive scan (a :class:`lodbuilder.archive.reader.ScanView`)."""
    names = [a for a in COLOUR_ATTRIBUTES if a in scan.attribute_names]
    attrs = scan.attributes(None, names if len(names) == 3 else False)
    importance = {m: np.asarray(scan.importance(m)) for m in scan.importance_names}
    return ViewData(
        points=scan.points(),
        radius=np.asarray(scan.radius),
        parent=np.asarray(scan.parent),
        attributes=attrs,
        importance=importance,
        scan_names=(scan.name,),
    )


def load_view_data(archive: str | os.PathLike | Any, scan: str | None = None) -> ViewData:
    """ViewData of ``scan``, or of every scan (merged by insertion radius) when ``scan`` is None.

    ``archive`` is a path or an open :class:`lodbuilder.archive.reader.Archive`.
    """
    from ..api import open_archive

    if isinstance(archive, (str, os.PathLike)):
        with open_archive(archive) as arc:
            return load_view_data(arc, scan)
    if scan is not None:
        return view_data_from_scan(archive.scan(scan))
    names = archive.scans
    if len(names) <= 1:
        return view_data_from_scan(archive.scan(None))
    return ViewData.merge([view_data_from_scan(archive.scan(n)) for n in names], names)
