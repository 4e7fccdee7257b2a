"""Survey filters: keep the points of a level by classification, return number, attribute
ranges, a box or a polygon (in the archive's CRS).

A :class:`LevelFilter` is one frozen value, parsed once (:func:`parse_polygon`,
``lodbuilder.cli.level_options.filter_from_args``) and applied to a level's arrays
(:meth:`LevelFilter.mask`, :meth:`LevelFilter.apply`).

What a filtered level promises. The level before the filter covers the scan within ``rho``:
every scan point is within rho of a level point. The filter keeps the level points that pass it.
* A box or polygon alone (a region R): every scan point of R at least rho from R's edge is
  within rho of a kept point (its nearest level point is within rho, hence inside R).
* Classification, returns or attribute ranges: a scan point that passes the filter is within
  rho of a level point, which need not pass it (a ground point covered by a roof point): the
  kept points then cover the filtered scan points only where points of the kept kind are the
  nearest. :meth:`LevelFilter.guarantee` says which of the two holds, in one line.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError

#: ASPRS standard classes (LAS 1.4 R15, point formats 6-10): code -> name
ASPRS_CLASSES: dict[int, str] = {
    0: "never classified", 1: "unassigned", 2: "ground", 3: "low vegetation",
    4: "medium vegetation", 5: "high vegetation", 6: "building", 7: "low point (noise)",
    8: "reserved", 9: "water", 10: "rail", 11: "road surface", 12: "reserved",
    13: "wire guard", 14: "wire conductor", 15: "transmission tower",
    16: "wire connector", 17: "bridge deck", 18: "high noise",
}

#: a polygon: its rings (outer first, then holes), each a tuple of (x, y) vertices
Polygon = tuple[tuple[tuple[float, float], ...], ...]
RETURN_WORDS = ("first", "last", "only")


@dataclass(frozen=True)
class LevelFilter:
    """Which points of a level to keep; every part given must hold (an empty filter keeps all).

    Attributes:
        classes: ASPRS classification codes to keep (attribute ``classification``).
        returns: return numbers (1, 2...) and/or ``"first"`` (return_number 1), ``"last"``
            (return_number == number_of_returns), ``"only"`` (number_of_returns 1).
        ranges: (attribute, low, high) triples, bounds included (-inf / inf for an open side).
        box: (xmin, ymin, xmax, ymax) or (xmin, ymin, zmin, xmax, ymax, zmax), bounds included.
        polygons: polygons in x, y (a point inside any of them is kept; holes excluded).
    """

    classes: tuple[int, ...] | None = None
    returns: tuple[int | str, ...] | None = None
    ranges: tuple[tuple[str, float, float], ...] = ()
    box: tuple[float, ...] | None = None
    polygons: tuple[Polygon, ...] | None = None

    def __post_init__(self) -> None:
        if self.box is not None:
            b = tuple(float(v) for v in self.box)
            if len(b) not in (4, 6) or not all(math.isfinite(v) for v in b):
                raise InputError(f"a filter box needs 4 or 6 finite numbers, got {list(self.box)}")
            half = len(b) // 2
            if any(b[i] > b[i + half] for i in range(half)):
                raise InputError(f"a filter box has a minimum above its maximum: {list(b)}")
            object.__setattr__(self, "box", b)
        for name, lo, hi in self.ranges:
            if not lo <= hi:
                raise InputError(f"filter range of {name!r}: {lo:g} is above {hi:g}")
        for r in self.returns or ():
            if isinstance(r, str) and r not in RETURN_WORDS:
                raise InputError(f"return {r!r}: use numbers or {', '.join(RETURN_WORDS)}")

    @property
    def empty(self) -> bool:
        return not (self.classes or self.returns or self.ranges or self.box or self.polygons)

    @property
    def spatial_only(self) -> bool:
        """Only a box and/or polygons: the region guarantee of the module docstring holds."""
        return not (self.classes or self.returns or self.ranges)

    def fields(self) -> list[str]:
        """The attributes the filter reads."""
        out = ["classification"] if self.classes else []
        if self.returns:
            out.append("return_number")
            if any(r in ("last", "only") for r in self.returns):
                out.append("number_of_returns")
        out += [name for name, _, _ in self.ranges if name not in out]
        return out

    def describe(self) -> str:
        """One line: the parts of the filter."""
        parts = []
        if self.classes:
            parts.append("class " + ", ".join(str(c) for c in self.classes))
        if self.returns:
            parts.append("return " + ", ".join(str(r) for r in self.returns))
        for name, lo, hi in self.ranges:
            parts.append(f"{name} in [{lo:g}, {hi:g}]")
        if self.box:
            half = len(self.box) // 2
            axes = "xyz"[:half]
            parts.append("box " + " ".join(f"{a} {self.box[i]:g}..{self.box[i + half]:g}"
                                           for i, a in enumerate(axes)))
        if self.polygons:
            n = sum(len(ring) for poly in self.polygons for ring in poly)
            parts.append(f"polygon ({len(self.polygons)} part(s), {n} vertices)")
        return "; ".join(parts) or "none"

    def guarantee(self, rho: float | None) -> str:
        """What the kept points promise, in one line (see the module docstring); ``rho`` None:
        for any level (the viewer's slider)."""
        r = "the level's rho" if rho is None else f"{rho:.6g}"
        if self.spatial_only:
            return (f"inside the region, every scan point at least {r} from its edge is within "
                    f"{r} of a kept point")
        return (f"every scan point is within {r} of a point of the level before the filter; the "
                "filter may have removed that point")

    def mask(self, points: np.ndarray, attributes: dict[str, np.ndarray], scan: str = "") -> np.ndarray:
        """(K,) bool: which of ``points`` (with their ``attributes``) pass the filter."""
        pts = np.asarray(points, dtype=np.float64)
        keep = np.ones(pts.shape[0], dtype=bool)
        for name in self.fields():
            if name not in attributes:
                have = ", ".join(sorted(attributes)) or "none"
                raise InputError(f"the filter needs attribute {name!r}, which scan {scan!r} does "
                                 f"not have (it has: {have})")
        if self.classes:
            keep &= np.isin(np.asarray(attributes["classification"]), self.classes)
        if self.returns:
            rn = np.asarray(attributes["return_number"])
            one = np.zeros(keep.shape, dtype=bool)
            for r in self.returns:
                if r == "first":
                    one |= rn == 1
                elif r == "last":
                    one |= rn == np.asarray(attributes["number_of_returns"])
                elif r == "only":
                    one |= np.asarray(attributes["number_of_returns"]) == 1
                else:
                    one |= rn == int(r)
            keep &= one
        for name, lo, hi in self.ranges:
            a = np.asarray(attributes[name])
            if a.ndim != 1:
                raise InputError(f"filter range of {name!r}: it has {a.shape[1]} values per point; "
                                 "a range needs one")
            keep &= (a >= lo) & (a <= hi)
        if self.box:
            half = len(self.box) // 2
            lo_b, hi_b = np.array(self.box[:half]), np.array(self.box[half:])
            keep &= np.all((pts[:, :half] >= lo_b) & (pts[:, :half] <= hi_b), axis=1)
        if self.polygons:
            inside = np.zeros(keep.shape, dtype=bool)
            for poly in self.polygons:
                inside |= in_polygon(pts[:, 0], pts[:, 1], poly)
            keep &= inside
        return keep

    def apply(self, level: Any) -> Any:
        """The level (a :class:`lodbuilder.levels.Level`) reduced to the points that pass; its
        ``region`` records the filter."""
        keep = self.mask(level.points, level.attributes, level.scan)
        idx = np.flatnonzero(keep)
        return replace(
            level,
            points=level.points[idx],
            attributes={k: np.asarray(v)[idx] for k, v in level.attributes.items()},
            source_index=level.source_index[idx],
            radius=level.radius[idx],
            rank=level.rank[idx],
            size=int(idx.size),
            region=dict(level.region, filter=self.describe(), level_size=level.size),
        )


def prefix_bounds(scan_radius: Any, rank: np.ndarray) -> np.ndarray:
    """(K,) covering bounds of the prefixes of a filtered level: ``b[k]`` for k >= 1 bounds the
    first k kept points' level before the filter, i.e. the scan's prefix up to the k-th kept
    point (rank ``rank[k-1]``), whose covering radius is ``scan_radius[rank[k-1] + 1]``
    (``b[0]`` = inf). The kept points' own ``radius[k]`` would understate it: the points the
    filter removed between them were part of that level."""
    rank = np.asarray(rank, dtype=np.int64)
    b = np.full(rank.size, np.inf)
    if rank.size > 1:
        hi = int(rank[-2]) + 2
        full = np.asarray(scan_radius[:hi], dtype=np.float64)
        nxt = rank[:-1] + 1
        b[1:] = np.where(nxt < full.size, full[np.minimum(nxt, full.size - 1)], 0.0)
    return b


def in_polygon(x: np.ndarray, y: np.ndarray, polygon: Polygon) -> np.ndarray:
    """(N,) bool: points strictly inside ``polygon`` by the even-odd rule over all its rings (so
    holes are out), one vectorised pass per edge."""
    inside = np.zeros(np.shape(x), dtype=bool)
    for ring in polygon:
        v = np.asarray(ring, dtype=np.float64)
        for (x0, y0), (x1, y1) in zip(v, np.roll(v, -1, axis=0), strict=True):
            if y0 == y1:
                continue
            crosses = (y0 > y) != (y1 > y)
            xc = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
            inside ^= crosses & (x < xc)
    return inside


# -- parsing ------------------------------------------------------------------------------------


def parse_classes(text: str) -> tuple[int, ...]:
    """Class codes from ``"2,6"`` or ASPRS names (``"ground,building"``, spaces as ``_``)."""
    by_name = {name.replace(" (noise)", "").replace(" ", "_"): code for code, name in ASPRS_CLASSES.items()
               if name != "reserved"}
    by_name.update(noise=7, low_noise=7, high_noise=18, vegetation=-1)
    out: list[int] = []
    for part in text.replace(" ", "").split(","):
        if not part:
            continue
        if re.fullmatch(r"\d+", part):
            out.append(int(part))
        elif part.lower() == "vegetation":
            out += [3, 4, 5]
        elif part.lower() in by_name:
            out.append(by_name[part.lower()])
        else:
            raise InputError(f"--class {text!r}: {part!r} is neither a code nor an ASPRS class "
                             f"name ({', '.join(sorted(k for k in by_name if k != 'vegetation'))}, "
                             "vegetation)")
    if not out:
        raise InputError(f"--class {text!r}: give codes or names, e.g. --class 2,6 or --class ground")
    return tuple(sorted(set(out)))


def parse_returns(text: str) -> tuple[int | str, ...]:
    """Returns from ``"1,2"``, ``"first"``, ``"last"``, ``"only"`` or a mix."""
    out: list[int | str] = []
    for part in text.replace(" ", "").lower().split(","):
        if re.fullmatch(r"\d+", part) and int(part) >= 1:
            out.append(int(part))
        elif part in RETURN_WORDS:
            out.append(part)
        else:
            raise InputError(f"--return {text!r}: {part!r} is not a return number (1, 2...) or "
                             f"one of {', '.join(RETURN_WORDS)}")
    return tuple(out)


def parse_range(text: str) -> tuple[str, float, float]:
    """``NAME=LO:HI`` (either bound may be left out: ``intensity=100:``)."""
    m = re.fullmatch(r"\s*([^=\s]+)\s*=\s*(\S*?)\s*:\s*(\S*)\s*", text)
    if m is None:
        raise InputError(f"--where {text!r}: write NAME=LO:HI (a bound may be left out: NAME=LO:)")
    name, lo, hi = m.groups()
    try:
        low = float(lo) if lo else -math.inf
        high = float(hi) if hi else math.inf
    except ValueError:
        raise InputError(f"--where {text!r}: {lo!r} or {hi!r} is not a number") from None
    if math.isnan(low) or math.isnan(high):
        raise InputError(f"--where {text!r}: bounds must be numbers, not nan")
    return name, low, high


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def parse_polygon(text: str) -> tuple[Polygon, ...]:
    """Polygons from WKT (``POLYGON``, ``MULTIPOLYGON``), GeoJSON (Polygon, MultiPolygon, a
    Feature or FeatureCollection of them) or a file holding either. Coordinates are taken in the
    archive's CRS as given (x, y; a z is ignored)."""
    src = text.strip()
    if not src.startswith(("{", "POLYGON", "MULTIPOLYGON", "polygon", "multipolygon")):
        path = Path(src)
        if not path.is_file():
            raise InputError(f"--polygon {text!r}: not WKT, GeoJSON or a readable file")
        src = path.read_text(encoding="utf-8").strip()
    if src.startswith("{"):
        try:
            doc = json.loads(src)
        except json.JSONDecodeError as exc:
            raise InputError(f"--polygon: GeoJSON not readable ({exc.msg} at {exc.pos})") from None
        polys = _geojson_polygons(doc)
    else:
        polys = _wkt_polygons(src)
    if not polys:
        raise InputError("--polygon: no polygon found (expect POLYGON/MULTIPOLYGON or GeoJSON)")
    for poly in polys:
        for ring in poly:
            if len(ring) < 3:
                raise InputError(f"--polygon: a ring has {len(ring)} vertices; a polygon needs 3 or more")
    return tuple(polys)


def _ring(coords: list[Any]) -> tuple[tuple[float, float], ...]:
    try:
        pts = [(float(c[0]), float(c[1])) for c in coords]
    except (TypeError, ValueError, IndexError):
        raise InputError("--polygon: a ring holds something other than coordinate pairs") from None
    if len(pts) > 1 and pts[0] == pts[-1]:
        pts = pts[:-1]
    return tuple(pts)


def _geojson_polygons(doc: Any) -> list[Polygon]:
    if not isinstance(doc, dict):
        return []
    kind = doc.get("type")
    if kind == "FeatureCollection":
        return [p for f in doc.get("features") or [] for p in _geojson_polygons(f)]
    if kind == "Feature":
        return _geojson_polygons(doc.get("geometry"))
    if kind == "Polygon":
        return [tuple(_ring(r) for r in doc.get("coordinates") or [])]
    if kind == "MultiPolygon":
        return [tuple(_ring(r) for r in poly) for poly in doc.get("coordinates") or []]
    raise InputError(f"--polygon: GeoJSON type {kind!r}; expect Polygon, MultiPolygon, Feature "
                     "or FeatureCollection")


def _wkt_polygons(text: str) -> list[Polygon]:
    body = text.strip()
    head = re.match(r"(?i)\s*(MULTIPOLYGON|POLYGON)\s*(Z|M|ZM)?\s*", body)
    if head is None:
        raise InputError(f"--polygon: WKT {text[:40]!r}: expect POLYGON or MULTIPOLYGON")
    rest = body[head.end():]
    if rest.count("(") != rest.count(")"):
        raise InputError("--polygon: WKT parentheses do not match")
    polys: list[Polygon] = []
    depth, rings, ring_text = 0, [], ""
    outer_depth = 2 if head.group(1).upper() == "MULTIPOLYGON" else 1
    for ch in rest:
        if ch == "(":
            depth += 1
            ring_text = ""
        elif ch == ")":
            if depth == outer_depth + 1 and ring_text.strip():
                rings.append(_wkt_ring(ring_text))
            if depth == outer_depth:
                polys.append(tuple(rings))
                rings = []
            depth -= 1
            ring_text = ""
        else:
            ring_text += ch
    return polys


def _wkt_ring(text: str) -> tuple[tuple[float, float], ...]:
    coords = []
    for pair in text.split(","):
        nums = re.findall(_NUM, pair)
        if len(nums) < 2:
            raise InputError(f"--polygon: WKT vertex {pair.strip()!r} is not 'X Y'")
        coords.append((float(nums[0]), float(nums[1])))
    return _ring(coords)
