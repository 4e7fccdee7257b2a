"""tools/bench_fill.py's oracle (issue 21): the least-squares surface of each class fitted to the
removed points themselves, checked on surfaces whose answer is known."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import bench_fill  # noqa: E402


def _grid(height) -> np.ndarray:
    g = np.arange(-8.0, 8.0001, 0.1)
    u, v = (a.ravel() for a in np.meshgrid(g, g))
    return np.c_[u, v, height(u, v)]


def _oracle(points: np.ndarray, radius: float) -> dict:
    removed = np.flatnonzero(np.hypot(points[:, 0], points[:, 1]) < radius)
    normals = bench_fill.pca_normals(points)
    return bench_fill.oracle_errors(points, None, normals, removed, np.array([0, 0, 1.0]), 1.0)


def test_the_oracle_of_a_paraboloid():
    """h = 0.02 (u^2 + v^2) over a hole of radius 4 (rho 1): h runs 0..0.32 over the hole, its
    least-squares plane is h = 0.16, missed by 0.16 at the centre and the rim; the quadric and
    the cubic fit it exactly."""
    out = _oracle(_grid(lambda u, v: 0.02 * (u * u + v * v)), 4.0)
    assert abs(out["oracle_plane_max_rho"] - 0.16) < 0.01
    assert out["oracle_quadric_max_rho"] < 0.005
    assert out["oracle_cubic_max_rho"] < 0.005


def test_the_oracle_of_a_cubic():
    """h = 0.005 u^3: the plane and the quadric miss it (odd: the quadric is no better than the
    plane's slope), the cubic does not."""
    out = _oracle(_grid(lambda u, v: 0.005 * u**3), 4.0)
    assert out["oracle_quadric_max_rho"] > 0.05
    assert out["oracle_cubic_max_rho"] < 0.005


def test_oracle_summary_counts_holes_within_a_quarter_rho():
    holes = [
        {"oracle_plane_max_rho": 0.3, "synthetic_error_max_rho": 0.2},
        {"oracle_plane_max_rho": 0.1, "synthetic_error_max_rho": None},
    ]
    out = bench_fill.oracle_summary(holes)
    assert out["plane"] == {"holes": 2, "share_within_0.25": 0.5, "max": 0.3}
    assert out["fill"] == {"holes": 1, "share_within_0.25": 1.0, "max": 0.2}


def test_only_points_over_the_original_surface_are_measured():
    """A ball of radius 3 punched in a plane z = 0 where the scan has a hole of its own (radius
    2.5, centre 3.5 from the ball's): synthetic points filling that hole within the ball's reach
    lie over surface the original does not have (their distance to the original, to the edge of
    its hole, is no error). Counted, such a point was the bunny's worst, 0.68 rho (seed 8), on a
    hole a fit to its rim misses by 0.07 rho. Points over the punched surface count however far
    off it they lie."""
    plane = _grid(lambda u, v: 0.0 * u)
    original = plane[np.hypot(plane[:, 0], plane[:, 1] - 3.5) >= 2.5]
    syn = np.array(
        [[0.0, 0.0, 0.0], [0.0, 0.5, 0.9], [2.0, -1.0, -1.5], [0.0, 1.3, 0.0], [0.0, 2.5, 0.2]]
    )
    normals = bench_fill.pca_normals(original)
    assert bench_fill.over_surface(syn, original, normals, 1.0).tolist() == [1, 1, 1, 1, 0]
    assert bench_fill.over_surface(syn, original, normals, 0.4).tolist() == [1, 1, 1, 0, 0]
    assert bench_fill.over_surface(syn[:0], original, normals, 1.0).shape == (0,)


def test_refusing_by_fit_residual_counts_every_hole():
    """The share is of every hole (unfilled ones and those without a fit count as refused), the
    error of the filled holes kept."""
    holes = [
        {"filled": True, "fit_residual_rho": 0.05, "synthetic_error_max_rho": 0.1},
        {"filled": True, "fit_residual_rho": 0.18, "synthetic_error_max_rho": 0.6},
        {"filled": False, "fit_residual_rho": 0.05, "synthetic_error_max_rho": None},
        {"filled": False, "synthetic_error_max_rho": None},
    ]
    out = bench_fill.refusal_tradeoff(holes)
    assert out["0.1"] == {"holes_filled_percent": 25.0, "synthetic_error_max_rho": 0.1}
    assert out["0.2"] == {"holes_filled_percent": 50.0, "synthetic_error_max_rho": 0.6}
    assert bench_fill.refusal_tradeoff([])["0.1"]["synthetic_error_max_rho"] is None


def test_a_holes_fit_is_that_of_the_gap_with_most_candidates_in_it():
    """The gap with synthetic points and the most candidates within r + rho of the hole's
    centre names the fit; none: no entry."""
    from types import SimpleNamespace

    from lodbuilder.fill.surface import HeightField

    flat = HeightField(np.random.default_rng(0).uniform(-5, 5, (50, 2)), np.zeros(50), 1.0)

    def gap(x, n_syn, residual):
        cand = np.c_[np.full(10, x), np.zeros((10, 2))]
        return SimpleNamespace(
            candidates=cand, n_synthetic=n_syn, implicit=False, surface=flat, residual=residual
        )

    report = SimpleNamespace(gaps=[gap(0.0, 3, 0.2), gap(0.5, 0, 0.3), gap(9.0, 5, 0.4)])
    out = bench_fill.hole_fit(report, np.zeros(3), 1.0, 1.0)
    assert out == {"fit": "thin_plate_spline", "fit_residual_rho": 0.2}
    assert bench_fill.hole_fit(report, np.array([50.0, 0, 0]), 1.0, 1.0) == {}


import fill_bounds  # noqa: E402


def _truth(points: np.ndarray, keep: np.ndarray, radius: float, distance) -> dict:
    normals = bench_fill.pca_normals(points)
    return fill_bounds.truth_errors(points, keep, normals, np.zeros(3), radius, 1.0, distance)


def _sphere(radius: float, n: int, seed: int = 0) -> np.ndarray:
    """n points on the cap z > 0 of a sphere of ``radius`` centred at (0, 0, -radius)."""
    x = np.random.default_rng(seed).normal(size=(4 * n, 3))
    x = radius * x / np.linalg.norm(x, axis=1, keepdims=True)
    x = x[x[:, 2] > 0.7 * radius][:n]
    return x - np.array([0.0, 0.0, radius])


def test_thinned_points_are_step_apart_and_cover_the_rest():
    x = np.random.default_rng(1).uniform(0, 10, (2000, 2))
    kept = fill_bounds.thin(x, 0.5)
    d = np.linalg.norm(x[kept][:, None] - x[kept][None], axis=2)
    assert d[np.triu_indices(kept.size, 1)].min() >= 0.5
    assert np.linalg.norm(x[:, None] - x[kept][None], axis=2).min(axis=1).max() <= 0.5


def test_on_a_sphere_every_bound_is_near_zero():
    """A hole of radius 4 (rho 1) at the top of a sphere of radius 20: every surface of the
    bounds (the local and the quartic truth, the rim quadrics) follows the sphere within 0.05 rho
    (the sphere is no polynomial: not exactly)."""
    pts = _sphere(20.0, 20000)
    keep = np.hypot(pts[:, 0], pts[:, 1]) >= 4.0

    def distance(q):
        return np.abs(np.linalg.norm(q + np.array([0.0, 0.0, 20.0]), axis=1) - 20.0)

    out = _truth(pts, keep, 4.0, distance)
    assert set(out) == {
        "truth_local_max_rho",
        "truth_quartic_max_rho",
        "rim_best_max_rho",
        "rim_cv_max_rho",
    }
    assert max(out.values()) < 0.05


def test_a_bump_hidden_in_the_hole_is_missed_by_the_rim_only():
    """A Gaussian bump 1 rho high (sigma 1 rho) in the middle of a hole of radius 4 in a plane:
    the rim is flat, so every rim fit misses the bump's top by about its height; the truth read
    at rho resolution follows it within 0.1 rho; the quartic through the hole's true points does
    not fit so narrow a bump (over 0.25 rho off)."""
    pts = _grid(lambda u, v: np.exp(-(u * u + v * v) / 2.0))
    keep = np.hypot(pts[:, 0], pts[:, 1]) >= 4.0
    fine = _grid(lambda u, v: np.exp(-(u * u + v * v) / 2.0))
    tree = bench_fill.cKDTree(fine)

    out = _truth(pts, keep, 4.0, lambda q: tree.query(q)[0])
    assert out["truth_local_max_rho"] < 0.1
    assert out["truth_quartic_max_rho"] > 0.25
    assert 0.8 < out["rim_best_max_rho"] < 1.05
    assert out["rim_cv_max_rho"] >= out["rim_best_max_rho"]


def test_a_hole_with_few_removed_points_has_no_bounds():
    pts = _grid(lambda u, v: 0.0 * u)
    keep = np.hypot(pts[:, 0], pts[:, 1]) >= 0.15
    assert _truth(pts, keep, 0.15, lambda q: np.abs(q[:, 2])) == {}


def test_the_distribution_counts_filled_holes_over_a_quarter_rho():
    holes = [
        {
            "filled": True,
            "radius_rho": 2.0,
            "synthetic_error_max_rho": 0.3,
            "oracle_plane_max_rho": 0.2,
        },
        {
            "filled": True,
            "radius_rho": 4.0,
            "synthetic_error_max_rho": 0.25,
            "oracle_plane_max_rho": 0.7,
        },
        {
            "filled": True,
            "radius_rho": 4.9,
            "synthetic_error_max_rho": 0.9,
            "oracle_plane_max_rho": 1.2,
        },
        {"filled": False, "radius_rho": 3.0, "synthetic_error_max_rho": 0.9},
        {"filled": True, "radius_rho": 3.0, "synthetic_error_max_rho": None},
    ]
    out = fill_bounds.hole_distribution(holes)
    assert out["all"] == {"filled": 3, "over_0.25": 2}
    assert out["by_radius"] == {
        "1.5-2.5 rho": {"filled": 1, "over_0.25": 1},
        "2.5-3.5 rho": {"filled": 0, "over_0.25": 0},
        "3.5-5 rho": {"filled": 2, "over_0.25": 1},
    }
    assert out["by_sagitta"] == {
        "0-0.5 rho": {"filled": 1, "over_0.25": 1},
        "0.5-1 rho": {"filled": 1, "over_0.25": 0},
        "1-99 rho": {"filled": 1, "over_0.25": 1},
    }


def test_the_refusal_bound_keeps_only_filled_holes_within_a_quarter_rho():
    holes = [
        {"filled": True, "synthetic_error_max_rho": 0.2, "truth_local_max_rho": 0.1},
        {"filled": True, "synthetic_error_max_rho": 0.4, "truth_local_max_rho": 0.3},
        {"filled": False, "synthetic_error_max_rho": 0.1},
        {"filled": True, "synthetic_error_max_rho": None},
    ]
    out = fill_bounds.refusal_bound(holes)
    assert out == {
        "holes_kept_percent": 25.0,
        "over_0.25": {"truth_local": {"holes": 2, "over": 1, "max": 0.3}},
    }


def test_distances_to_the_part_of_the_mesh_near_a_hole_are_those_to_the_whole_mesh():
    """A bumpy grid mesh (spacing 0.25): points within 5 of a centre, up to 1 off the surface,
    are as far from the faces whose vertices lie within 8 of it as from every face."""
    pytest.importorskip("point_cloud_utils")
    g = np.arange(-12.0, 12.001, 0.25)
    n = g.size
    u, v = (a.ravel() for a in np.meshgrid(g, g))
    verts = np.c_[u, v, np.sin(u) * np.cos(0.7 * v)]
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    faces = np.r_[np.c_[i, i + 1, i + n], np.c_[i + 1, i + n + 1, i + n]]
    rng = np.random.default_rng(3)
    q = rng.uniform(-3.5, 3.5, (200, 3))
    q[:, 2] = np.sin(q[:, 0]) * np.cos(0.7 * q[:, 1]) + rng.uniform(-1, 1, 200)
    centre = np.array([0.5, -0.5, 0.0])
    part = fill_bounds.near_mesh(verts, faces, centre, 8.0)
    assert part[1] is not None and 0 < part[1].shape[0] < faces.shape[0]
    near, _ = bench_fill.surface_distance(q, *part)
    full, _ = bench_fill.surface_distance(q, verts, faces)
    np.testing.assert_allclose(near, full, rtol=0, atol=1e-12)
    pts, none = fill_bounds.near_mesh(verts, None, centre, 8.0)
    assert none is None and np.linalg.norm(pts - centre, axis=1).max() < 8.0
