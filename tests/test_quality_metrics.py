"""Quality metrics against hand-computable cases (a grid, a sphere) and the naive references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from surfaces import fibonacci_sphere

from lodbuilder.errors import InputError
from lodbuilder.quality import (
    chamfer,
    covering_radius,
    evaluate_level,
    evaluate_prefixes,
    hausdorff,
    meets_rho,
    prefix_sizes,
    spacing,
    surface_error,
    uniformity,
)
from tests.naive import covering_radius as naive_covering_radius


def grid(n: int = 10) -> np.ndarray:
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    return np.column_stack([i.ravel(), j.ravel(), np.zeros(n * n)]).astype(float)


def even_subgrid(pts: np.ndarray) -> np.ndarray:
    keep = (pts[:, 0] % 2 == 0) & (pts[:, 1] % 2 == 0)
    return pts[keep]


def test_grid_metrics_by_hand():
    pts = grid(10)
    lev = even_subgrid(pts)  # 5 x 5 points at even coordinates
    assert lev.shape == (25, 3)
    # odd-odd points (e.g. (1, 1), (9, 9)) are sqrt(2) from the nearest even-even point
    assert covering_radius(pts, lev) == pytest.approx(math.sqrt(2))
    h = hausdorff(pts, lev)
    assert h.input_to_level == pytest.approx(math.sqrt(2))
    assert h.level_to_input == 0.0
    assert h.value == pytest.approx(math.sqrt(2))
    # 25 points at 0, 50 at distance 1, 25 at sqrt(2)
    c = chamfer(pts, lev)
    assert c.input_to_level == pytest.approx((50 + 25 * math.sqrt(2)) / 100)
    assert c.level_to_input == 0.0
    assert c.value == pytest.approx(0.5 * (50 + 25 * math.sqrt(2)) / 100)
    sp = spacing(lev)
    assert (sp.min, sp.mean, sp.max) == (pytest.approx(2.0), pytest.approx(2.0), pytest.approx(2.0))
    assert uniformity(sp.min, math.sqrt(2)) == pytest.approx(math.sqrt(2))
    # every point lies on the plane z = 0
    assert np.abs(surface_error(pts, lev)).max() < 1e-12
    assert np.abs(surface_error(pts, lev, method="mls")).max() < 1e-9


def test_grid_level_not_subset_of_input():
    pts = grid(4)
    lev = pts + np.array([0.0, 0.0, 0.25])  # the same grid lifted by 0.25
    h = hausdorff(pts, lev)
    assert h.input_to_level == pytest.approx(0.25)
    assert h.level_to_input == pytest.approx(0.25)
    assert chamfer(pts, lev).value == pytest.approx(0.25)
    np.testing.assert_allclose(surface_error(pts, lev), 0.25, atol=1e-12)


def test_octahedron_covers_sphere_by_hand():
    dense = fibonacci_sphere(4000)
    corners = np.array([[1, 1, 1], [-1, 1, 1], [1, -1, -1], [-1, -1, 1]]) / math.sqrt(3)
    pts = np.vstack([dense, corners])
    lev = np.vstack([np.eye(3), -np.eye(3)])
    # farthest point of the sphere from the six axis points: a face centre (1,1,1)/sqrt(3)
    expected = math.sqrt(2 - 2 / math.sqrt(3))
    assert covering_radius(pts, lev) == pytest.approx(expected, rel=1e-12)
    assert naive_covering_radius(
        np.vstack([pts, lev]), np.arange(pts.shape[0], pts.shape[0] + 6)
    ) == (pytest.approx(expected, rel=1e-12))
    # the level points lie on the input sphere up to the Fibonacci lattice's spacing
    assert hausdorff(pts, lev).level_to_input < 0.05


def test_sphere_surface_error_offset_shell():
    level = fibonacci_sphere(20000, radius=1.0)
    shell = fibonacci_sphere(500, radius=1.05)  # every input point 0.05 off the unit sphere
    plane = surface_error(shell, level, k=8)
    mls = surface_error(shell, level, method="mls", k=16)
    # MLS fits the curvature: error ~ 0.05 within a small fraction of the neighbour spacing
    np.testing.assert_allclose(mls, 0.05, atol=2e-4)
    # the plane of 8 neighbours (ring radius a ~ 0.03) lies inside the sphere by about a^2 / 2
    assert np.all(plane >= 0.05) and np.all(plane < 0.0505)
    assert np.abs(mls - 0.05).mean() < np.abs(plane - 0.05).mean()


def test_surface_error_small_levels_fall_back():
    pts = grid(3)
    one = pts[:1]
    np.testing.assert_allclose(surface_error(pts, one), np.linalg.norm(pts - pts[0], axis=1))
    # 4 coplanar points: MLS needs 6, falls back to the plane (exact here)
    assert surface_error(pts, pts[[0, 2, 6, 8]], method="mls").max() < 1e-12


def test_matches_naive_covering_radius(rng):
    pts = rng.normal(size=(500, 3))
    kept = rng.choice(500, size=37, replace=False)
    assert covering_radius(pts, pts[kept]) == pytest.approx(
        naive_covering_radius(pts, kept), rel=1e-12
    )


def test_meets_rho():
    assert meets_rho(1.0, 1.0) is True
    assert meets_rho(1.0 + 1e-6, 1.0) is False
    assert meets_rho(0.0, 0.0) is True
    assert meets_rho(1.0, None) is None
    assert meets_rho(1.0, math.inf) is None


def test_uniformity_edges():
    assert uniformity(0.0, 0.0) == 1.0
    assert uniformity(1.0, 0.0) == math.inf
    assert uniformity(1.0, 2.0) == 0.5
    assert spacing(np.zeros((1, 3))).min == math.inf
    assert spacing(np.zeros((2, 3))).min == 0.0  # duplicates


def test_evaluate_level_report_fields():
    pts = grid(10)
    lev = even_subgrid(pts)
    rep = evaluate_level(pts, lev, rho=1.5, label="even")
    assert rep.size == 25 and rep.fraction == 0.25
    assert rep.covering_radius == pytest.approx(math.sqrt(2))
    assert rep.meets_rho is True
    assert rep.min_spacing == pytest.approx(2.0)
    assert rep.uniformity == pytest.approx(math.sqrt(2))
    assert rep.surface_error["max"] < 1e-12
    assert rep.diagonal == pytest.approx(math.sqrt(2) * 9)
    d = rep.as_dict()
    assert d["label"] == "even" and d["meets_rho"] is True
    assert evaluate_level(pts, lev, rho=1.4).meets_rho is False
    one = evaluate_level(pts, lev[:1]).as_dict()
    assert one["min_spacing"] == "inf"  # lodbuilder's one JSON convention (lodbuilder._json)


def test_guarantee_flags_thinned_level(rng):
    from lodbuilder import euclidean_fps

    pts = rng.random((2000, 3)) * np.array([1.0, 1.0, 0.05])
    ordering = euclidean_fps(pts)
    reps = evaluate_prefixes(pts, ordering.order, ordering.radius, sizes=[10, 100, 500, 2000])
    assert [r.meets_rho for r in reps] == [True, True, True, True]
    assert all(r.uniformity >= 1.0 - 1e-12 for r in reps[:3])
    # thin the 100-point level: drop every other point, keep its claim
    k = 100
    thinned = pts[ordering.order[:k:2]]
    rep = evaluate_level(pts, thinned, rho=float(ordering.radius[k]))
    assert rep.meets_rho is False
    assert rep.covering_radius > ordering.radius[k]
    # dropping just the last point added is caught too: its own cell is no longer covered
    rep1 = evaluate_level(pts, pts[ordering.order[: k - 1]], rho=float(ordering.radius[k]))
    assert rep1.meets_rho is False


def test_prefix_sizes():
    radius = np.array([np.inf, 4.0, 3.0, 3.0, 1.0, 0.5])
    assert prefix_sizes(radius, 6, sizes=[1, 2, 6]) == [(1, 4.0), (2, 3.0), (6, 0.0)]
    # rho 3: the first prefix whose next radius is <= 3 has 2 points
    assert prefix_sizes(radius, 6, rhos=[3.0, 0.75, 10.0]) == [(2, 3.0), (5, 0.75), (1, 10.0)]
    assert prefix_sizes(radius, 6, fractions=[0.5]) == [(3, 3.0)]
    # halves go up, as for every level (lodbuilder.levels.size_for_fraction): 2.5 -> 3
    assert prefix_sizes(radius[:5], 5, fractions=[0.5]) == [(3, 3.0)]
    with pytest.raises(InputError, match=r"fraction 0.9 is 7 points, more than the 5 the ordering"):
        prefix_sizes(radius[:5], 8, fractions=[0.9])
    # a truncated ordering (5 of 8 points) claims nothing at its end
    assert prefix_sizes(radius[:5], 8, sizes=[5]) == [(5, None)]
    with pytest.raises(InputError, match="finer than the ordering reaches"):
        prefix_sizes(radius[:5], 8, rhos=[0.1])
    with pytest.raises(
        InputError, match=r"size must be between 1 and the number of points \(6\), got 7"
    ):
        prefix_sizes(radius, 6, sizes=[7])
    with pytest.raises(InputError, match="rho must be a finite number > 0, got -1"):
        prefix_sizes(radius, 6, rhos=[-1])


def test_errors_name_the_input():
    pts = grid(3)
    with pytest.raises(InputError, match=r"level must have shape \(N, 3\), got \(4,\)"):
        covering_radius(pts, np.zeros(4))
    with pytest.raises(InputError, match="method must be one of plane, mls, got 'rbf'"):
        surface_error(pts, pts, method="rbf")
    with pytest.raises(InputError, match="k must be a whole number of neighbours >= 3, got 2"):
        surface_error(pts, pts, k=2)
    with pytest.raises(InputError, match="rho must be a number >= 0, got nan"):
        evaluate_level(pts, pts, rho=float("nan"))
    with pytest.raises(InputError, match=r"order and radius must have the same shape"):
        evaluate_prefixes(pts, np.arange(9), np.ones(8))
