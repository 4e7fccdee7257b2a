"""Quality of a level against its scan: covering radius and the rho guarantee, Hausdorff, Chamfer,
spacing and uniformity, point-to-surface error, per-level reports and plots.

Metrics are pure NumPy/SciPy functions over (input points, level points). Plots import matplotlib
only when called.
"""

from .metrics import (
    Spacing,
    TwoSided,
    chamfer,
    covering_radius,
    hausdorff,
    meets_rho,
    nearest_distances,
    spacing,
    uniformity,
)
from .report import LevelReport, default_sizes, evaluate_level, evaluate_prefixes, prefix_sizes
from .surface import ErrorStats, surface_error

__all__ = [
    "ErrorStats",
    "LevelReport",
    "Spacing",
    "TwoSided",
    "chamfer",
    "covering_radius",
    "default_sizes",
    "evaluate_level",
    "evaluate_prefixes",
    "hausdorff",
    "meets_rho",
    "nearest_distances",
    "prefix_sizes",
    "spacing",
    "surface_error",
    "uniformity",
]
