"""Importance maps by name, so the CLI can say ``--importance curvature,colour,noise``.

Built-in names (aliases in brackets):

- ``curvature`` (``surface_variation``): :func:`~lodbuilder.features.geometry.surface_variation`
- ``normal`` (``normal_variation``): :func:`~lodbuilder.features.geometry.normal_variation`,
  on the scan's ``nx``/``ny``/``nz`` when present, PCA normals otherwise
- ``colour`` (``color``): :func:`~lodbuilder.features.colour.colour_difference`
- ``noise`` (``outlier``): :func:`~lodbuilder.features.geometry.noise_score`

User maps:

- ``attr:NAME``: the scan attribute ``NAME`` (a PLY vertex property or a LAS dimension), stored as
  map ``NAME``;
- ``PATH.npy`` or ``npy:PATH``: one value per point in input order, stored as map ``<file stem>``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import strict_keywords, validate_points
from ..errors import InputError, ScanFileError
from ..progress import ProgressCallback, report
from .colour import colour_difference, scan_colours
from .geometry import noise_score, normal_variation, surface_variation
from .neighbours import kd_tree
from .weights import validate_weights

log = logging.getLogger(__name__)

MapResult = tuple[np.ndarray, dict[str, Any]]
MapFunction = Callable[..., MapResult]


def _curvature(scan: Any, tree: Any, **kw: Any) -> MapResult:
    return surface_variation(scan.points, tree=tree, **kw)


def _normal(scan: Any, tree: Any, **kw: Any) -> MapResult:
    attrs = scan.attributes
    normals = None
    if all(c in attrs for c in ("nx", "ny", "nz")):
        normals = np.stack([np.asarray(attrs[c], dtype=np.float64) for c in ("nx", "ny", "nz")], 1)
        if not (np.isfinite(normals).all() and (np.linalg.norm(normals, axis=1) > 0).all()):
            log.warning("scan %r has zero or non-finite normals; using PCA normals", scan.name)
            normals = None
    return normal_variation(scan.points, normals, tree=tree, **kw)


def _colour(scan: Any, tree: Any, **kw: Any) -> MapResult:
    return colour_difference(scan.points, scan_colours(scan.attributes, scan.name), tree=tree, **kw)


def _noise(scan: Any, tree: Any, **kw: Any) -> MapResult:
    return noise_score(scan.points, tree=tree, **kw)


#: canonical name -> function(scan, tree, **options) -> (values, params)
REGISTRY: dict[str, MapFunction] = {
    "curvature": _curvature,
    "normal": _normal,
    "colour": _colour,
    "noise": _noise,
}
ALIASES = {
    "surface_variation": "curvature",
    "normal_variation": "normal",
    "color": "colour",
    "outlier": "noise",
}


@strict_keywords
def parse_names(names: str | Iterable[str]) -> list[str]:
    """Split ``"curvature,colour"`` (or a list) into stripped, non-empty, distinct specs."""
    items = names.split(",") if isinstance(names, str) else list(names)
    out: list[str] = []
    for item in items:
        s = str(item).strip()
        if s and s not in out:
            out.append(s)
    if not out:
        raise InputError("no importance map named; give e.g. --importance curvature,colour")
    return out


@strict_keywords
def map_name(spec: str) -> str:
    """The name a map spec is stored under (``attr:intensity`` -> ``intensity``)."""
    low = spec.lower()
    if low in REGISTRY:
        return low
    if low in ALIASES:
        return ALIASES[low]
    if spec.startswith("attr:"):
        return spec[5:]
    if spec.startswith("npy:") or low.endswith(".npy"):
        return Path(spec[4:] if spec.startswith("npy:") else spec).stem
    known = ", ".join(sorted(REGISTRY) + sorted(ALIASES))
    raise InputError(
        f"unknown importance map {spec!r}; use one of {known}, attr:NAME (a scan attribute) "
        "or a .npy file"
    )


def user_map(scan: Any, spec: str) -> MapResult:
    """A user map: ``attr:NAME`` from the scan's attributes, or a ``.npy`` file."""
    n = len(scan.points)
    if spec.startswith("attr:"):
        attr = spec[5:]
        if attr not in scan.attributes:
            have = ", ".join(sorted(scan.attributes)) or "none"
            raise InputError(
                f"scan {scan.name!r} has no attribute {attr!r} for importance map {spec!r} "
                f"(attributes: {have})"
            )
        return validate_weights(scan.attributes[attr], n, attr), {
            "source": "attribute",
            "name": attr,
        }
    path = Path(spec[4:] if spec.startswith("npy:") else spec)
    try:
        values = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise ScanFileError(
            f"importance map file {str(path)!r} not found; check the path"
        ) from None
    except (OSError, ValueError) as exc:
        raise InputError(
            f"importance map file {str(path)!r} is not a readable .npy array ({exc}); "
            "save it with np.save"
        ) from None
    return validate_weights(values, n, path.stem), {"source": "npy", "file": path.name}


@strict_keywords
def compute_importance(
    scan: Any,
    names: str | Iterable[str],
    *,
    k: int = 16,
    radius: float | None = None,
    options: dict[str, dict[str, Any]] | None = None,
    progress: ProgressCallback = None,
) -> dict[str, MapResult]:
    """Compute importance maps of a :class:`~lodbuilder.io.base.Scan` by name.

    Args:
        scan: the scan (``points``, ``attributes``, ``name``).
        names: map specs, a list or a comma-separated string (see the module docstring).
        k: neighbours per point for the built-in maps (the point included).
        radius: use radius neighbourhoods instead of kNN.
        options: per-map keyword arguments by canonical name, e.g. ``{"curvature": {"k": [8, 16, 32]}}``.

    Returns:
        ``{name: (values, params)}``, values (N,) float64, params a JSON-serialisable dict that
        names the map kind.
    """
    points = validate_points(scan.points)
    specs = parse_names(names)
    stored = [map_name(s) for s in specs]
    dupes = {s for s in stored if stored.count(s) > 1}
    if dupes:
        raise InputError(f"importance maps {sorted(dupes)} are named twice; give each map once")
    options = options or {}
    tree = None
    out: dict[str, MapResult] = {}
    for i, (spec, name) in enumerate(zip(specs, stored, strict=True)):
        report(progress, "importance", i, len(specs))
        if name in REGISTRY and (spec.lower() in REGISTRY or spec.lower() in ALIASES):
            tree = kd_tree(points) if tree is None else tree
            kw: dict[str, Any] = {"radius": radius} if radius is not None else {"k": k}
            kw.update(options.get(name, {}))
            values, params = REGISTRY[name](scan, tree, **kw)
            params = {"kind": name} | params
        else:
            values, params = user_map(scan, spec)
            params = {"kind": "user"} | params
        log.info(
            "importance map %s: min %.3g median %.3g max %.3g",
            name,
            values.min(),
            np.median(values),
            values.max(),
        )
        out[name] = (values, params)
    report(progress, "importance", len(specs), len(specs))
    return out
