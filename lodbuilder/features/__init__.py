"""Importance maps: surface variation, normal variation, colour difference, noise score, user maps.

Every map is one float per point plus a dict of the parameters that made it. Neighbour queries use
scipy's cKDTree (imported when first needed); nothing here imports numba.
"""

from __future__ import annotations

from .colour import colour_difference, srgb_to_lab
from .geometry import noise_score, normal_variation, pca_normals, surface_variation
from .registry import REGISTRY, compute_importance, map_name, parse_names
from .weights import (
    check_adaptivity,
    combine_maps,
    cost_from_weights,
    normalise,
    validate_weights,
)

__all__ = [
    "REGISTRY",
    "check_adaptivity",
    "colour_difference",
    "combine_maps",
    "compute_importance",
    "cost_from_weights",
    "map_name",
    "noise_score",
    "normal_variation",
    "normalise",
    "parse_names",
    "pca_normals",
    "srgb_to_lab",
    "surface_variation",
    "validate_weights",
]
