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
def filter_view(data: ViewData, flt: Any, scan: str = "") -> ViewData:
    """The points of ``data`` that pass ``flt`` (a :class:`lodbuilder.filters.LevelFilter`), in
    the same order. The slider's rho of a prefix stays a true covering bound: ``radius`` becomes
    :func:`lodbuilder.filters.prefix_bounds` of the kept positions (the radius of the next point
    of the ordering before the filter), so a prefix of k kept points shows the rho of the level
    it was cut from; parents that the filter removed become -1."""
    from ..filters import prefix_bounds

    keep = flt.mask(data.points, {**data.attributes, **data.importance}, scan)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        from ..errors import InputError

        raise InputError(f"the filter ({flt.describe()}) keeps no point of scan {scan!r}")
    new = np.cumsum(keep) - 1
    parent = data.parent[idx]
    parent = np.where((parent >= 0) & keep[np.maximum(parent, 0)], new[np.maximum(parent, 0)], -1)
    radius = prefix_bounds(data.radius, idx)
    radius[0] = data.radius[idx[0]]
    return ViewData(
        points=data.points[idx],
        radius=radius,
        parent=parent,
        attributes={k: np.asarray(v)[idx] for k, v in data.attributes.items()},
        importance={k: np.asarray(v)[idx] for k, v in data.importance.items()},
        scan_id=np.asarray(data.scan_id)[idx],
        scan_names=data.scan_names,
        crs=data.crs,
        units=data.units,
        up=data.up,
        stop_radius=data.stop_radius,
    )


@strict_keywords
def view_data_from_scan(scan: Any, ordering: str | None = None, flt: Any = None) -> ViewData:
    """ViewData of one archive scan (a :class:`lodbuilder.archive.scanview.ScanView`), in its stored
    (uniform) order or in one of its extra orderings (``weighted``, ``floor``, ...), whose levels
    are then the prefixes the viewer shows; with ``flt`` only the points that pass it
    (:func:`filter_view`)."""
    data = _view_data_from_scan(scan, ordering, flt)
    return data if flt is None else filter_view(data, flt, scan.name)


def _view_data_from_scan(scan: Any, ordering: str | None, flt: Any) -> ViewData:
    from ..export import joint_member_names as joint_members

    names = [a for a in COLOUR_ATTRIBUTES if a in scan.attribute_names]
    wanted = (names if len(names) == 3 else []) + (flt.fields() if flt is not None else [])
    # the attributes colour modes read (elevation needs none)
    wanted += [a for a in ("intensity", "classification") if a in scan.attribute_names]
    members = joint_members(scan)
    if members and "scan_id" in scan.attribute_names:
        wanted.append("scan_id")
    wanted = list(dict.fromkeys(wanted))
    attrs = scan.attributes(None, wanted if wanted else False)
    joint: dict[str, Any] = {}
    if members and "scan_id" in attrs:  # a joint scan: its points keep their member scan
        joint = {"scan_id": np.asarray(attrs.pop("scan_id"), dtype=np.int32),
                 "scan_names": tuple(members)}
    importance = {m: np.asarray(scan.importance(m)) for m in scan.importance_names}
    crs = {"crs": scan.crs, "units": scan.units}
    if ordering in (None, "uniform"):
        return ViewData(
            stop_radius=scan.stop_radius,
            points=scan.points(),
            radius=np.asarray(scan.radius),
            parent=np.asarray(scan.parent),
            attributes=attrs,
            importance=importance,
            **({"scan_names": (scan.name,)} | joint),
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
        scan_id=joint["scan_id"][pos] if joint else None,
        scan_names=joint["scan_names"] if joint else (f"{scan.name} ({ordering})",),
        **crs,
    )


@strict_keywords
def load_view_data(
    archive: str | os.PathLike | Any, scan: str | None = None, ordering: str | None = None,
    flt: Any = None,
) -> ViewData:
    """ViewData of ``scan``, or of every scan (merged by insertion radius) when ``scan`` is None,
    in the stored order or the extra ``ordering`` of each scan; with ``flt`` (a
    :class:`lodbuilder.filters.LevelFilter`) only the points that pass it.

    ``archive`` is a path or an open :class:`lodbuilder.archive.reader.Archive`.
    """
    from ..archive.reader import open_archive

    if isinstance(archive, (str, os.PathLike)):
        with open_archive(archive) as arc:
            return load_view_data(arc, scan, ordering, flt)
    if scan is not None:
        return view_data_from_scan(archive.scan(scan), ordering, flt)
    names = archive.scans
    if len(names) <= 1:
        return view_data_from_scan(archive.scan(None), ordering, flt)
    parts = [view_data_from_scan(archive.scan(n), ordering, flt) for n in names]
    return ViewData.merge(parts, names)
