"""Load what the viewer shows from an archive (through the archive reader; no PyVista here)."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .._validate import strict_keywords
from ..archive import layout as L
from .data import ViewData

COLOUR_ATTRIBUTES = ("red", "green", "blue")


@strict_keywords
def view_data_from_scan(scan: Any, ordering: str | None = None) -> ViewData:
    """ViewData of one archive scan (a :class:`lodbuilder.archive.scanview.ScanView`), in its stored
    (uniform) order or in one of its extra orderings (``weighted``, ``floor``, ...), whose levels
    are then the prefixes the viewer shows."""
    names = [a for a in COLOUR_ATTRIBUTES if a in scan.attribute_names]
    attrs = scan.attributes(None, names if len(names) == 3 else False)
    importance = {m: np.asarray(scan.importance(m)) for m in scan.importance_names}
    crs = {"crs": scan.crs, "units": scan.units}
    if ordering in (None, "uniform"):
        return ViewData(
            points=scan.points(),
            radius=np.asarray(scan.radius),
            parent=np.asarray(scan.parent),
            attributes=attrs,
            importance=importance,
            scan_names=(scan.name,),
            **crs,
        )
    pos = scan.ordering_positions(ordering)  # (an unknown ordering: the reader's InputError)
    group = f"{L.G_ORDERINGS}/{ordering}"
    return ViewData(
        points=scan.points()[pos],
        radius=np.asarray(scan.dataset(f"{group}/{L.D_RADIUS}")[:]),
        parent=np.asarray(scan.dataset(f"{group}/{L.D_PARENT}")[:]),
        attributes={k: np.asarray(v)[pos] for k, v in attrs.items()},
        importance={k: v[pos] for k, v in importance.items()},
        scan_names=(f"{scan.name} ({ordering})",),
        **crs,
    )


@strict_keywords
def load_view_data(
    archive: str | os.PathLike | Any, scan: str | None = None, ordering: str | None = None
) -> ViewData:
    """ViewData of ``scan``, or of every scan (merged by insertion radius) when ``scan`` is None,
    in the stored order or the extra ``ordering`` of each scan.

    ``archive`` is a path or an open :class:`lodbuilder.archive.reader.Archive`.
    """
    from ..archive.reader import open_archive

    if isinstance(archive, (str, os.PathLike)):
        with open_archive(archive) as arc:
            return load_view_data(arc, scan, ordering)
    if scan is not None:
        return view_data_from_scan(archive.scan(scan), ordering)
    names = archive.scans
    if len(names) <= 1:
        return view_data_from_scan(archive.scan(None), ordering)
    parts = [view_data_from_scan(archive.scan(n), ordering) for n in names]
    return ViewData.merge(parts, names)
