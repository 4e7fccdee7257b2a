"""Colour difference in CIELAB: sRGB -> CIE L*a*b* (D65) in NumPy, and the mean Delta-E to neighbours."""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validate import strict_keywords, validate_points
from ..errors import InputError
from .neighbours import kd_tree, mean_pair_function, neighbourhoods

# linear sRGB -> CIE XYZ (D65), IEC 61966-2-1
_SRGB_TO_XYZ = np.array(
    [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ]
)
_WHITE_D65 = np.array([0.95047, 1.0, 1.08883])
_DELTA = 6.0 / 29.0

#: colour attribute names tried in order (PLY/LAS, PLY "diffuse_", E57)
COLOUR_NAMES = (
    ("red", "green", "blue"),
    ("r", "g", "b"),
    ("diffuse_red", "diffuse_green", "diffuse_blue"),
    ("colorRed", "colorGreen", "colorBlue"),
)


def to_unit_rgb(rgb: Any, name: str = "colours") -> np.ndarray:
    """Colours as (N, 3) float64 in [0, 1].

    uint8 is divided by 255; uint16 by 65535, unless every value is <= 255 (LAS files that hold
    8-bit values in 16-bit fields), then by 255; floats are taken as [0, 1] unless some value
    exceeds 1, then as [0, 255].
    """
    arr = np.asarray(rgb)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    if np.issubdtype(arr.dtype, np.integer):
        top = 255.0 if arr.dtype.itemsize == 1 or (arr.size and arr.max() <= 255) else 65535.0
        if arr.size and arr.min() < 0:
            raise InputError(f"{name} has negative values; colours must be >= 0")
        return arr.astype(np.float64) / top
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError(f"{name} must hold numbers, got dtype {arr.dtype}")
    out = arr.astype(np.float64)
    if not np.isfinite(out).all() or (out < 0).any():
        raise InputError(f"{name} has NaN, inf or negative values; colours must be finite and >= 0")
    if out.size and out.max() > 1.0:
        out = out / 255.0
    return np.clip(out, 0.0, 1.0)


@strict_keywords
def srgb_to_lab(rgb: Any) -> np.ndarray:
    """(N, 3) sRGB colours (any dtype :func:`to_unit_rgb` accepts) -> (N, 3) CIE L*a*b* under D65.

    L* is in [0, 100]; white (1, 1, 1) maps to (100, 0, 0) and black to (0, 0, 0).
    """
    c = to_unit_rgb(rgb)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    xyz = lin @ _SRGB_TO_XYZ.T / _WHITE_D65
    f = np.where(xyz > _DELTA**3, np.cbrt(xyz), xyz / (3 * _DELTA**2) + 4.0 / 29.0)
    lab = np.empty_like(f)
    lab[:, 0] = 116.0 * f[:, 1] - 16.0
    lab[:, 1] = 500.0 * (f[:, 0] - f[:, 1])
    lab[:, 2] = 200.0 * (f[:, 1] - f[:, 2])
    return lab


def scan_colours(attributes: dict[str, np.ndarray], scan_name: str = "scan") -> np.ndarray:
    """The (N, 3) colour columns of a scan's attributes, or an InputError naming what was looked for."""
    for names in COLOUR_NAMES:
        if all(n in attributes for n in names):
            return np.stack([np.asarray(attributes[n]) for n in names], axis=1)
    raise InputError(
        f"scan {scan_name!r} has no colours (no red/green/blue attributes); "
        "leave 'colour' out of the importance maps"
    )


@strict_keywords
def colour_difference(
    points: Any, colours: Any, *, k: int = 16, radius: float | None = None, tree: Any = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Mean CIE76 Delta-E (Euclidean distance in L*a*b*) from each point's colour to its
    neighbours' colours (the point itself left out). About 2.3 is a just-noticeable difference."""
    pts = validate_points(points)
    lab = srgb_to_lab(colours)
    if lab.shape[0] != pts.shape[0]:
        raise InputError(
            f"colours has {lab.shape[0]} rows but points has {pts.shape[0]}; give one colour per point"
        )
    tree = kd_tree(pts) if tree is None else tree
    nb = neighbourhoods(pts, k=k, radius=radius, tree=tree).without_self()
    values = mean_pair_function(nb, lambda i, j: np.linalg.norm(lab[i] - lab[j], axis=1))
    params: dict[str, Any] = {"radius": float(radius)} if radius is not None else {"k": int(k)}
    return values, params | {"space": "CIELAB D65", "delta_e": "CIE76"}
