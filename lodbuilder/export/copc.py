"""A level as a COPC 1.0 file (Cloud Optimized Point Cloud): ``lodbuilder export A.h5 -o OUT.copc.laz``.

COPC stores points in the nodes of an octree; a reader takes the nodes down to the depth it needs.
Here the depths follow the farthest-point ordering: with ``s0`` the spacing written in the COPC
info VLR (twice the insertion radius of point ROOT_POINTS), a point of insertion radius ``r``
belongs to depth ``floor(log2(s0 / r))`` (seeds to depth 0; the deepest depth takes the rest,
see :func:`octree_spacing`), i.e. depth d holds the radii in ``(s0 / 2**(d+1), s0 / 2**d]``.
Radii never increase along the ordering, so the points of depths <= D are a prefix of it, of
length ``n_D``, which covers the scan within ``rho_D = radius[n_D]`` (<= s0 / 2**(D+1)): every
depth prefix is a level with a known covering radius. The file says so in an EVLR of ours (user
id ``lodbuilder``, record 1, JSON: per depth the prefix length, the points and rho).

``rank_radius="level"`` (``--rank-radius``) refines each depth into up to SUBLEVELS (256)
levels: depth d's band of the ordering is cut into runs of equal count, each point stores the
index of its run in a uint8 extra byte ``sublevel``, and record 3 (:func:`read_sublevels`)
holds per (depth, sublevel) the prefix that ends there, the points a reader keeps and their
covering radius (the archive's radius at that prefix, exactly). Keeping the points of depths
< D and those of depth D with sublevel <= s gives that prefix: a level of any of up to
256 x depths sizes with its covering radius. ``rank_radius="exact"`` (``--rank-radius exact``)
keeps each point's ``rank`` (uint32 extra bytes) and the insertion radius by rank (record 2,
:func:`read_radius_table`): the exact ordering, so every level can be rebuilt.

What that costs (bytes a point over the file without; autzen / the 4x4 survey, whose source
LAZ holds 5.5 bytes a point; tools/bench_export.py): the sublevel byte about 1.0 (a uniform
byte in scanner order), its table 5.6 / 11 kB: 1.31 / 1.28 x the source LAZ. The exact rank
2.1 / 2.6 and its radius table 1.0 / 0.3: 1.69 / 1.63 x. The rank cannot be much cheaper: in
any order LAZ compresses well the ranks of a depth are a random permutation of it, log2(m!)
/ m bits a point at least (2.4 bytes for the survey's 1.6M-point deepest depth: 1.53 x with
a perfect coder). Radius as float64 extra bytes instead would cost 6.9, as float32 3.2.

Inside a node the order is free (the depths carry the levels): points go by GPS time where they
have one (the scanner's order, which LAZ's delta coding compresses best), else by Morton code.

One exception keeps the octree walkable: a reader descends from the root, so every node's parent
must exist. When the parent voxel of a point holds no point of the depth above (a voxel that
only grazes the surface), the point moves up to the first missing depth of its chain (points
taken in rank order, so the earliest ones move). Depths <= D then hold the prefix of n_D points
plus those few moved points (``promoted`` per depth in the EVLR); their covering radius is still
at most rho_D.

Nodes are written breadth-first (depth 0, then 1, ...), so the points of depths <= D are one
contiguous byte range of the file. Attributes, scale, offset and CRS go through
:func:`lodbuilder.io.las.las_layout` (point format 6, 7 or 8: the ones COPC allows; a format 0-5
source maps to its LAS 1.4 equivalent); :mod:`._copc_file` writes the bytes (laspy and lazrs).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from . import check_level_output
from ._copc_tables import (
    RADIUS_DESCRIPTION,
    RADIUS_RECORD_ID,
    SUBLEVEL_DESCRIPTION,
    SUBLEVEL_RECORD_ID,
    SUBLEVELS,
    VLR_DESCRIPTION,
    VLR_RECORD_ID,
    VLR_USER_ID,
    check_rank_radius,
    radius_table,
    read_radius_table,
    read_sublevels,
    sublevel_payload,
    sublevels,
)

#: about this many points in the root node: the spacing s0 is twice the insertion radius there
ROOT_POINTS = 10_000
#: when the radii cannot give s0 (a few or duplicate points): the cube side over this (the
#: convention of Untwine, PDAL and Potree)
ROOT_CELLS = 128
#: deepest octree level (voxel keys of 21 bits a coordinate)
MAX_DEPTH = 21

__all__ = ["RADIUS_RECORD_ID", "SUBLEVEL_RECORD_ID", "SUBLEVELS", "VLR_USER_ID", "read_radius_table",
           "read_sublevels", "radius_table", "sublevels", "write_copc", "export_copc"]


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


def check_copc_dependencies() -> None:
    """Raise MissingDependencyError when laspy or lazrs (what COPC export needs) is missing."""
    from .._optional import require

    require("laspy", "COPC export")
    require("lazrs", "COPC export")


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


def octree_spacing(radius: np.ndarray, width: float, tail: int = 8) -> tuple[float, int]:
    """(s0, deepest depth) for a level's insertion radii in a cube of side ``width``.

    s0 = 2 radius[ROOT_POINTS]: the root holds the first ~ROOT_POINTS points and each depth about
    4x more on a surface (radii halve per depth), so nodes keep a few thousand points. The deepest
    depth is the band of radius[K / tail]: it takes the rest of the ordering, at least
    1 - 1/tail of the points, never a thin tail. A deeper cut costs size, not levels worth
    having: LAZ codes each point from its predecessor, and a coarse depth is a sparse subsample
    of the scan (10-11 bytes a point on airborne data against 5.6 for the dense rest, 5.4 for
    the source in scanner order: tools/bench_export.py), so the bytes grow with the share of
    points in the coarse depths (the 4x4 survey: 1.33 x its source LAZ with tail 4, 1.10 x with
    tail 8). 3D Tiles take the same depths: fewer, bigger tiles that CesiumJS loads in fewer
    frames (1M points: 41 tiles instead of 169)."""
    k = radius.size
    r_root = float(radius[min(ROOT_POINTS, k - 1)])
    spacing = 2.0 * r_root if math.isfinite(r_root) and r_root > 0 else width / ROOT_CELLS
    r_tail = float(radius[k // tail])
    if not (math.isfinite(r_tail) and r_tail > 0):
        return spacing, 0
    return spacing, int(min(MAX_DEPTH, max(0, math.floor(math.log2(spacing / r_tail)))))


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


def morton_codes(ijk: np.ndarray) -> np.ndarray:
    """(N,) uint64 Morton (Z-order) codes of (N, 3) non-negative voxel coordinates < 2**21."""
    code = np.zeros(ijk.shape[0], dtype=np.uint64)
    for axis in range(3):
        v = ijk[:, axis].astype(np.uint64) & np.uint64(0x1FFFFF)
        for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                            (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        code |= v << np.uint64(axis)
    return code


def node_order(depth: np.ndarray, codes: np.ndarray, stored: np.ndarray, lo: np.ndarray,
               width: float, gps_time: np.ndarray | None) -> np.ndarray:
    """The file order of the points: by depth, then node (breadth-first), then inside a node by
    GPS time where the points have one that varies (the order a scanner recorded them, which
    LAZ's delta coding compresses best), else by Morton code of their position. The order
    inside a node carries nothing: the depths hold the levels."""
    if gps_time is not None and np.ptp(gps_time) > 0:
        inner = np.asarray(gps_time, dtype=np.float64)
        tie = morton_codes(_voxels(stored, lo, width, MAX_DEPTH))
        return np.lexsort((tie, inner, codes, depth))
    return np.lexsort((morton_codes(_voxels(stored, lo, width, MAX_DEPTH)), codes, depth))


def octree_cube(stored: np.ndarray, scales: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(lo, width, margin): the octree cube [lo, lo + width]^3 around the stored coordinates,
    padded by ``margin`` (one quantisation step) on every side so that no point lies on a face
    of the cube. The header's bounds are written as [lo, pmax + margin]: copclib takes node boxes
    from the header's minimum and its longest side (COPC 1.0 readers from the info VLR's centre
    and half size), and both then give the same cube, so ValidateSpatialBounds holds."""
    pmin, pmax = stored.min(axis=0), stored.max(axis=0)
    margin = float(np.max(scales))
    width = float((pmax - pmin).max()) + 2.0 * margin
    return pmin - margin, width, margin


@dataclass(frozen=True)
class _Tree:
    """The octree of a level: the padded cube, the spacing, each point's depth band, depth and
    voxel code, and the nodes (file order of the points, node i = ``order[starts[i]:ends[i]]``
    with voxel key ``keys[i]`` = (depth, x, y, z))."""

    lo: np.ndarray
    width: float
    margin: float
    spacing: float
    band: np.ndarray
    depth: np.ndarray
    order: np.ndarray
    starts: np.ndarray
    ends: np.ndarray
    keys: np.ndarray


def build_tree(stored: np.ndarray, scales: np.ndarray, radius: np.ndarray,
               gps: np.ndarray | None) -> _Tree:
    """The octree of the stored (quantised) coordinates: a padded cube, spacing s0 at the root,
    depths from the insertion radii (module docstring), nodes breadth-first."""
    lo, width, margin = octree_cube(stored, scales)
    spacing, max_depth = octree_spacing(radius, width)
    band = depth_bands(radius, spacing, max_depth)
    depth, codes = assign_depths(stored, band, lo, width)
    order = node_order(depth, codes, stored, lo, width, gps)
    d_sorted, c_sorted = depth[order], codes[order]
    cut = np.flatnonzero((np.diff(d_sorted) != 0) | (np.diff(c_sorted) != 0)) + 1
    starts = np.concatenate([[0], cut]).astype(np.int64)
    ends = np.concatenate([cut, [order.size]]).astype(np.int64)
    c0 = c_sorted[starts]
    keys = np.column_stack([d_sorted[starts], c0 >> 42, (c0 >> 21) & 0x1FFFFF, c0 & 0x1FFFFF])
    return _Tree(lo, width, margin, spacing, band, depth, order, starts, ends, keys)


def _layout(pts: np.ndarray, attributes: dict[str, np.ndarray], meta: dict[str, Any],
            ours: dict[str, np.ndarray], scans: list[str] | None) -> Any:
    """The LAS layout of the points and attributes, with ``ours`` (``rank`` or ``sublevel``)
    as extra bytes."""
    from ..io.las import las_layout

    attrs = dict(attributes)
    for key, values in ours.items():
        if key in attributes:
            raise InputError(f"attribute {key!r} would clash with the {key} the COPC file records; "
                             "rename it")
        attrs[key] = values
    layout = las_layout(pts, attrs, meta, point_format=copc_point_format(meta, set(attributes)),
                        version="1.4")
    described = {"scan_id": "scan index: names in EVLR" if scans else None,
                 "rank": "lodbuilder farthest-point rank",
                 "sublevel": "lodbuilder sub-level of depth"}
    for ed in layout.extra_dims:
        if described.get(ed.name) and (ed.name in ours or ed.name == "scan_id"):
            ed.description = str(described[ed.name])
    return layout


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
    rank_radius: str | None = None,
    rank: np.ndarray | None = None,
    filtered: str | None = None,
    bounds: np.ndarray | None = None,
    scans: list[str] | None = None,
) -> CopcFile:
    """Write a level (points in farthest-point order, their insertion radii, the level's covering
    bound ``rho``) as a COPC 1.0 file whose octree depths are its levels (module docstring),
    atomically. ``attributes``: LAS fields or extra bytes (:func:`lodbuilder.io.las.las_layout`
    with ``metadata``, the scan's format metadata; what the mapping changed is in ``notes`` and
    logged as lodbuilder.io warnings). ``rank_radius="level"``: also each point's ``sublevel``
    (a uint8 extra byte) and, per depth and sub-level, the prefix and its covering radius (an
    EVLR, :func:`read_sublevels`): up to SUBLEVELS levels a depth, about 1 byte a point.
    ``rank_radius="exact"``: each point's ``rank`` (extra bytes) and the insertion radius by
    rank (an EVLR, :func:`read_radius_table`): the exact ordering, 2.9-3.8 bytes a point.

    ``rank``: each point's rank in the scan's ordering (default 0..K-1). ``filtered``: what
    filter removed points from the level (they are a subsequence of it), with ``bounds`` the
    covering bound of each prefix (:func:`lodbuilder.filters.prefix_bounds`; default
    ``radius``). ``scans``: the scan names that attribute ``scan_id`` indexes (in the EVLR)."""
    check_copc_dependencies()
    from ..io._files import atomic_output
    from ..io.api import log_notes
    from ._copc_file import write_copc_file

    mode = check_rank_radius(rank_radius)
    out, pts, radius = check_level_output(out, "COPC output", (".copc.laz",), points, radius)
    k = pts.shape[0]
    meta = dict(metadata or {})
    bounds = radius if bounds is None else np.asarray(bounds)
    order_rank, ours = _our_dims(mode, rank, k)
    layout = _layout(pts, attributes, meta, ours, scans)
    las = layout.las_data(pts)
    stored, gps = _stored(las)
    tree = build_tree(stored, layout.scales, radius, gps)
    octree = _header(las, stored, tree)
    levels = _levels(bounds, tree.band, tree.depth, rho, tree.spacing)
    table = _fill_sublevels(las, tree, bounds, rho) if mode == "level" else None
    doc = _doc(name, k, int(n_total or k), tree.spacing, levels, mode, filtered, scans)
    evlrs = _evlrs(doc, order_rank, radius, table)
    gps_range = (float(gps.min()), float(gps.max())) if gps is not None else (0.0, 0.0)
    with atomic_output(out) as tmp:
        with open(tmp, "wb") as f:
            write_copc_file(f, las.header, las.points.array[tree.order], tree.keys, tree.starts,
                            tree.ends, octree, gps_range, layout.crs_wkt, evlrs)
        n_bytes = tmp.stat().st_size
    log_notes(out, layout.notes)
    return CopcFile(path=out, n_points=k, n_total=int(n_total or k), rho=float(rho),
                    n_bytes=n_bytes, depths=int(tree.depth.max()) + 1, nodes=len(tree.starts),
                    spacing=tree.spacing, levels=levels, notes=list(layout.notes))


def _our_dims(mode: str | None, rank: np.ndarray | None,
              k: int) -> tuple[np.ndarray | None, dict[str, np.ndarray]]:
    """(rank of each point or None, our extra dimensions): ``rank`` for the exact mode,
    ``sublevel`` (zeros until the depths are known) for the level mode."""
    if mode == "level":
        return None, {"sublevel": np.zeros(k, dtype=np.uint8)}
    if mode != "exact":
        return None, {}
    order_rank = np.arange(k) if rank is None else np.asarray(rank)
    return order_rank, {"rank": order_rank.astype(np.uint32 if order_rank.max() < 2**32 else np.uint64)}


def _fill_sublevels(las: Any, tree: _Tree, bounds: np.ndarray, rho: float) -> np.ndarray:
    """Set each point's ``sublevel``; return the sub-level table (:func:`sublevels`)."""
    sub, table = sublevels(tree.band, tree.depth, bounds, rho)
    las["sublevel"] = sub
    return table


def _stored(las: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """(the quantised coordinates, the GPS times or None) of a LasData."""
    stored = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    gps = (np.asarray(las.gps_time, dtype=np.float64)
           if "gps_time" in las.point_format.dimension_names else None)
    return stored, gps


def _header(las: Any, stored: np.ndarray, tree: _Tree) -> Any:
    """Set the LAS header's point counts and bounds (the padded cube's minimum, the maximum
    point plus the margin: see :func:`octree_cube`); return the COPC info VLR's octree."""
    from ._copc_file import Octree

    header = las.header
    header.point_count = stored.shape[0]
    header.mins = tree.lo
    header.maxs = stored.max(axis=0) + tree.margin
    returns = np.bincount(np.asarray(las.return_number, dtype=np.int64), minlength=16)
    header.number_of_points_by_return = returns[1:16]
    centre = tree.lo + tree.width / 2.0
    return Octree((float(centre[0]), float(centre[1]), float(centre[2])), tree.width / 2.0,
                  tree.spacing)


def _evlrs(doc: dict[str, Any], rank: np.ndarray | None, radius: np.ndarray,
           table: np.ndarray | None) -> list[Any]:
    """Our EVLRs: the levels (JSON), with ``rank`` the radius by rank, with ``table`` the
    sub-levels."""
    import laspy

    evlrs = [laspy.VLR(VLR_USER_ID, VLR_RECORD_ID, VLR_DESCRIPTION,
                       json.dumps(doc, allow_nan=False).encode("utf-8"))]
    if rank is not None:
        evlrs.append(laspy.VLR(VLR_USER_ID, RADIUS_RECORD_ID, RADIUS_DESCRIPTION,
                               radius_table(rank, radius)[1]))
    if table is not None:
        evlrs.append(laspy.VLR(VLR_USER_ID, SUBLEVEL_RECORD_ID, SUBLEVEL_DESCRIPTION,
                               sublevel_payload(table)))
    return evlrs


def _doc(name: str, k: int, n_total: int, spacing: float, levels: list[dict[str, Any]],
         mode: str | None, filtered: str | None, scans: list[str] | None) -> dict[str, Any]:
    """The JSON of our EVLR (record VLR_RECORD_ID)."""
    ranked = mode == "exact"
    doc: dict[str, Any] = {
        "format": "lodbuilder farthest-point levels",
        "version": 2,
        "scan": name,
        "n_points": k,
        "n_points_scan": n_total,
        "spacing": spacing,
        "rule": "depth d holds the points of insertion radius in (spacing/2^(d+1), spacing/2^d]; "
        "depths <= d hold the prefix of fps_prefix points of the farthest-point order (plus "
        "'promoted' points that keep the octree connected) and cover the scan within rho",
        "extra_bytes": ({"rank": "position in the farthest-point order"} if ranked else
                        {"sublevel": "sub-level of the point's depth"} if mode == "level" else {}),
        "levels": levels,
    }
    if mode == "level":
        doc["sublevels"] = {
            "user_id": VLR_USER_ID, "record_id": SUBLEVEL_RECORD_ID,
            "rule": "the points of depths < D and those of depth D with sublevel <= s are the "
            "prefix of 'prefix' points of the farthest-point order (plus the promoted points of "
            "depths <= D: 'points' in all) and cover the scan within 'rho'",
            "encoding": "zlib of little-endian columns, one row per (depth, sublevel) in order: "
            "depth uint8, sublevel uint8, prefix uint64, points uint64, rho float64",
        }
    if ranked:
        doc["radius_by_rank"] = {
            "user_id": VLR_USER_ID, "record_id": RADIUS_RECORD_ID,
            "encoding": "zlib of little-endian int32 differences of the float32 bit patterns of "
            "the insertion radius of ranks 0, 1, ... (rounded up to float32; NaN: rank not in "
            "the file); radius = cumsum(differences) as uint32 viewed as float32",
        }
    if filtered is not None:
        doc["filter"] = filtered
    if scans:
        doc["scans"] = list(scans)
    return doc


def _levels(
    bounds: np.ndarray, band: np.ndarray, depth: np.ndarray, rho: float, spacing: float
) -> list[dict[str, Any]]:
    """Per depth D: points at depths <= D, the farthest-point prefix among them, the points
    moved up to keep the octree connected, and the covering radius of the prefix (``bounds[p]``
    for a prefix of p points: the next insertion radius, see :func:`write_copc`)."""
    radius = bounds
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


def export_copc(scan: Any, out: str | os.PathLike, size: int, *, rank_radius: str | None = None,
                flt: Any = None) -> CopcFile:
    """Write the level of ``size`` points of an archive scan (a ScanView) as COPC, with every
    attribute, its importance maps (extra bytes ``importance_<name>``), and with
    ``rank_radius`` the rank and insertion radius of every point; with ``flt`` (a
    :class:`lodbuilder.filters.LevelFilter`) only the level's points that pass it (the depths
    are then the filtered prefixes, their rho still the level's before the filter)."""
    from ..filters import prefix_bounds
    from . import joint_member_names as joint_members

    level = scan.level(size=size)
    if flt is not None:
        level = flt.apply(level)
    attrs = dict(level.attributes)
    for m in scan.importance_names:
        key = f"importance_{m}"[:32]
        if key not in attrs:
            attrs[key] = np.asarray(scan.importance(m)[:size], dtype=np.float32)[level.rank]
    return write_copc(
        out,
        level.points,
        attrs,
        level.radius,
        level.rho,
        metadata=scan.format_metadata,  # (the CRS included: ScanView.crs is read from it)
        n_total=scan.n_ordered,
        name=scan.name,
        rank_radius=rank_radius,
        rank=level.rank,
        filtered=flt.describe() if flt is not None else None,
        bounds=prefix_bounds(scan.radius, level.rank) if flt is not None else None,
        scans=joint_members(scan) if "scan_id" in level.attributes else None,
    )
