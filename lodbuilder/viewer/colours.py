"""Colours of a view: colour maps, the legends of continuous values and of categories (ASPRS
classes, scans), shared by the viewer and the web page."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: ``gaps`` colours: away from gaps, near a fillable gap, near a rough one
GAP_COLOURS = np.array([[200, 200, 200], [220, 30, 30], [240, 150, 0]], dtype=np.uint8)


#: ASPRS classes (lodbuilder.filters.ASPRS_CLASSES) in the colours survey viewers use
ASPRS_COLOURS: dict[int, tuple[int, int, int]] = {
    0: (160, 160, 160), 1: (200, 200, 200), 2: (166, 118, 64), 3: (170, 230, 120),
    4: (80, 190, 60), 5: (20, 110, 30), 6: (220, 60, 40), 7: (255, 0, 255), 8: (120, 120, 120),
    9: (40, 110, 230), 10: (120, 60, 160), 11: (90, 90, 90), 12: (230, 230, 120),
    13: (255, 220, 0), 14: (255, 180, 0), 15: (200, 140, 0), 16: (255, 240, 120),
    17: (0, 190, 200), 18: (255, 120, 200),
}
#: distinct colours for scans (Tableau 10, then its light half): neighbours never look alike
SCAN_PALETTE: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
    (174, 199, 232), (255, 187, 120), (152, 223, 138), (255, 152, 150), (197, 176, 213),
    (196, 156, 148), (247, 182, 210), (199, 199, 199), (219, 219, 141), (158, 218, 229),
)


@dataclass(frozen=True)
class Legend:
    """How a scalar colour mode maps values to viridis: ``lo`` -> 0, ``hi`` -> 1, linearly or on a
    log scale; ``title`` names the quantity and its unit (what a scalar bar shows)."""

    title: str
    lo: float
    hi: float
    log: bool

    def normalise(self, values: np.ndarray) -> np.ndarray:
        v = np.asarray(values, dtype=np.float64)
        if self.log:
            lo, hi = math.log(self.lo), math.log(self.hi)
            with np.errstate(divide="ignore", invalid="ignore"):
                return (np.log(np.maximum(v, self.lo)) - lo) / ((hi - lo) or 1.0)
        return (v - self.lo) / ((self.hi - self.lo) or 1.0)


@dataclass(frozen=True)
class Categories:
    """How a categorical colour mode colours values: ``values[i]`` is drawn in ``colours[i]``
    and named ``names[i]`` in the legend (classification, scan)."""

    title: str
    values: tuple[int, ...]
    names: tuple[str, ...]
    colours: tuple[tuple[int, int, int], ...]

    def colour(self, labels: np.ndarray) -> np.ndarray:
        """(M, 3) uint8 colours of ``labels`` (a value not listed: a hashed colour)."""
        lab = np.asarray(labels).astype(np.int64)
        out = categorical(lab)
        lut = np.asarray(self.colours, dtype=np.uint8).reshape(-1, 3)
        vals = np.asarray(self.values, dtype=np.int64)
        if vals.size:
            order = np.argsort(vals)
            pos = np.clip(np.searchsorted(vals[order], lab), 0, vals.size - 1)
            hit = vals[order][pos] == lab
            out[hit] = lut[order][pos[hit]]
        return out


def classification_legend(codes: np.ndarray) -> Categories:
    """The ASPRS names and colours of the classes present in ``codes``."""
    from ..filters import ASPRS_CLASSES

    present = [int(c) for c in np.unique(np.asarray(codes).astype(np.int64))]
    names = tuple(f"{c} {ASPRS_CLASSES.get(c, 'user class')}" for c in present)
    colours = tuple(ASPRS_COLOURS.get(c, tuple(int(v) for v in categorical(np.array([c]))[0]))
                    for c in present)
    return Categories("classification", tuple(present), names, colours)  # type: ignore[arg-type]


def scan_legend(names: Sequence[str]) -> Categories:
    """Distinct colours for scans 0..n-1 (a palette of 20, then hashed) with their names."""
    n = len(names)
    colours = tuple(SCAN_PALETTE[i] if i < len(SCAN_PALETTE)
                    else tuple(int(v) for v in categorical(np.array([i]))[0]) for i in range(n))
    return Categories("scan", tuple(range(n)), tuple(names), colours)  # type: ignore[arg-type]


def elevation_legend(values: np.ndarray, axis: str, units: str | None) -> Legend:
    """Linear scale of elevation (the up axis) from its 1st to its 99th percentile."""
    lo, hi = np.percentile(values, [1, 99]) if values.size > 1 else (0.0, 1.0)
    return Legend(f"elevation {axis} ({units or 'scan units'})", float(lo), float(max(hi, lo)), False)


def intensity_legend(values: np.ndarray) -> Legend:
    """Linear scale of intensity from its 1st to its 99th percentile."""
    v = np.asarray(values, dtype=np.float64)
    lo, hi = np.percentile(v, [1, 99]) if v.size > 1 else (0.0, 1.0)
    return Legend("intensity", float(lo), float(max(hi, lo)), False)


def radius_legend(radius: np.ndarray, units: str | None = None) -> Legend:
    """Log scale of insertion radii, from their 1st percentile to the largest finite one.

    (The last radii of an ordering, near-duplicates, reach far below the scan's spacing: from
    the smallest one, every other point would get one colour.)"""
    r = np.asarray(radius, dtype=np.float64)
    finite = r[np.isfinite(r) & (r > 0)]
    lo = float(np.percentile(finite, 1)) if finite.size else 1.0
    hi = float(finite.max()) if finite.size else 1.0
    return Legend(f"radius ({units or 'scan units'}, log)", lo, max(hi, lo), True)


def rank_legend(n: int) -> Legend:
    """Log scale of ranks 1..n (the first point is rank 1)."""
    return Legend("rank (log)", 1.0, float(max(n, 2)), True)


def importance_legend(name: str, values: np.ndarray) -> Legend:
    """Linear scale of an importance map from its 1st to its 99th percentile."""
    v = np.asarray(values, dtype=np.float64)
    lo, hi = np.nanpercentile(v, [1, 99]) if v.size > 1 else (0.0, 1.0)
    return Legend(f"importance: {name}", float(lo), float(hi), False)


def _to_uint8_rgb(rgb: np.ndarray) -> np.ndarray:
    if rgb.dtype == np.uint8:
        return np.ascontiguousarray(rgb)
    rgb = rgb.astype(np.float64)
    top = float(np.nanmax(rgb)) if rgb.size else 1.0
    if np.issubdtype(rgb.dtype, np.floating) and top <= 1.0:
        scale = 255.0
    elif top <= 255:
        scale = 1.0
    else:
        scale = 255.0 / 65535.0  # 16-bit colours (LAS)
    return np.clip(rgb * scale, 0, 255).astype(np.uint8)


_LUT: np.ndarray | None = None


def _viridis() -> np.ndarray:
    global _LUT
    if _LUT is None:
        try:
            import matplotlib

            lut = matplotlib.colormaps["viridis"](np.linspace(0, 1, 256))[:, :3]
        except ImportError:  # a two-stop fallback: dark blue to yellow
            t = np.linspace(0, 1, 256)[:, None]
            lut = (1 - t) * np.array([0.27, 0.0, 0.33]) + t * np.array([0.99, 0.91, 0.14])
        _LUT = np.round(lut * 255).astype(np.uint8)
    return _LUT


def colormap(t: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 viridis colours of values ``t`` in [0, 1] (clipped; NaN -> 0)."""
    t = np.nan_to_num(np.asarray(t, dtype=np.float64), nan=0.0)
    idx = np.clip((t * 255.0).astype(np.int64), 0, 255)
    return _viridis()[idx]


def categorical(labels: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 well-spread colours of integer labels (a hash, so equal labels match)."""
    x = np.asarray(labels).astype(np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    x ^= x >> np.uint64(29)
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    x ^= x >> np.uint64(32)
    rgb = np.column_stack([(x >> np.uint64(s)) & np.uint64(0xFF) for s in (0, 8, 16)]).astype(
        np.int64
    )
    return (48 + rgb * 207 // 255).astype(np.uint8)  # avoid near-black cells
