"""The point-spacing estimate behind the default voxel size, and the band's shared grid."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from surfaces import folded_sheet, jittered_plane

from lodbuilder.sampling.band import (
    build_band,
    build_planned_band,
    cells,
    grid_origin,
    median_spacing,
    plan_band,
    sheet_separation,
)


def _kth_reference(points: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    return cKDTree(points).query(queries, k=[k])[0][:, 0]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(2, 400),
    k=st.integers(1, 9),
    cell=st.floats(0.05, 0.6),
    kind=st.sampled_from(["cloud", "plane", "clusters"]),
)
def test_kth_neighbour_matches_a_kd_tree(seed, n, k, cell, kind):
    """The grid search (cells visited nearest first, farther ones pruned) finds the same k-th
    distance as a k-d tree wherever it says it is sure, and never a smaller one elsewhere."""
    from lodbuilder._kernels.grid import kth_neighbour

    rng = np.random.default_rng(seed)
    if kind == "cloud":
        pts = rng.random((n, 3))
    elif kind == "plane":
        pts = np.c_[rng.random((n, 2)), np.zeros(n)]
    else:  # tight clusters with exact duplicates
        centres = np.repeat(rng.random((n // 4 + 1, 3)), 4, axis=0)[:n]
        pts = centres + rng.normal(0, 0.01, (n, 3)) * (rng.random((n, 1)) < 0.5)
    k = min(k, n)
    origin = pts.min(axis=0) - cell
    keys, _, u, ostart = cells(pts, origin, cell)
    queries = np.vstack([pts[: n // 2], rng.random((20, 3))])
    dk, sure = kth_neighbour(u, ostart, keys[ostart[:-1]], (queries - origin) / cell, k)
    ref = _kth_reference(pts, queries, k) / cell
    assert np.allclose(dk[sure], ref[sure], rtol=1e-12, atol=1e-12)
    assert np.all(dk >= ref - 1e-12)
    assert np.array_equal(sure, np.isfinite(dk) & (dk <= 1.0))


def test_median_spacing_is_the_kd_tree_figure():
    """median_spacing equals the same statistic computed with a k-d tree on the same sample."""
    rng = np.random.default_rng(3)
    pts = jittered_plane(30_000, rng)
    s = median_spacing(pts)
    q = pts[np.random.default_rng(0).choice(len(pts), 20_000, replace=False)]
    ref = float(np.median(_kth_reference(pts, q, 7))) * math.sqrt(math.pi / 6)
    assert s == np.float64(ref) or abs(s - ref) <= 1e-12 * ref


def test_the_sheet_grid_is_the_band_grid():
    """plan_band sorts the points into the band's grid once: the band built from the plan equals
    one built from scratch, and the separation measured on the shared cells equals the one
    measured without them."""
    pts = folded_sheet(0.01, gap=0.03)[0]
    plan = plan_band(pts, None, None)
    assert plan.normal is not None and plan.sorted_cells is not None
    shared = plan.sorted_cells
    sep_shared = sheet_separation(pts, plan.h, plan.r, shared)
    sep_own = sheet_separation(pts, plan.h, plan.r)
    for a, b in zip(sep_shared, sep_own, strict=True):
        assert np.array_equal(a, b)
    origin = grid_origin(pts, plan.h, plan.r)
    assert np.array_equal(shared[2], cells(pts, origin, plan.h)[2])
    band, plan2 = build_planned_band(pts, plan)
    assert plan2.sorted_cells is None
    ref = build_band(pts, plan.h, plan.r)
    for name in ("u", "perm", "keys", "nbr", "cs", "foot"):
        assert np.array_equal(getattr(band, name), getattr(ref, name)), name
