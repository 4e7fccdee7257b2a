"""The point-spacing estimate behind the default voxel size."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from surfaces import folded_sheet, jittered_plane

from lodbuilder.errors import MemoryBudgetError
from lodbuilder.sampling import band, spacing
from lodbuilder.sampling.band import cells, median_spacing, plan_and_build_band


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
    dk, sure = kth_neighbour(u, ostart, keys, (queries - origin) / cell, k)
    ref = _kth_reference(pts, queries, k) / cell
    assert np.allclose(dk[sure], ref[sure], rtol=1e-12, atol=1e-12)
    assert np.all(dk >= ref - 1e-12)
    assert np.array_equal(sure, np.isfinite(dk) & (dk <= 1.0))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(0, 3000),
    bits=st.sampled_from([0, 1, 5, 14, 15, 29, 40, 62]),
    distinct=st.integers(1, 50),
    order=st.sampled_from(["random", "sorted", "nearly sorted", "reversed"]),
)
def test_sorted_keys_sorts_as_a_stable_sort(seed, n, bits, distinct, order):
    """The cells' sort (the radix sort, or NumPy's merge sort for nearly sorted keys) gives the
    permutation of a stable sort (equal keys in index order) and the keys in that order: with
    many ties, one key for all, keys of up to 62 bits, none or one key."""
    from naive import naive_stable_argsort

    from lodbuilder._kernels.grid import radix_argsort

    rng = np.random.default_rng(seed)
    pool = rng.integers(0, 2**bits, distinct, dtype=np.int64) if bits else np.zeros(distinct, np.int64)
    keys = pool[rng.integers(0, distinct, n)]
    if order == "sorted":
        keys = np.sort(keys)
    elif order == "nearly sorted":
        keys = np.sort(keys)
        swap = rng.integers(0, max(n - 1, 1), n // 200 + 1)
        if n > 1:
            keys[swap], keys[swap + 1] = keys[swap + 1].copy(), keys[swap].copy()
    elif order == "reversed":
        keys = np.sort(keys)[::-1].copy()
    ref = naive_stable_argsort(keys)
    for sk, perm in (radix_argsort(keys), spacing.sorted_keys(keys)):
        assert perm.dtype == np.int32
        assert np.array_equal(perm, ref)
        assert np.array_equal(sk, keys[ref])


def test_median_spacing_is_the_kd_tree_figure():
    """median_spacing equals the same statistic computed with a k-d tree on the same sample."""
    rng = np.random.default_rng(3)
    pts = jittered_plane(30_000, rng)
    s = median_spacing(pts)
    q = pts[np.random.default_rng(0).choice(len(pts), 20_000, replace=False)]
    ref = float(np.median(_kth_reference(pts, q, 7))) * math.sqrt(math.pi / 6)
    assert s == np.float64(ref) or abs(s - ref) <= 1e-12 * ref


def test_two_threads_answer_like_one(monkeypatch):
    """The spacing's neighbour queries split over two threads give the same figure as one."""
    pts = jittered_plane(30_000, np.random.default_rng(5))
    monkeypatch.setattr(spacing, "_cores", lambda: 2)
    two = median_spacing(pts)
    monkeypatch.setattr(spacing, "_cores", lambda: 1)
    assert median_spacing(pts) == two


def test_the_band_built_meanwhile_is_the_band_built_after(monkeypatch):
    """plan_and_build_band builds the plain band on a second thread while the sheets are measured
    (small inputs, two cores): the same band and plan as one after the other."""
    pts = folded_sheet(0.01, gap=0.03)[0]
    monkeypatch.setattr(band, "OVERLAP_MIN_POINTS", 0)
    results = []
    for cores, limit in ((2, band.OVERLAP_MAX_POINTS), (1, 0)):
        monkeypatch.setattr(band, "_cores", lambda c=cores: c)
        monkeypatch.setattr(band, "OVERLAP_MAX_POINTS", limit)
        results.append(plan_and_build_band(pts, None, None))
    (b1, p1, f1), (b2, p2, f2) = results
    assert f1 == f2 > 0 and p1.thin_points == p2.thin_points
    for name in ("u", "perm", "keys", "nbr", "cs", "vcost", "foot", "near"):
        assert np.array_equal(getattr(b1, name), getattr(b2, name)), name
    assert np.array_equal(p1.separation, p2.separation) and p1.handover == p2.handover


def test_a_band_too_big_for_the_budget_fails_the_same_on_the_second_thread(monkeypatch):
    """The plain band's error (built on the second thread) reaches the caller as before."""
    monkeypatch.setattr(band, "_cores", lambda: 2)  # the second thread whatever the machine
    monkeypatch.setattr(band, "OVERLAP_MIN_POINTS", 0)
    pts = jittered_plane(5_000, np.random.default_rng(2))
    with pytest.raises(MemoryBudgetError, match="increase voxel_size or max_memory"):
        plan_and_build_band(pts, None, None, max_memory=1_000_000)


def test_small_inputs_build_the_band_in_this_thread(monkeypatch):
    """Below OVERLAP_MIN_POINTS points the plain band is built after the sheets, in this thread (a
    second thread costs more than it saves there), even with two cores; above it, on the second."""
    import concurrent.futures

    started = []

    class Recording(concurrent.futures.ThreadPoolExecutor):
        def submit(self, fn, /, *args, **kwargs):
            started.append(getattr(fn, "__name__", "?"))
            return super().submit(fn, *args, **kwargs)

    monkeypatch.setattr(concurrent.futures, "ThreadPoolExecutor", Recording)
    monkeypatch.setattr(band, "_cores", lambda: 2)
    pts = folded_sheet(0.045, gap=0.14)[0]  # 1,056 points, all thin
    assert len(pts) < band.OVERLAP_MIN_POINTS
    _, plan, found = plan_and_build_band(pts, None, None)
    assert found > 0 and "build_band" not in started
    monkeypatch.setattr(band, "OVERLAP_MIN_POINTS", len(pts))
    plan_and_build_band(pts, None, None)
    assert "build_band" in started


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_axis_min_and_max_are_numpys_along_the_first_axis(dtype):
    # (column by column, for speed: the same values, dtype and shape as points.min(axis=0))
    rng = np.random.default_rng(3)
    pts = (rng.normal(size=(1001, 3)) * [1e5, 1.0, 1e-3]).astype(dtype)
    pts[17] = [-0.0, np.float32(3e38), -5e-300]  # signed zero, large, tiny
    lo, hi = spacing.axis_min(pts), spacing.axis_max(pts)
    for got, want in ((lo, pts.min(axis=0)), (hi, pts.max(axis=0))):
        assert got.dtype == want.dtype and got.shape == (3,)
        assert np.array_equal(got, want)
