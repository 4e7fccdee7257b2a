"""A level as a COPC file (Cloud Optimized Point Cloud): ``lodbuilder export A.h5 -o OUT.copc.laz``.

COPC stores points in the nodes of an octree; a reader takes the nodes down to the depth it needs.
Here the depths follow the farthest-point ordering: with ``s0`` the spacing written in the COPC
info VLR (the cube side / 128, the usual convention), a point of insertion radius ``r`` belongs
to depth ``floor(log2(s0 / r))`` (seeds to depth 0), i.e. depth d holds the radii in
``(s0 / 2**(d+1), s0 / 2**d]``. Radii never increase along the ordering, so the points of depths
<= D are a prefix of it, of length ``n_D``, which covers the scan within ``rho_D = radius[n_D]``
(<= s0 / 2**(D+1)): every depth prefix is a level with a known covering radius. The file says so
in an EVLR of ours (user id ``lodbuilder``, record 1, JSON: per depth the prefix length, the points
and rho) and keeps ``rank`` and ``radius`` as extra bytes, so the exact ordering can be rebuilt.

One exception keeps the octree walkable: a reader descends from the root, so every node's parent
must exist, and copclib cannot write an empty node. When the parent voxel of a point holds no
point of the depth above (a voxel that only grazes the surface), the point moves up to the first
missing depth of its chain (points taken in rank order, so the earliest ones move). Depths <= D
then hold the prefix of n_D points plus those few moved points (``promoted`` per depth in the
EVLR); their covering radius is still at most rho_D.

Nodes are written breadth-first (depth 0, then 1, ...), so the points of depths <= D are one
contiguous byte range of the file. Attributes, scale, offset and CRS go through
:func:`lodbuilder.io.las.las_layout` (point format 6, 7 or 8: the ones COPC allows; a format 0-5
source maps to its LAS 1.4 equivalent) and copclib writes the file (``pip install
lodbuilder[copc]``).
"""

from __future__ import annotations

import json
import math
import os
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from . import check_level_output

#: about this many points in the root node: the spacing s0 is twice the insertion radius there
ROOT_POINTS = 10_000
#: when the radii cannot give s0 (a few or duplicate points): the cube side over this (the
#: convention of Untwine, PDAL and Potree)
ROOT_CELLS = 128
#: deepest octree level (voxel keys of 21 bits a coordinate)
MAX_DEPTH = 21
#: our EVLR
VLR_USER_ID = "lodbuilder"
VLR_RECORD_ID = 1
VLR_DESCRIPTION = "farthest-point levels per depth"
#: LAS 1.4 header: offset of "Start of first EVLR" (uint64) and "Number of EVLRs" (uint32)
_EVLR_START, _EVLR_COUNT = 235, 243


@dataclass(frozen=True)
class CopcFile:
    """What :func:`write_copc` wrote."""

    path: Path
    n_points: int
    n_total: int
    rho: float
    n_bytes: int
    depths: int
    nodes: int
    spacing: float
    levels: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def promoted(self) -> int:
        return int(sum(lv["promoted_here"] for lv in self.levels))


def _copclib() -> Any:
    from .._optional import require

    return require("copclib", "COPC export")


def copc_point_format(metadata: dict[str, Any], attribute_names: set[str]) -> int:
    """The COPC point format (6, 7 or 8) that holds a source's fields: a LAS source's format
    mapped to its LAS 1.4 equivalent (0, 1, 4 -> 6; 2, 3, 5 -> 7; 6-10 kept, 9 -> 6, 10 -> 8),
    otherwise 7 with red/green/blue (8 with nir too) and 6 without."""
    fmt = metadata.get("las_point_format")
    if fmt is not None:
        return {0: 6, 1: 6, 2: 7, 3: 7, 4: 6, 5: 7, 6: 6, 7: 7, 8: 8, 9: 6, 10: 8}[int(fmt)]
    if {"red", "green", "blue"} <= attribute_names:
        return 8 if "nir" in attribute_names else 7
    return 6


def octree_spacing(radius: np.ndarray, width: float) -> tuple[float, int]:
    """(s0, deepest depth) for a level's insertion radii in a cube of side ``width``.

    s0 = 2 radius[ROOT_POINTS]: the root holds the first ~ROOT_POINTS points and each depth about
    4x more on a surface (radii halve per depth), so nodes keep a few thousand points. The deepest
    depth is one below the band of radius[K / 2]: it takes the tail of the ordering (radii far
    below the scan's spacing, near-duplicates), which would otherwise spread over many deep,
    nearly empty nodes."""
    k = radius.size
    r_root = float(radius[min(ROOT_POINTS, k - 1)])
    spacing = 2.0 * r_root if math.isfinite(r_root) and r_root > 0 else width / ROOT_CELLS
    r_mid = float(radius[k // 2])
    if not (math.isfinite(r_mid) and r_mid > 0):
        return spacing, 0
    return spacing, int(min(MAX_DEPTH, max(0, math.floor(math.log2(spacing / r_mid)) + 1)))


def depth_bands(radius: np.ndarray, spacing: float, max_depth: int) -> np.ndarray:
    """(N,) depth of each insertion radius: floor(log2(spacing / r)) clipped to [0, max_depth]
    (inf -> 0, 0 -> max_depth)."""
    r = np.asarray(radius, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.floor(np.log2(spacing / r))
    d = np.where(np.isinf(r) & (r > 0), 0, d)
    d = np.where(r <= 0, max_depth, d)
    return np.clip(np.nan_to_num(d, nan=max_depth), 0, max_depth).astype(np.int64)


def _voxels(points: np.ndarray, lo: np.ndarray, width: float, depth: int) -> np.ndarray:
    """(M, 3) int64 voxel coordinates of points at ``depth`` in the cube [lo, lo + width]^3."""
    n = 1 << depth
    ijk = np.floor((points - lo) / (width / n)).astype(np.int64)
    return np.clip(ijk, 0, n - 1)


def _code(ijk: np.ndarray) -> np.ndarray:
    return (ijk[..., 0] << 42) | (ijk[..., 1] << 21) | ijk[..., 2]


def assign_depths(
    points: np.ndarray, band: np.ndarray, lo: np.ndarray, width: float
) -> tuple[np.ndarray, np.ndarray]:
    """(depth, voxel code) of every point: its band, except that a point whose parent voxel has
    no point of the depth above moves up to the first missing depth of its chain (points in
    rank order; see the module docstring). Every node's parent then exists."""
    n = points.shape[0]
    depth = band.copy()
    nodes: list[set[int]] = [set() for _ in range(int(band.max()) + 1)]
    for d in range(int(band.max()) + 1):
        sel = np.flatnonzero(band == d)
        if sel.size == 0:
            continue
        if d == 0:
            nodes[0].add(0)
            continue
        ijk = _voxels(points[sel], lo, width, d)
        parents = _code(ijk >> 1)
        known = np.fromiter(nodes[d - 1], dtype=np.int64, count=len(nodes[d - 1]))
        ok = np.isin(parents, known)
        nodes[d].update(np.unique(_code(ijk[ok])).tolist())
        for i in np.flatnonzero(~ok):  # orphans, in rank order (sel is sorted)
            p = int(sel[i])
            chain = [_code(ijk[i] >> (d - a)) for a in range(d)]  # ancestor codes, depth 0..d-1
            e = d - 1
            while e >= 0 and int(chain[e]) not in nodes[e]:
                e -= 1  # (e = -1: no root yet; the point becomes the root)
            if e == d - 1:  # an earlier orphan made the parent exist
                nodes[d].add(int(_code(ijk[i])))
                continue
            depth[p] = e + 1
            nodes[e + 1].add(int(chain[e + 1]))
    codes = np.empty(n, dtype=np.int64)
    for d in np.unique(depth):
        sel = np.flatnonzero(depth == d)
        codes[sel] = _code(_voxels(points[sel], lo, width, int(d)))
    return depth, codes


def _extra_bytes_vlr(copclib: Any, header: Any) -> Any:
    """copclib's extra-bytes VLR for a laspy header: copclib builds one only from a file, so a
    one-point LAZ with that header is written and read back (its Python API has no other way)."""
    import laspy

    with tempfile.TemporaryDirectory(prefix="lodbuilder-copc-") as tmp:
        path = os.path.join(tmp, "eb.laz")
        one = laspy.LasData(header)
        one.points = laspy.ScaleAwarePointRecord.zeros(1, header=header)
        one.write(path, do_compress=True)
        return copclib.LazReader(path).laz_config.extra_bytes_vlr


def _append_evlr(path: Path, user_id: str, record_id: int, description: str, data: bytes) -> None:
    """Append an EVLR to a finished LAS 1.4 file and count it in the header (laspy serialises the
    record; the header's EVLR count and start are two fixed fields of the LAS 1.4 header)."""
    import laspy
    from laspy.vlrs.vlrlist import VLRList

    with open(path, "r+b") as f:
        f.seek(_EVLR_START)
        start, count = struct.unpack("<QI", f.read(12))
        f.seek(0, os.SEEK_END)
        end = f.tell()
        VLRList([laspy.VLR(user_id, record_id, description, data)]).write_to(f, as_extended=True)
        f.seek(_EVLR_START)
        f.write(struct.pack("<QI", start if count else end, count + 1))


def write_copc(
    out: str | os.PathLike,
    points: np.ndarray,
    attributes: dict[str, np.ndarray],
    radius: np.ndarray,
    rho: float,
    *,
    metadata: dict[str, Any] | None = None,
    n_total: int | None = None,
    name: str = "scan",
) -> CopcFile:
    """Write a level (points in farthest-point order, their insertion radii, the level's covering
    bound ``rho``) as a COPC file whose octree depths are its levels (module docstring), atomically.

    ``attributes`` are written as LAS fields or extra bytes by :func:`lodbuilder.io.las.las_layout`
    with ``metadata`` (the scan's format metadata: LAS scale/offset, CRS...), plus ``rank`` and
    ``radius`` extra bytes. What the mapping changed is in ``notes`` and logged as warnings of
    lodbuilder.io, as :func:`lodbuilder.io.write_points` does."""
    copclib = _copclib()
    from ..io._files import atomic_output, run_isolated
    from ..io.api import log_notes
    from ..io.las import las_layout

    out, pts, radius = check_level_output(out, "COPC output", (".copc.laz",), points, radius)
    k = pts.shape[0]
    for reserved in ("rank", "radius"):
        if reserved in attributes:
            raise InputError(
                f"attribute {reserved!r} would clash with the {reserved} the COPC file records; "
                "rename it"
            )
    meta = dict(metadata or {})
    n_total = int(n_total or k)

    # the records: attributes, rank and radius through the one LAS mapping of lodbuilder.io
    attrs = dict(attributes)
    attrs["rank"] = np.arange(k, dtype=np.uint32 if n_total < 2**32 else np.uint64)
    attrs["radius"] = radius
    fmt = copc_point_format(meta, set(attributes))
    layout = las_layout(pts, attrs, meta, point_format=fmt, version="1.4")
    for ed in layout.extra_dims:
        if ed.name == "rank":
            ed.description = "lodbuilder farthest-point rank"
        elif ed.name == "radius":
            ed.description = "lodbuilder insertion radius"
    las = layout.las_data(pts)
    records = las.points.array

    # the octree: a cube from the minimum corner of the stored (quantised) coordinates, as
    # copclib derives node boxes from the header's minimum; spacing s0 at the root
    stored = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    pmin, pmax = stored.min(axis=0), stored.max(axis=0)
    half = max(float((pmax - pmin).max()) / 2.0, float(layout.scales.max()))
    width = 2.0 * half
    lo = pmin
    centre = pmin + half
    spacing, max_depth = octree_spacing(radius, width)
    band = depth_bands(radius, spacing, max_depth)
    depth, codes = assign_depths(stored, band, lo, width)

    # in the file's order: depth, node, rank (breadth-first, so depths <= D are one byte range)
    order = np.lexsort((np.arange(k), codes, depth))
    records = records[order]
    d_sorted, c_sorted = depth[order], codes[order]
    cut = np.flatnonzero((np.diff(d_sorted) != 0) | (np.diff(c_sorted) != 0)) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [k]])

    header = layout.header()
    header.global_encoding.wkt = True  # (COPC is LAS 1.4 with WKT)
    config = copclib.CopcConfigWriter(
        fmt,
        copclib.Vector3(*map(float, layout.scales)),
        copclib.Vector3(*map(float, layout.offsets)),
        layout.crs_wkt or "",
        _extra_bytes_vlr(copclib, header),
    )
    info = config.copc_info
    info.center_x, info.center_y, info.center_z = map(float, centre)
    info.halfsize = half
    info.spacing = spacing
    config.las_header.min = copclib.Vector3(*map(float, pmin))
    config.las_header.max = copclib.Vector3(*map(float, pmax))
    if layout.system_identifier:
        config.las_header.system_identifier = layout.system_identifier[:32]
    config.las_header.generating_software = "lodbuilder"
    returns = np.bincount(np.asarray(las.return_number, dtype=np.int64), minlength=16)
    config.las_header.points_by_return = [int(c) for c in returns[1:16]]

    levels = _levels(radius, band, depth, rho, spacing)
    doc = {
        "format": "lodbuilder farthest-point levels",
        "version": 1,
        "scan": name,
        "n_points": k,
        "n_points_scan": n_total,
        "spacing": spacing,
        "rule": "depth d holds the points of insertion radius in (spacing/2^(d+1), spacing/2^d]; "
        "depths <= d hold the prefix of fps_prefix points of the farthest-point order (plus "
        "'promoted' points that keep the octree connected) and cover the scan within rho",
        "extra_bytes": {"rank": "position in the farthest-point order", "radius": "insertion radius"},
        "levels": levels,
    }

    def write_nodes(tmp: Path) -> None:
        writer = copclib.FileWriter(str(tmp), config)
        try:
            for s, e in zip(starts, ends, strict=True):
                key = copclib.VoxelKey(
                    int(d_sorted[s]),
                    int(c_sorted[s] >> 42),
                    int((c_sorted[s] >> 21) & 0x1FFFFF),
                    int(c_sorted[s] & 0x1FFFFF),
                )
                data = np.frombuffer(records[s:e].tobytes(), dtype=np.int8)
                writer.AddNode(key, copclib.VectorChar(data))
        finally:
            writer.Close()

    with atomic_output(out) as tmp:
        # copclib aborts the process when a write fails (a full disk): it writes in a child
        run_isolated(write_nodes, tmp, "copclib")
        _append_evlr(
            tmp,
            VLR_USER_ID,
            VLR_RECORD_ID,
            VLR_DESCRIPTION,
            json.dumps(doc, allow_nan=False).encode("utf-8"),
        )
        n_bytes = tmp.stat().st_size
    log_notes(out, layout.notes)
    return CopcFile(
        path=out,
        n_points=k,
        n_total=n_total,
        rho=float(rho),
        n_bytes=n_bytes,
        depths=int(depth.max()) + 1,
        nodes=len(starts),
        spacing=spacing,
        levels=levels,
        notes=list(layout.notes),
    )


def _levels(
    radius: np.ndarray, band: np.ndarray, depth: np.ndarray, rho: float, spacing: float
) -> list[dict[str, Any]]:
    """Per depth D: points at depths <= D, the farthest-point prefix among them, the points
    moved up to keep the octree connected, and the covering radius of the prefix."""
    k = radius.size
    out = []
    for d in range(int(depth.max()) + 1):
        prefix = int(np.count_nonzero(band <= d))  # a prefix: bands never decrease along it
        points = int(np.count_nonzero(depth <= d))
        r = float(radius[prefix]) if prefix < k else float(rho)
        out.append(
            {
                "depth": d,
                "points": points,
                "fps_prefix": prefix,
                "promoted": points - prefix,
                "promoted_here": int(np.count_nonzero((depth == d) & (band != d))),
                "rho": r if math.isfinite(r) else None,
                "spacing": spacing / 2**d,
            }
        )
    return out


def export_copc(scan: Any, out: str | os.PathLike, size: int) -> CopcFile:
    """Write the level of ``size`` points of an archive scan (a ScanView) as COPC, with every
    attribute, its importance maps (extra bytes ``importance_<name>``), rank and radius."""
    level = scan.level(size=size)
    attrs = dict(level.attributes)
    for m in scan.importance_names:
        key = f"importance_{m}"[:32]
        if key not in attrs:
            attrs[key] = np.asarray(scan.importance(m)[:size], dtype=np.float32)
    return write_copc(
        out,
        level.points,
        attrs,
        level.radius,
        level.rho,
        metadata=scan.format_metadata,  # (the CRS included: ScanView.crs is read from it)
        n_total=scan.n_ordered,
        name=scan.name,
    )
