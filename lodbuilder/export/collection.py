"""One export of a whole collection: ``lodbuilder export A.h5 --all-scans -o OUT.copc.laz |
OUT.html``. The levels of every scan of the archive (a joint scan counts as its member scans)
at one density rho are merged into one ordering by insertion radius (stable, descending), so
that every prefix cut at a radius threshold is the union of each scan's level at that
threshold, and written as one COPC file or one web page with the scan of each point as an
attribute (``scan_id``) whose names the file carries (the COPC EVLR's ``scans``, the page's
legend)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError


@dataclass(frozen=True)
class MergedLevel:
    """The merged levels of an archive's scans (see the module docstring)."""

    points: np.ndarray
    radius: np.ndarray
    scan_id: np.ndarray
    names: list[str]
    rho: float
    n_total: int
    metadata: dict[str, Any]
    crs: str | None
    units: str | None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)


def merged_level(arc: Any, rho: float | None) -> MergedLevel:
    """Every scan's level at ``rho`` (None: every point), merged by insertion radius. Scans in
    different CRSs are refused (one file has one CRS)."""
    from . import joint_member_names as joint_members

    parts = []
    names: list[str] = []
    ids: list[np.ndarray] = []
    crs_seen: dict[str | None, str] = {}
    for name in arc.scans:
        view = arc.scan(name)
        crs_seen.setdefault(view.crs, name)
        level = view.level(size=view.n_ordered) if rho is None else view.level(rho=rho)
        members = joint_members(view)
        if members and "scan_id" in level.attributes:
            ids.append(np.asarray(level.attributes["scan_id"], dtype=np.int64) + len(names))
            names += members
        else:
            ids.append(np.full(level.size, len(names), dtype=np.int64))
            names.append(view.name)
        parts.append((view, level))
    if len(crs_seen) > 1:
        raise InputError(
            "the scans are in different CRSs (" + ", ".join(f"{s!r}" for s in crs_seen.values())
            + " differ); export them one at a time with --scan NAME"
        )
    radius = np.concatenate([lv.radius for _, lv in parts])
    perm = np.argsort(-radius, kind="stable")
    common = set.intersection(*(set(lv.attributes) for _, lv in parts)) - {"scan_id", "scan_point"}
    attrs = {k: np.concatenate([np.asarray(lv.attributes[k]) for _, lv in parts])[perm]
             for k in sorted(common)}
    first = parts[0][0]
    return MergedLevel(
        points=np.concatenate([lv.points for _, lv in parts])[perm],
        radius=radius[perm],
        scan_id=np.concatenate(ids)[perm],
        names=names,
        rho=max(float(lv.rho) for _, lv in parts),
        n_total=int(sum(v.n_ordered for v, _ in parts)),
        metadata=dict(first.format_metadata),
        crs=first.crs,
        units=first.units,
        attributes=attrs,
    )


def export_collection(arc: Any, out: str | os.PathLike, rho: float | None, *, fmt: str,
                      max_points: int | None = None, up: str = "z") -> tuple[Any, MergedLevel]:
    """Write the merged level of every scan as one COPC file (``fmt`` "COPC") or web page
    ("web page"); returns (what the writer returned, the merged level)."""
    m = merged_level(arc, rho)
    sid = m.scan_id.astype(np.uint16 if len(m.names) < 2**16 else np.uint32)
    if fmt == "COPC":
        from .copc import write_copc

        return write_copc(out, m.points, {**m.attributes, "scan_id": sid}, m.radius, m.rho,
                          metadata=m.metadata, n_total=m.n_total, name="collection",
                          scans=m.names), m
    if fmt != "web page":
        raise InputError(f"a collection exports as one COPC file or web page, not {fmt}; "
                         "export one scan with --scan NAME")
    from ..viewer.data import classification_legend, elevation_legend, intensity_legend, scan_legend
    from .web import write_web_page

    k = m.points.shape[0]
    if max_points is not None and k > max_points:
        raise InputError(f"the collection's level has {k:,} points, more than a web page holds "
                         f"({max_points:,}); ask for a coarser level (--rho) or raise --max-points")
    rgb = None
    if {"red", "green", "blue"} <= set(m.attributes):
        rgb = np.column_stack([m.attributes[c] for c in ("red", "green", "blue")])
    axis = "xyz".index(up[-1])
    elev = m.points[:, axis] * (-1.0 if up.startswith("-") else 1.0)
    scalars = {"elevation": (elev, elevation_legend(elev, up, m.units))}
    if "intensity" in m.attributes:
        scalars["intensity"] = (m.attributes["intensity"], intensity_legend(m.attributes["intensity"]))
    cats: dict[str, tuple[np.ndarray, Any]] = {}
    if len(m.names) <= 256:
        cats["scan"] = (m.scan_id, scan_legend(m.names))
    if "classification" in m.attributes:
        codes = np.asarray(m.attributes["classification"])
        cats["classification"] = (codes, classification_legend(codes))
    page = write_web_page(out, m.points, m.radius, m.rho, n_total=m.n_total, rgb=rgb,
                          name="collection", crs=m.crs, units=m.units, up=up,
                          note=f"{len(m.names)} scans", scalars=scalars, categories=cats)
    return page, m
