"""The surface preview of a level (key ``m``, ``view --surface``), trimmed to where the points are.

VTK's implicit reconstruction (``vtkSurfaceReconstructionFilter``) closes every surface it is
given: on an open or thin scan (the bunny's ears, a range scan's border) it draws large planar
sheets far from any point. The preview keeps only the triangles that stay near the level:

    a triangle is kept when its corners and edge midpoints are each within ``TRIM * rho`` of a
    point of the level and its longest edge is at most ``EDGE * rho``.

Guarantee: every point of a kept triangle lies in one of the four triangles of its midpoint
subdivision, within half the longest edge of one of that triangle's corners (which are the tested
samples), so it is within ``TRIM * rho + EDGE * rho / 2 = 2 rho`` of a point of the level, hence
of an input point (the level's points are input points).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: corners and edge midpoints within TRIM * rho of the level (the level covers the scan within
#: rho, and a surface point lies a little off the input points: 1.25 keeps the true surface whole)
TRIM = 1.25
#: longest edge kept, in rho (reconstruction samples at rho / 2, so its edges are ~0.7 rho)
EDGE = 1.5


def trim_surface(surface: Any, points: np.ndarray, rho: float) -> Any:
    """The triangles of ``surface`` (a PyVista PolyData) that stay within 2 ``rho`` of ``points``
    (see the module docstring); an empty PolyData when none does."""
    import pyvista as pv
    from scipy.spatial import cKDTree

    tri = surface.triangulate()
    if tri.n_cells == 0 or rho <= 0:
        return tri
    faces = np.asarray(tri.faces).reshape(-1, 4)
    keep_cells = np.flatnonzero(faces[:, 0] == 3)
    corners = np.asarray(tri.points, dtype=np.float64)[faces[keep_cells, 1:]]  # (T, 3, 3)
    mids = (corners + np.roll(corners, -1, axis=1)) / 2.0
    edges = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2).max(axis=1)
    samples = np.concatenate([corners, mids], axis=1).reshape(-1, 3)
    tree = cKDTree(np.asarray(points, dtype=np.float64))
    dist, _ = tree.query(samples, k=1, distance_upper_bound=TRIM * rho * (1 + 1e-9), workers=-1)
    near = (dist.reshape(-1, 6) <= TRIM * rho).all(axis=1) & (edges <= EDGE * rho)
    kept = faces[keep_cells[near]]
    return pv.PolyData(np.asarray(tri.points), kept.ravel()).clean(
        point_merging=False, lines_to_points=False, polys_to_lines=False, strips_to_polys=False
    )


def reconstruct(points: np.ndarray, rho: float) -> Any:
    """VTK's implicit surface through ``points`` sampled at rho / 2 (untrimmed); Delaunay 2D
    where it fails (few or degenerate points)."""
    import pyvista as pv

    pts = pv.PolyData(np.ascontiguousarray(points, dtype=np.float64))
    surf = None
    if pts.n_points >= 10 and rho > 0:
        try:
            surf = pts.reconstruct_surface(
                nbr_sz=min(20, pts.n_points - 1), sample_spacing=0.5 * rho
            )
        except Exception as exc:  # VTK raises on degenerate inputs
            log.info("reconstruct_surface failed (%s); using delaunay_2d", exc)
    if surf is None or surf.n_cells == 0:
        surf = pts.delaunay_2d()
    return surf


def level_surface(points: np.ndarray, rho: float) -> Any:
    """A surface through the level's ``points`` (density ``rho``): :func:`reconstruct`, trimmed
    by :func:`trim_surface`."""
    return trim_surface(reconstruct(points, rho), points, rho)
