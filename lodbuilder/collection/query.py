"""Queries over every scan of an archive: list, totals, one level across all scans."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._validate import check_positive, quoted_names, strict_keywords, strict_methods
from ..levels import LevelQuery
from ..query import read_level


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


def joint_members(view: Any) -> list[str] | None:
    """The member scan names of a joint scan (built with ``joint``), else None."""
    joint = view.build.get("joint") if isinstance(view.build, dict) else None
    if not joint:
        return None
    return [str(m.get("name")) for m in joint.get("scans", [])]


@strict_keywords
def collection_level(archive: str | os.PathLike[str], rho: float, *, scans: Any = None,
                     attributes: Any = True) -> CollectionLevel:
    """The level of every scan (or of ``scans``) at density ``rho``, merged, with a scan id.

    A joint scan (one ordering of several posed scans, ``build --joint``) counts as its member
    scans: its points carry their own ``scan_id``, ``scans`` lists the member names, and a member
    named in ``scans`` gives the joint level's points of that member only."""
    from ..archive.reader import open_archive

    rho_v = check_positive(rho, "rho", allow_none=False)
    parts: list[tuple[Any, np.ndarray | None, list[str]]] = []  # (level, member ids or None, names)
    with open_archive(archive) as arc:
        members = {n: joint_members(arc.scan(n)) for n in arc.scans}
        for n, member in _wanted(arc, archive, members, scans):
            lv = read_level(arc.scan(n), LevelQuery(rho=rho_v), attributes=True if members[n] else attributes).level
            ms = members[n]
            if ms is None:
                parts.append((lv, None, [n]))
                continue
            ids = np.asarray(lv.attributes["scan_id"], dtype=np.int64)
            if member is None:
                parts.append((lv, ids, ms))
            else:
                keep = ids == ms.index(member)
                parts.append((_subset(lv, keep), np.zeros(int(keep.sum()), np.int64), [member]))
    return _merged(parts, float(rho_v))  # type: ignore[arg-type]


def _wanted(arc: Any, archive: Any, members: dict[str, list[str] | None],
            scans: Any) -> list[tuple[str, str | None]]:
    """``(scan, joint member or None)`` of each scan asked for (every scan when ``scans`` is None);
    a name that is neither a scan nor a joint member is refused with the names there are."""
    from ..errors import ScanNotFoundError

    if scans is None:
        return [(n, None) for n in arc.scans]
    wanted: list[tuple[str, str | None]] = []
    for want in scans:
        owner = next((j for j, m in members.items() if m and want in m and want not in arc.scans), None)
        if owner is not None:
            wanted.append((owner, str(want)))
            continue
        try:
            wanted.append((arc.scan(want).name, None))
        except ScanNotFoundError:
            joint = [m for ms in members.values() if ms for m in ms]
            raise ScanNotFoundError(
                f"archive {archive} has no scan {want!r}; it holds {quoted_names(sorted(arc.scans))}"
                + (f" and the joint members {quoted_names(sorted(joint))}" if joint else "")) from None
    return wanted


def _merged(parts: list[tuple[Any, np.ndarray | None, list[str]]], rho: float) -> CollectionLevel:
    """One level of the parts' points, with a scan id counting joint members as scans."""
    names: list[str] = []
    sids: list[np.ndarray] = []
    sizes: list[int] = []
    pts: list[np.ndarray] = []
    attr_lists: list[dict[str, np.ndarray]] = []
    for lv, member_ids, ns in parts:
        base = len(names)
        names += ns
        m = len(lv.points)
        sid = np.full(m, base, np.int32) if member_ids is None else (member_ids + base).astype(np.int32)
        sids.append(sid)
        pts.append(lv.points)
        attr_lists.append(lv.attributes)
        sizes += [int((sid == base + j).sum()) for j in range(len(ns))]
    common = set.intersection(*(set(a) for a in attr_lists)) - {"scan_id", "scan_point"} if attr_lists else set()
    sid_all = np.concatenate(sids) if sids else np.zeros(0, np.int32)
    attrs: dict[str, np.ndarray] = {k: np.concatenate([a[k] for a in attr_lists]) for k in sorted(common)}
    attrs["scan_id"] = sid_all
    return CollectionLevel(points=np.concatenate(pts) if pts else np.zeros((0, 3)), attributes=attrs,
                           scan_id=sid_all, scans=names, sizes=sizes, rho=rho)


def _subset(level: Any, keep: np.ndarray) -> Any:
    """A level's points and attributes where ``keep``."""
    from types import SimpleNamespace

    return SimpleNamespace(points=level.points[keep], attributes={k: v[keep] for k, v in level.attributes.items()})


@strict_keywords
def scan_level(archive: str | os.PathLike[str], scan: str | None = None, *, rho: Any = None,
               size: Any = None, fraction: Any = None, attributes: Any = True) -> Any:
    """A level of one scan (the archive reader's :class:`~lodbuilder.levels.Level`)."""
    from ..archive.reader import open_archive

    with open_archive(archive) as arc:
        query = LevelQuery(rho=rho, size=size, fraction=fraction)
        return read_level(arc.scan(scan), query, attributes=attributes).level
