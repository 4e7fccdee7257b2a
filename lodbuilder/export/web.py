"""A level as one self-contained web page: ``lodbuilder export ARCHIVE -o OUT.html``.

The page holds the points of a level in farthest-point order and draws them with WebGL (the
script and its data are in the one file: see :mod:`lodbuilder.export._page`). Its slider shows any
prefix of the level, i.e. any coarser level of the scan, with its covering radius rho; colours
follow RGB, the insertion radius, each importance map or the rank, with a legend.

Why a page of our own rather than PyVista's ``export_html`` (trame + vtk.js): for 1M points it is
about 15 MB against 24.6 MB, needs no trame packages, opens with the coarse points drawn while the
rest loads, and its Content-Security-Policy (``default-src 'none'``) forbids the browser any
request, so it is offline by construction (see tools/bench_export.py for the figures).

Encoding, per point: x/y/z quantised to 16 bits each over the bounding box (error at most
1/131,070 of the box side), RGB as 3 bytes, each scalar colour mode as one byte (its legend's
0..255 index), base64: (6 + 3 + maps) * 4/3 bytes. Data chunks grow 4x from 16,384 points, so the
first chunk is a coarse level of the scan.
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from . import check_level_output

#: the default cap of a page: WebGL in a browser stays interactive up to about this many points
MAX_POINTS = 2_000_000
#: points in the first data chunk; each next chunk is CHUNK_GROWTH times larger
FIRST_CHUNK = 16_384
CHUNK_GROWTH = 4
#: slider stops (log-spaced level sizes)
STEPS = 400
UPS = ("z", "y", "x", "-z", "-y", "-x")


@dataclass(frozen=True)
class WebPage:
    """What :func:`write_web_page` wrote."""

    path: Path
    n_points: int  # points in the page
    n_total: int  # points of the scan
    rho: float  # covering radius of the page's finest level (0: every point)
    n_bytes: int
    chunks: int


def _chunks(n: int) -> list[tuple[int, int]]:
    """[start, end) of the data chunks: ends at FIRST_CHUNK * CHUNK_GROWTH**i, then n."""
    ends, end = [], FIRST_CHUNK
    while end < n:
        ends.append(end)
        end *= CHUNK_GROWTH
    ends.append(n)
    return list(zip([0] + ends[:-1], ends, strict=True))


def _quantise(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(uint16 (N, 3) positions, lo, span) with position = lo + q / 65535 * span, centred at 0."""
    pmin, pmax = points.min(axis=0), points.max(axis=0)
    centre = (pmin + pmax) / 2.0
    span = np.maximum(pmax - pmin, 1e-12 * max(1.0, float(np.abs(pmax).max())))
    q = np.rint((points - pmin) / span * 65535.0)
    return np.clip(q, 0, 65535).astype("<u2"), pmin - centre, span


def _steps(radius: np.ndarray, rho: float) -> list[list[float]]:
    """[k, rho_k] at log-spaced k in [1, K]: rho_k = radius[k] (the next insertion radius), and
    the level's own ``rho`` at k = K; -1 where rho_k is infinite (the next point is a seed of
    another piece: the prefix promises no bound; 0 would read as 'every point')."""
    k_all = len(radius)
    ks = np.unique(np.rint(np.geomspace(1, k_all, min(STEPS, k_all))).astype(np.int64))
    out = []
    for k in ks:
        r = float(radius[k]) if k < k_all else float(rho)
        out.append([int(k), r if math.isfinite(r) else -1.0])
    return out


def _first_view(points: np.ndarray, up: str) -> list[float]:
    """[yaw, pitch] of the page's orbit camera (its basis: U = up, A = the next axis, B = the
    one after, times up's sign) for :func:`lodbuilder.viewer.data.facing_camera`."""
    from ..viewer.data import facing_camera

    d, _ = facing_camera(points, up)
    a = "xyz".index(up[-1])
    sign = -1.0 if up.startswith("-") else 1.0
    along_a, along_b = float(d[(a + 1) % 3]), float(d[(a + 2) % 3]) * sign
    pitch = math.asin(max(-1.0, min(1.0, float(d[a]) * sign)))
    return [math.atan2(along_b, along_a), pitch]


def write_web_page(
    out: str | os.PathLike,
    points: np.ndarray,
    radius: np.ndarray,
    rho: float,
    *,
    n_total: int | None = None,
    rgb: np.ndarray | None = None,
    importance: dict[str, np.ndarray] | None = None,
    name: str = "scan",
    crs: str | None = None,
    units: str | None = None,
    up: str = "z",
    bounds: np.ndarray | None = None,
    note: str = "",
    scalars: dict[str, tuple[np.ndarray, Any]] | None = None,
    categories: dict[str, tuple[np.ndarray, Any]] | None = None,
) -> WebPage:
    """Write the points of a level (farthest-point order) as one HTML page, atomically.

    ``points`` (K, 3): a prefix of the scan's ordering; ``radius`` (K,): their insertion radii
    (the prefix of k is covered within radius[k]); ``rho``: the whole level's bound (0: the whole
    scan); ``n_total``: points of the scan (default K); ``rgb`` (K, 3): uint8, 16-bit or unit
    floats (scaled as the viewer does); ``importance``: maps to colour by; ``crs``/``units``:
    shown on the page; ``up``: the up axis of the first view (``z``, ``-y``...); ``bounds``: the
    covering bound of each prefix (default ``radius``; a filtered level's from
    :func:`lodbuilder.filters.prefix_bounds`); ``note``: a line shown with the name (a filter);
    ``scalars``: label -> (values, a viewer ``Legend``) (elevation, intensity); ``categories``:
    label -> (integer labels 0..255, a viewer ``Categories``) (classification, scan)."""
    from ..io._files import atomic_output
    from ..viewer.data import crs_label
    from ._page import HEAD

    if up not in UPS:
        raise InputError(f"up must be one of {', '.join(UPS)}, got {up!r}")
    out, pts, radius = check_level_output(out, "web page", (".html", ".htm"), points, radius)
    k = pts.shape[0]
    n_total = int(n_total or k)
    q, lo, span = _quantise(pts)
    columns: list[np.ndarray] = [q.view(np.uint8)]  # (K, 6): little-endian uint16 x, y, z
    if rgb is not None:
        columns.append(_rgb_bytes(rgb).reshape(k, 3))
    scalar_specs = _scalar_columns(columns, radius, units, scalars, importance)
    cats = _category_columns(columns, categories)
    chunks = _chunks(k)
    header = {
        "n": k, "n_total": n_total, "rgb": rgb is not None, "scalars": scalar_specs,
        "cats": cats, "chunks": chunks, "bytes_per_point": sum(c.shape[1] for c in columns),
        "lo": lo.tolist(), "span": span.tolist(), "up": up, "view": _first_view(pts, up),
        **_header(pts, radius, rho, bounds, span, n_total, units),
        "info": f"{name}: {k:,} of {n_total:,} points; {crs_label(crs, units)}"
        + (f"; {note}" if note else ""),
    }
    head = HEAD.replace("@TITLE@", html.escape(f"{name} - lodbuilder", quote=True)).replace(
        "@HEADER@", json.dumps(header, allow_nan=False).replace("<", "\\u003c")
    )
    with atomic_output(out) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as f:
        f.writelines(_page_parts(head, columns, chunks))
    return WebPage(out, k, n_total, float(rho), out.stat().st_size, len(chunks))


def _rgb_bytes(rgb: np.ndarray) -> np.ndarray:
    from ..viewer.data import _to_uint8_rgb

    return _to_uint8_rgb(np.asarray(rgb))


def _scalar_columns(columns: list[np.ndarray], radius: np.ndarray, units: str | None,
                    scalars: dict[str, tuple[np.ndarray, Any]] | None,
                    importance: dict[str, np.ndarray] | None) -> list[dict[str, Any]]:
    """Append one byte a point per scalar colour mode (radius, ``scalars``, importance maps:
    the legend's 0..255 index) to ``columns``; return the modes' specs for the page."""
    from ..viewer.data import importance_legend, radius_legend

    legends = [("radius", radius_legend(radius, units), radius)]
    legends += [(label, legend, v) for label, (v, legend) in (scalars or {}).items()]
    legends += [(f"importance: {m}", importance_legend(m, v), v) for m, v in (importance or {}).items()]
    specs = []
    for label, legend, values in legends:
        v = np.asarray(values, dtype=np.float64)
        if label == "radius":
            finite = v[np.isfinite(v) & (v > 0)]
            top = float(finite.max()) if finite.size else 1.0
            v = np.where(np.isfinite(v) & (v > 0), v, top)
        idx = np.clip(np.nan_to_num(legend.normalise(v), nan=0.0) * 255.0, 0, 255).astype(np.uint8)
        columns.append(idx.reshape(-1, 1))
        specs.append({"label": label, "title": legend.title, "lo": legend.lo, "hi": legend.hi})
    return specs


def _category_columns(columns: list[np.ndarray],
                      categories: dict[str, tuple[np.ndarray, Any]] | None) -> list[dict[str, Any]]:
    """Append one byte a point per categorical colour mode to ``columns``; return their tables."""
    cats = []
    for label, (labels, cat) in (categories or {}).items():
        lab = np.asarray(labels).astype(np.int64)
        if lab.size and (lab.min() < 0 or lab.max() > 255):
            raise InputError(f"colour {label!r}: labels must lie in 0..255 to fit one byte")
        columns.append(lab.astype(np.uint8).reshape(-1, 1))
        cats.append({"label": label, "title": cat.title,
                     "table": [[int(v), str(n), [int(c) for c in rgb_]]
                               for v, n, rgb_ in zip(cat.values, cat.names, cat.colours, strict=True)]})
    return cats


def _header(pts: np.ndarray, radius: np.ndarray, rho: float, bounds: np.ndarray | None,
            span: np.ndarray, n_total: int, units: str | None) -> dict[str, Any]:
    """The page header's rank legend, colour table, slider stops and point size."""
    from ..viewer.data import colormap, rank_legend

    k = pts.shape[0]
    rank = rank_legend(n_total)
    finite = radius[np.isfinite(radius) & (radius > 0)]
    # points of the finest level are squares 1.5 spacing wide: rho, or the scan's own spacing
    spacing = float(radius[k // 2]) if k > 1 and rho == 0 else float(rho)
    if not math.isfinite(spacing) or spacing <= 0:
        spacing = float(finite.min()) if finite.size else float(np.linalg.norm(span)) * 1e-3
    return {
        "rank": {"title": rank.title, "lo": rank.lo, "hi": rank.hi},
        "lut": colormap(np.linspace(0.0, 1.0, 256)).ravel().tolist(),
        "steps": _steps(radius if bounds is None else np.asarray(bounds), rho),
        "diag": float(np.linalg.norm(span)),
        "spacing": spacing,
        "unit": units or "scan units",
    }


def _page_parts(head: str, columns: list[np.ndarray], chunks: list[tuple[int, int]]):
    yield head
    for i, (start, end) in enumerate(chunks):
        block = b"".join(np.ascontiguousarray(c[start:end]).tobytes() for c in columns)
        yield f'<script type="application/octet-stream" id="c{i}">'
        yield base64.b64encode(block).decode("ascii")
        yield f"</script>\n<script>LOD.chunk({i});</script>\n"
    from ._page import TAIL

    yield TAIL


def export_web(
    scan: Any,
    out: str | os.PathLike,
    size: int,
    *,
    up: str = "z",
    flt: Any = None,
) -> WebPage:
    """Write the level of ``size`` points of an archive scan (a ScanView) as a web page, with its
    RGB (when the scan has red/green/blue) and its importance maps; with ``flt`` (a
    :class:`lodbuilder.filters.LevelFilter`) only the level's points that pass it."""
    names = [c for c in ("red", "green", "blue") if c in scan.attribute_names]
    from . import joint_member_names as joint_members

    members = joint_members(scan)
    survey = [a for a in ("intensity", "classification") if a in scan.attribute_names]
    if members and "scan_id" in scan.attribute_names and len(members) <= 256:
        survey.append("scan_id")
    wanted = (names if len(names) == 3 else []) + survey + (flt.fields() if flt is not None else [])
    level = scan.level(size=size, attributes=sorted(set(wanted)) if wanted else False)
    bounds = None
    if flt is not None:
        from ..filters import prefix_bounds

        level = flt.apply(level)
        bounds = prefix_bounds(scan.radius, level.rank)
    rgb = None
    if len(names) == 3:
        rgb = np.column_stack([level.attributes[c] for c in names])
    importance = {m: np.asarray(scan.importance(m)[:size])[level.rank] for m in scan.importance_names}
    extra, cats = _survey_colours(level, up, scan.units, members)
    return write_web_page(
        out,
        level.points,
        level.radius,
        level.rho,
        n_total=scan.n_ordered,
        rgb=rgb,
        importance=importance,
        name=scan.name,
        crs=scan.crs,
        units=scan.units,
        up=up,
        bounds=bounds,
        note=f"filter {flt.describe()}" if flt is not None else "",
        scalars=extra,
        categories=cats,
    )


def _survey_colours(level: Any, up: str, units: str | None,
                    members: list[str] | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """(scalar, categorical) colour modes of a level: elevation along ``up``, intensity;
    the member scans of a joint scan, classification."""
    from ..viewer.data import classification_legend, elevation_legend, intensity_legend

    axis = "xyz".index(up[-1])
    elev = level.points[:, axis] * (-1.0 if up.startswith("-") else 1.0)
    extra = {"elevation": (elev, elevation_legend(elev, up, units))}
    if "intensity" in level.attributes:
        extra["intensity"] = (level.attributes["intensity"], intensity_legend(level.attributes["intensity"]))
    cats = {}
    if members and "scan_id" in level.attributes:  # a joint scan: its member scans
        from ..viewer.data import scan_legend

        cats["scan"] = (np.asarray(level.attributes["scan_id"]), scan_legend(members))
    if "classification" in level.attributes:
        codes = np.asarray(level.attributes["classification"])
        cats["classification"] = (codes, classification_legend(codes))
    return extra, cats
