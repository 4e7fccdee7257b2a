"""The surface preview (``view --surface``, key ``m``) does not invent geometry: no point of any
triangle lies farther than 2 rho from the scan, on a closed scan with thin parts (the bunny's
ears) and on a raw range scan with an open border."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.viewer


def level(shared_data, name: str, k: int):
    """(the first k points in Euclidean farthest-point order, all points, the covering radius)."""
    from plyfile import PlyData

    from lodbuilder import euclidean_fps

    v = PlyData.read(str(shared_data / name))["vertex"].data
    pts = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    o = euclidean_fps(pts, size=k + 1)
    return pts[o.order[:k]], pts, float(o.radius[k])


def farthest_triangle_point(surface, points: np.ndarray, steps: int = 4) -> float:
    """The largest distance from a point of any triangle of ``surface`` to ``points``, sampled on
    a barycentric grid of ``steps`` subdivisions (corners, edges and inside)."""
    from scipy.spatial import cKDTree

    faces = np.asarray(surface.faces).reshape(-1, 4)
    assert np.all(faces[:, 0] == 3)
    tri = np.asarray(surface.points)[faces[:, 1:]]  # (T, 3, 3)
    bary = np.array(
        [(i, j, steps - i - j) for i in range(steps + 1) for j in range(steps + 1 - i)], float
    ) / steps
    samples = np.einsum("bk,tkd->tbd", bary, tri).reshape(-1, 3)
    dist, _ = cKDTree(points).query(samples, k=1)
    return float(dist.max())


def level_points_near(surface, level_points: np.ndarray, rho: float) -> float:
    """Share of the level's points within rho of a vertex of the surface (it is not empty)."""
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(np.asarray(surface.points)).query(level_points, k=1)
    return float(np.mean(dist <= rho))


@pytest.mark.parametrize(
    "name, k",
    [("bun_zipper.ply", 3000), ("bun000.ply", 1500)],
    ids=["bunny-3000", "open-range-scan"],
)
def test_surface_stays_within_two_rho_of_the_scan(shared_data, name, k):
    from lodbuilder.viewer import surface as S

    lvl, pts, rho = level(shared_data, name, k)
    raw = S.reconstruct(lvl, rho)
    surf = S.trim_surface(raw, lvl, rho)
    assert farthest_triangle_point(surf, pts) <= 2.0 * rho
    # and it is a surface of the level, not an empty or token one
    assert surf.n_cells > 20 * k and level_points_near(surf, lvl, rho) > 0.97
    if name == "bun_zipper.ply":
        # what it replaced: VTK's implicit surface alone draws sheets far from the scan
        assert farthest_triangle_point(raw.triangulate(), pts) > 4.0 * rho


def test_trim_keeps_near_triangles_and_drops_far_ones():
    import pyvista as pv

    from lodbuilder.viewer.surface import trim_surface

    # a 1 x 1 grid of points 0.1 apart, and a surface with a triangle on it and one 1.0 above
    g = np.stack(np.meshgrid(np.linspace(0, 1, 11), np.linspace(0, 1, 11)), -1).reshape(-1, 2)
    pts = np.column_stack([g, np.zeros(len(g))])
    verts = np.array(
        [[0.3, 0.3, 0], [0.4, 0.3, 0], [0.3, 0.4, 0], [0.3, 0.3, 1], [0.4, 0.3, 1], [0.3, 0.4, 1]]
    )
    surf = pv.PolyData(verts, np.array([3, 0, 1, 2, 3, 3, 4, 5]))
    out = trim_surface(surf, pts, rho=0.1)
    assert out.n_cells == 1 and np.allclose(np.asarray(out.points)[:, 2], 0)
    # a long triangle whose every point is near the points is still dropped by its edge length
    long = pv.PolyData(np.array([[0.0, 0, 0], [1.0, 0, 0], [0.5, 0.02, 0]]), np.array([3, 0, 1, 2]))
    assert trim_surface(long, pts[pts[:, 1] == 0], rho=0.1).n_cells == 0  # edge 1.0 > 1.5 rho
