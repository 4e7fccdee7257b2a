"""The result of a farthest point ordering."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validate import strict_methods


@strict_methods
@dataclass(frozen=True)
class Ordering:
    """A farthest point ordering of a point set.

    Attributes:
        order: (K,) int64. ``order[k]`` is the input index of the k-th point. K == N for a full
            ordering, fewer when the ordering was stopped early by ``rho`` or ``size``.
        radius: (K,) float64, non-increasing. ``radius[k]`` is the insertion radius of the k-th point:
            an upper bound of the distance from every input point to the first k points
            (the prefix ``order[:k]`` covers the whole input within ``radius[k]``).
            Convention: seeds have radius ``inf``; the first point of every other piece of the band
            enters when the radius falls to its Euclidean distance to the points before it, with that
            distance as radius and the nearest of them as parent; exact duplicates of an earlier
            point have radius 0.
        parent: (K,) int64. Position in the ordering of the nearest earlier point at insertion time
            (the Voronoi cell the point fell in); -1 for seeds.
        voxel_size: the grid spacing h used by the band.
        band_radius: the band radius r.
        seeds: (S,) int64 input indices that start the ordering, in order.
        stats: counters of the build (band voxels, pops, phases, ...), for benchmarks and logs.
        stop_radius: covering bound of the whole ordering: 0 when every point is ordered; for an
            ordering stopped early by ``rho`` or ``size``, the next candidate's distance when it
            stopped (an upper bound of every unordered point's distance to the ordered ones).
        pieces: (N,) int32 with ``fastfps(..., pieces=True)``: each input point's connected piece
            of the band (0 .. ``stats["pieces"]`` - 1; a duplicate has its first copy's); else None.
    """

    order: np.ndarray
    radius: np.ndarray
    parent: np.ndarray
    voxel_size: float
    band_radius: float
    seeds: np.ndarray
    n_points: int
    stats: dict[str, Any] = field(default_factory=dict)
    stop_radius: float = 0.0
    pieces: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.order.shape[0])

    def size_for_rho(self, rho: float) -> int:
        """Number of leading points whose prefix covers every input point within ``rho``
        (:func:`lodbuilder.levels.count_above`)."""
        from ..levels import count_above

        return count_above(self.radius, rho)

    def rank(self) -> np.ndarray:
        """(N,) int64: position of every input point in the ordering, -1 if not ordered."""
        r = np.full(self.n_points, -1, dtype=np.int64)
        r[self.order] = np.arange(self.order.shape[0], dtype=np.int64)
        return r
