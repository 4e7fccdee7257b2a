"""Queries over every scan of an archive: list, totals, one level across all scans."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._validate import check_positive, strict_keywords, strict_methods


@strict_methods
@dataclass
class CollectionLevel:
    """One level of every scan, concatenated.

    ``scan_id[i]`` is the index into ``scans`` of the scan point i comes from; ``attributes`` holds
    the attributes every scan has (others are left out) plus ``scan_id``.
    """

    points: np.ndarray
    attributes: dict[str, np.ndarray]
    scan_id: np.ndarray
    scans: list[str]
    sizes: list[int]
    rho: float

    def __len__(self) -> int:
        return int(self.points.shape[0])


@strict_keywords
def list_scans(archive: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """One dict per scan (name, n_points, bounds_min, bounds_max, source, reader, collection_key)."""
    from ..archive.reader import open_archive

    with open_archive(archive) as arc:
        rows = arc.index()
        for row in rows:
            view = arc.scan(row["name"])
            prov = view.provenance
            row["source"] = prov.get("source_name")
            row["source_sha256"] = prov.get("source_sha256")
            row["reader"] = prov.get("reader")
            row["collection_key"] = view.build.get("collection_key")
        return rows


@strict_keywords
def total_points(archive: str | os.PathLike[str]) -> int:
    """Number of points of every scan together."""
    from ..archive.reader import open_archive

    with open_archive(archive) as arc:
        return int(sum(r["n_points"] for r in arc.index()))


@strict_keywords
def collection_level(archive: str | os.PathLike[str], rho: float, *, scans: Any = None,
                     attributes: Any = True) -> CollectionLevel:
    """The level of every scan (or of ``scans``) at density ``rho``, merged, with a scan id."""
    from ..archive.reader import open_archive

    rho_v = check_positive(rho, "rho", allow_none=False)
    with open_archive(archive) as arc:
        names = arc.scans if scans is None else [arc.scan(n).name for n in scans]
        levels = [arc.scan(n).level(rho=rho_v, attributes=attributes) for n in names]
    common = set.intersection(*(set(lv.attributes) for lv in levels)) if levels else set()
    pts = np.concatenate([lv.points for lv in levels]) if levels else np.zeros((0, 3))
    sizes = [len(lv) for lv in levels]
    sid = np.repeat(np.arange(len(levels), dtype=np.int32), sizes)
    attrs: dict[str, np.ndarray] = {}
    for key in sorted(common):
        attrs[key] = np.concatenate([lv.attributes[key] for lv in levels])
    attrs["scan_id"] = sid
    return CollectionLevel(points=pts, attributes=attrs, scan_id=sid, scans=list(names), sizes=sizes,
                           rho=float(rho_v))  # type: ignore[arg-type]


@strict_keywords
def scan_level(archive: str | os.PathLike[str], scan: str | None = None, *, rho: Any = None,
               size: Any = None, fraction: Any = None, attributes: Any = True) -> Any:
    """A level of one scan (the archive reader's :class:`~lodbuilder.archive.levels.Level`)."""
    from ..archive.reader import open_archive

    with open_archive(archive) as arc:
        return arc.scan(scan).level(rho, size=size, fraction=fraction, attributes=attributes)
