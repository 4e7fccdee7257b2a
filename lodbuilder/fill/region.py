"""One region of the surface far from every input point: what :mod:`lodbuilder.fill.gaps` finds,
on a height field over a plane or on an implicit surface (:mod:`lodbuilder.fill.implicit`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._validate import strict_methods
from .implicit import ImplicitSurface
from .surface import Frame, HeightField

STATUS_FILLABLE = "fillable"
STATUS_ROUGH = "rough"


@strict_methods
@dataclass
class Region:
    """One enclosed region of the surface farther than rho/2 from every input point.

    Attributes:
        id: the gap's number in the report (0, 1, ... in the order found); -1 for a region that
            is no gap.
        status: ``"fillable"``, or ``"rough"`` when the surrounding input is not one smooth height
            field (not filled; ``reason`` says why). Only gaps are assessed (a region that is no
            gap is never filled).
        candidates: (M, 3) grid nodes of the region lifted onto the fitted surface (on an
            implicit surface: one point per grid cell it crosses).
        distance: (M,) distance of each candidate to the nearest sample point.
        rho: the density asked for.
        area: area of the part farther than rho from the input (0 when the region only lies
            between rho/2 and rho from it: not a gap, but the level still misses rho there).
        region_area: area of the whole region.
        node_area: surface area each candidate stands for.
        residual: RMS error of the fitted surface predicting the inner ring points of each sixth
            of the ring from the rest (NaN for a region that is no gap: not assessed).
        tilted: share of the inner ring's normals tilted more than 60 degrees from the plane's.
        frame: the hole's plane; ``uv`` (M, 2) the candidates' coordinates in it.
        surface: the height field over the plane, or, where the hole's surroundings are no
            height field (they fold over every plane), an implicit surface
            (:class:`~lodbuilder.fill.implicit.ImplicitSurface`).
        ring: indices (into the sample) of the input points around the region.
    """

    id: int
    status: str
    candidates: np.ndarray
    distance: np.ndarray
    rho: float
    area: float
    region_area: float
    node_area: np.ndarray
    residual: float
    frame: Frame
    uv: np.ndarray
    surface: HeightField | ImplicitSurface
    ring: np.ndarray
    tilted: float = 0.0
    reason: str = ""
    n_synthetic: int = 0
    #: enclosed only once cut from a channel of surface within rho of the input (kept only when
    #: a fillable gap)
    opened: bool = False
    #: enclosed only along the surface (the seeds' own sheet, in the steeper cone)
    along: bool = False

    @property
    def normal(self) -> np.ndarray:
        return self.frame.normal

    @property
    def implicit(self) -> bool:
        """Filled from an implicit surface, not a height field over ``frame``."""
        return isinstance(self.surface, ImplicitSurface)

    def normals_at(self, picked: np.ndarray) -> np.ndarray:
        """(K, 3) unit normals of the fitted surface at the candidates ``picked``."""
        if isinstance(self.surface, ImplicitSurface):
            return self.surface.normals(self.candidates[picked])
        return self.surface.normals(self.uv[picked], self.frame)

    def coordinates(self, points: np.ndarray) -> np.ndarray:
        """Coordinates over which attributes are interpolated, in units of rho: in the hole's
        plane for a height field, in 3D for an implicit surface (a fold overlaps itself over
        any plane)."""
        if isinstance(self.surface, ImplicitSurface):
            return (points - self.frame.origin) / self.rho
        return self.frame.uv(points) / self.surface.scale

    @property
    def is_gap(self) -> bool:
        """Some of it is farther than rho from every input point."""
        return bool(self.area > 0)

    @property
    def max_distance(self) -> float:
        return float(self.distance.max()) if self.distance.size else 0.0

    def gap_points(self) -> np.ndarray:
        """Candidates farther than rho from every input point."""
        return self.candidates[self.distance > self.rho]

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) bounding box of the gap (of the region when it is no gap)."""
        pts = self.gap_points() if self.is_gap else self.candidates
        return np.stack([pts.min(axis=0), pts.max(axis=0)])

    def as_dict(self) -> dict[str, Any]:
        lo, hi = self.bounds
        return {
            "id": self.id,
            "status": self.status,
            "reason": self.reason,
            "area": self.area,
            "region_area": self.region_area,
            "max_distance": self.max_distance,
            "bounds_min": lo.tolist(),
            "bounds_max": hi.tolist(),
            "centre": self.candidates.mean(axis=0).tolist(),
            "normal": self.normal.tolist(),
            "residual": self.residual if math.isfinite(self.residual) else None,
            "n_synthetic": self.n_synthetic,
            "surface": "implicit" if self.implicit else "height field",
        }
