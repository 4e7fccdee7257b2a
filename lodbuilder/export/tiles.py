"""A level as 3D Tiles 1.1 (Cesium, and viewers that load 3D Tiles): ``lodbuilder export A.h5 -o
DIR/tileset.json``.

A tile's ``geometricError`` is the error of drawing it and not its children; for farthest-point
levels that is the covering radius the archive stores, exactly. The tiles are the octree nodes of
:mod:`lodbuilder.export.copc` (the same depths: depth d holds the insertion radii of its band,
a few points moved up where a parent voxel would be empty), refinement ADD (the levels nest: a
child adds points to its parent's), and a tile of depth d has geometricError ``rho_d``, the
covering radius of the points of depths <= d (the deepest depth: the level's own rho, 0 for the
whole scan). The tileset's own geometricError (nothing drawn) is the diagonal of the points'
box. Each tile's points are one binary glTF (``.glb``: a POINTS primitive, float32 POSITION
relative to the tileset's centre, COLOR_0 as RGBA bytes: the scan's RGB, or its elevation on
viridis), in a folder ``<stem>_tiles/`` next to the tileset JSON.

Placement: the root's ``transform`` is the east-north-up frame at the centre of the points, whose
longitude and latitude come from the archive's CRS (pyproj) with coordinates scaled to metres; a
scan without a CRS (or without pyproj) is placed at longitude 0, latitude 0 with its coordinates
read as metres (``asset.extras`` says which). Grid north of a projected CRS is taken as true
north (the meridian convergence, under a degree over most of a UTM zone, is not applied).

What py3dtiles (PyPI) does and what we write: py3dtiles converts LAS/XYZ files to a tileset of
``.pnts`` tiles (3D Tiles 1.0) with its own octree subsampling and geometric errors; it does not
know our levels or their covering radii, so the tileset JSON, the tiles and the glTF encoding
are written here with the standard library and numpy (no dependency).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from . import check_level_output

#: the folder of the tiles is marked with this file, so a later export may replace it
MARKER = ".lodbuilder-tiles"
_WGS84_A, _WGS84_F = 6378137.0, 1 / 298.257223563


@dataclass(frozen=True)
class Tileset:
    """What :func:`write_tiles` wrote."""

    path: Path
    n_points: int
    n_total: int
    rho: float
    tiles: int
    depths: int
    n_bytes: int
    placed: str
    geometric_errors: list[float]


def glb_points(positions: np.ndarray, rgba: np.ndarray) -> bytes:
    """A binary glTF 2.0 of one POINTS primitive: (n, 3) float32 positions (glTF's y-up axes)
    and (n, 4) uint8 colours."""
    pos = np.ascontiguousarray(positions, dtype="<f4")
    col = np.ascontiguousarray(rgba, dtype=np.uint8)
    n = pos.shape[0]
    body = pos.tobytes() + col.tobytes()  # 12 n + 4 n bytes: already 4-aligned
    doc = {
        "asset": {"version": "2.0", "generator": "lodbuilder"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "COLOR_0": 1}, "mode": 0}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3",
             "min": pos.min(axis=0).tolist(), "max": pos.max(axis=0).tolist()},
            {"bufferView": 1, "componentType": 5121, "normalized": True, "count": n, "type": "VEC4"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 12 * n, "target": 34962},
            {"buffer": 0, "byteOffset": 12 * n, "byteLength": 4 * n, "target": 34962},
        ],
        "buffers": [{"byteLength": len(body)}],
    }
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(body)
    return b"".join([
        struct.pack("<4sII", b"glTF", 2, total),
        struct.pack("<I4s", len(js), b"JSON"), js,
        struct.pack("<I4s", len(body), b"BIN\0"), body,
    ])


def enu_frame(crs: str | None, centre: np.ndarray) -> tuple[list[float], float, str]:
    """(column-major 4x4 east-north-up -> ECEF matrix, metres per coordinate unit, how it was
    placed) for a point ``centre`` in ``crs``."""
    lon = lat = 0.0
    height = 0.0
    factor = 1.0
    placed = "no CRS: placed at longitude 0, latitude 0, coordinates read as metres"
    if crs:
        try:
            import pyproj

            src = pyproj.CRS.from_wkt(crs)
            geo = pyproj.Transformer.from_crs(src, src.geodetic_crs or "EPSG:4326", always_xy=True)
            lon, lat = geo.transform(float(centre[0]), float(centre[1]))[:2]
            unit = src.axis_info[0].unit_conversion_factor if src.axis_info else 1.0
            factor = float(unit or 1.0)
            height = float(centre[2]) * factor
            placed = f"CRS {src.name}: centre at longitude {lon:.6f}, latitude {lat:.6f}"
            if not (math.isfinite(lon) and math.isfinite(lat)):
                raise ValueError("not finite")
        except Exception:  # no pyproj, or a CRS it cannot place: say so, place at 0, 0
            lon = lat = height = 0.0
            factor = 1.0
            placed = "CRS not placeable here (pyproj missing or failed): placed at longitude 0, latitude 0"
    lo, la = math.radians(lon), math.radians(lat)
    e2 = _WGS84_F * (2 - _WGS84_F)
    nn = _WGS84_A / math.sqrt(1 - e2 * math.sin(la) ** 2)
    origin = [(nn + height) * math.cos(la) * math.cos(lo), (nn + height) * math.cos(la) * math.sin(lo),
              (nn * (1 - e2) + height) * math.sin(la)]
    east = [-math.sin(lo), math.cos(lo), 0.0]
    north = [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)]
    up = [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)]
    return [*east, 0.0, *north, 0.0, *up, 0.0, *origin, 1.0], factor, placed


def _colours(local: np.ndarray, rgb: np.ndarray | None) -> np.ndarray:
    """(n, 4) uint8: the scan's colours, or its elevation (local z) on viridis."""
    from ..viewer.data import _to_uint8_rgb, colormap

    if rgb is not None:
        c = _to_uint8_rgb(np.asarray(rgb)).reshape(-1, 3)
    else:
        z = local[:, 2]
        span = float(np.ptp(z)) or 1.0
        c = colormap((z - z.min()) / span)
    return np.column_stack([c, np.full(c.shape[0], 255, dtype=np.uint8)])


def write_tiles(
    out: str | os.PathLike,
    points: np.ndarray,
    radius: np.ndarray,
    rho: float,
    *,
    rgb: np.ndarray | None = None,
    bounds: np.ndarray | None = None,
    n_total: int | None = None,
    crs: str | None = None,
    name: str = "scan",
    note: str = "",
) -> Tileset:
    """Write a level (points in farthest-point order, their insertion radii, the level's covering
    bound ``rho``) as a 3D Tiles 1.1 tileset (module docstring). ``bounds``: the covering bound
    of each prefix (default ``radius``; a filtered level's from
    :func:`lodbuilder.filters.prefix_bounds`). The tiles' folder is written first, then the
    tileset JSON; a previous export's folder is replaced, any other folder of that name refused."""
    from ..io._files import atomic_output

    out, pts, radius = check_level_output(out, "3D Tiles output", (".json",), points, radius)
    k = pts.shape[0]
    folder = out.parent / f"{out.name[:-5]}_tiles"
    if folder.exists() and not (folder / MARKER).is_file():
        raise InputError(f"{folder} exists and is not a lodbuilder tiles folder; move it or choose "
                         "another -o name")
    pmin, pmax = pts.min(axis=0), pts.max(axis=0)
    centre = (pmin + pmax) / 2.0
    transform, factor, placed = enu_frame(crs, centre)
    local = (pts - centre) * factor
    b = None if bounds is None else np.asarray(bounds, dtype=np.float64) * factor
    octree = _octree(local, radius * factor, b, rho * factor)
    diagonal = float(np.linalg.norm(local.max(axis=0) - local.min(axis=0))) or 1.0
    # (a prefix whose next radius is a seed's inf covers nothing for sure: the whole diagonal)
    errors = [diagonal if lv["rho"] is None else float(lv["rho"]) for lv in octree["levels"]]
    tmp_dir = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=out.parent))
    try:
        tiles = _write_tiles(tmp_dir, folder.name, local, _colours(local, rgb), octree, errors)
        (tmp_dir / MARKER).write_text("written by lodbuilder export; replaced by the next export\n")
        root = {**_tree(tiles), "refine": "ADD", "transform": transform}
        extras = {"scan": name, "points": k, "points_scan": int(n_total or k),
                  "placement": placed, "metres_per_unit": factor, "filter": note,
                  "geometricError": "covering radius of the points of depths <= the tile's "
                  "depth (metres)"}
        doc = {"asset": {"version": "1.1", "generator": "lodbuilder", "extras": extras},
               "geometricError": max(diagonal, errors[0]), "root": root}
        if folder.exists():
            shutil.rmtree(folder)
        os.replace(tmp_dir, folder)
    except BaseException:
        shutil.rmtree(tmp_dir, ignore_errors=True)
        raise
    with atomic_output(out) as tmp:
        tmp.write_text(json.dumps(doc, indent=1, allow_nan=False), encoding="utf-8")
    n_bytes = out.stat().st_size + sum(f.stat().st_size for f in folder.iterdir())
    return Tileset(out, k, int(n_total or k), float(rho), len(tiles), len(errors), n_bytes,
                   placed, errors)


def _octree(local: np.ndarray, r_local: np.ndarray, bounds: np.ndarray | None,
            rho: float) -> dict[str, Any]:
    """The COPC octree of the points (metres, centred): the cube, each point's depth and voxel
    code, the levels (:func:`lodbuilder.export.copc._levels`)."""
    from .copc import _levels, assign_depths, depth_bands, octree_spacing

    half = float(np.abs(local).max()) * (1 + 1e-9) + 1e-9
    lo, width = np.full(3, -half), 2.0 * half
    spacing, max_depth = octree_spacing(r_local, width)
    band = depth_bands(r_local, spacing, max_depth)
    depth, codes = assign_depths(local, band, lo, width)
    levels = _levels(r_local if bounds is None else bounds, band, depth, rho, spacing)
    return {"lo": lo, "width": width, "depth": depth, "codes": codes, "levels": levels}


def _write_tiles(folder: Path, name: str, local: np.ndarray, colours: np.ndarray,
                 octree: dict[str, Any], errors: list[float]) -> dict[tuple[int, int], dict[str, Any]]:
    """Write one .glb a node into ``folder``; return each node's tile (without children)."""
    depth, codes, lo, width = octree["depth"], octree["codes"], octree["lo"], octree["width"]
    order = np.lexsort((np.arange(depth.size), codes, depth))
    d_s, c_s = depth[order], codes[order]
    cut = np.flatnonzero((np.diff(d_s) != 0) | (np.diff(c_s) != 0)) + 1
    tiles: dict[tuple[int, int], dict[str, Any]] = {}
    for s, e in zip(np.concatenate([[0], cut]), np.concatenate([cut, [depth.size]]), strict=True):
        d, c = int(d_s[s]), int(c_s[s])
        ijk = np.array([c >> 42, (c >> 21) & 0x1FFFFF, c & 0x1FFFFF], dtype=np.float64)
        w = width / 2**d
        mid = lo + (ijk + 0.5) * w
        sel = order[s:e]
        p = local[sel]
        uri = f"{d}-{c >> 42}-{(c >> 21) & 0x1FFFFF}-{c & 0x1FFFFF}.glb"
        (folder / uri).write_bytes(glb_points(np.column_stack([p[:, 0], p[:, 2], -p[:, 1]]),
                                              colours[sel]))
        tiles[(d, c)] = {
            "boundingVolume": {"box": [*mid.tolist(), w / 2, 0, 0, 0, w / 2, 0, 0, 0, w / 2]},
            "geometricError": errors[d],
            "content": {"uri": f"{name}/{uri}"},
        }
    return tiles


def _tree(tiles: dict[tuple[int, int], dict[str, Any]]) -> dict[str, Any]:
    """Link each tile to its parent (voxel code >> 1 a coordinate, one depth up): the root."""
    for (d, c) in sorted(tiles, reverse=True):
        if d == 0:
            continue
        parent = ((((c >> 42) >> 1) << 42) | ((((c >> 21) & 0x1FFFFF) >> 1) << 21)
                  | ((c & 0x1FFFFF) >> 1))
        tiles[(d - 1, parent)].setdefault("children", []).insert(0, tiles[(d, c)])
    return tiles[(0, 0)]


def export_tiles(scan: Any, out: str | os.PathLike, size: int, *, flt: Any = None) -> Tileset:
    """Write the level of ``size`` points of an archive scan (a ScanView) as 3D Tiles, coloured
    by its RGB (or elevation); with ``flt`` only the level's points that pass it."""
    names = [c for c in ("red", "green", "blue") if c in scan.attribute_names]
    wanted = (names if len(names) == 3 else []) + (flt.fields() if flt is not None else [])
    level = scan.level(size=size, attributes=sorted(set(wanted)) if wanted else False)
    bounds = None
    if flt is not None:
        from ..filters import prefix_bounds

        level = flt.apply(level)
        bounds = prefix_bounds(scan.radius, level.rank)
    rgb = np.column_stack([level.attributes[c] for c in names]) if len(names) == 3 else None
    return write_tiles(out, level.points, level.radius, level.rho, rgb=rgb, bounds=bounds,
                       n_total=scan.n_ordered, crs=scan.crs, name=scan.name,
                       note=flt.describe() if flt is not None else "")
