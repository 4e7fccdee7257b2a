"""The FastFPS engine: invariants, guarantees, references and degenerate input."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from naive import covering_radius, naive_euclidean_fps
from scipy.spatial import cKDTree
from surfaces import folded_sheet, jittered_plane, sphere

from lodbuilder import euclidean_fps, fastfps
from lodbuilder.errors import InputError, MemoryBudgetError
from lodbuilder.sampling.band import band_distance

EPS = 1e-9


def check_invariants(points: np.ndarray, o) -> None:
    n = len(points)
    assert o.order.dtype == np.int64 and o.parent.dtype == np.int64
    assert np.array_equal(np.sort(o.order), np.arange(n)), "order is not a permutation"
    assert np.isinf(o.radius[0])
    assert np.all(o.radius[1:] <= o.radius[:-1]), "radii increase somewhere"
    pos = np.arange(n)
    assert np.all(o.parent < pos), "a parent comes after its child"
    assert np.all(o.parent >= -1)


def check_covering(points: np.ndarray, o, ks) -> None:
    """Every input point lies within radius[k] (Euclidean) of the first k points."""
    for k in ks:
        if k <= 0 or k >= len(o) or not np.isfinite(o.radius[k]):
            continue
        d, _ = cKDTree(points[o.order[:k]]).query(points, k=1)
        assert d.max() <= o.radius[k] * (1 + EPS) + 1e-12, (k, d.max(), o.radius[k])


shapes = st.sampled_from(["cloud", "plane", "sphere", "line", "two_blobs"])


def make(shape: str, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if shape == "cloud":
        return rng.random((n, 3))
    if shape == "plane":
        return jittered_plane(n, rng)
    if shape == "sphere":
        return sphere(n, rng)
    if shape == "line":
        t = rng.random(n)
        return np.c_[t, 2 * t, -t] * 3.0 + 1.0
    a = rng.normal(0, 0.1, (n // 2, 3))
    b = rng.normal(0, 0.1, (n - n // 2, 3)) + [5.0, 0, 0]
    return np.vstack([a, b])


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(shape=shapes, n=st.integers(2, 400), seed=st.integers(0, 2**31 - 1))
def test_invariants_and_covering(shape, n, seed):
    pts = make(shape, n, seed)
    o = fastfps(pts)
    check_invariants(pts, o)
    ks = np.random.default_rng(seed).integers(1, len(pts), 6)
    check_covering(pts, o, ks)


def test_matches_exact_euclidean_fps_when_everything_is_in_the_tail(rng):
    # a voxel as large as the cloud puts every radius below the hand-over radius: the ordering is
    # then exact Euclidean FPS from the seed, which the naive O(N^2) reference computes too.
    pts = rng.random((300, 3))
    o = fastfps(pts, seeds=[7], voxel_size=2.0)
    order, radius, parent = naive_euclidean_fps(pts, [7])
    assert np.array_equal(o.order, order)
    # stored radii carry the rounding bound of grid-unit arithmetic (sampling/precision.py): never
    # below the exact ones, and above by far less than 1e-9 relative plus the bound's absolute part
    # (ABS * S = 2^-49 * S, the coordinate scale S under 100 here; a radius of 8.5e-6 was 6e-9 relative above)
    assert (o.radius >= radius).all()
    np.testing.assert_allclose(o.radius, radius, rtol=1e-9, atol=1e-12)
    assert np.array_equal(o.parent, parent)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(3, 200), seed=st.integers(0, 2**31 - 1), n_timed=st.integers(1, 20))
def test_timed_seeds_match_the_naive_reference_in_the_tail(n, seed, n_timed):
    # everything in the tail (one voxel for the cloud): the ordering with timed seeds is the exact
    # Euclidean one of the naive reference, timed seeds at their keys included
    r = np.random.default_rng(seed)
    pts = r.random((n, 3))
    idx = r.choice(np.arange(1, n), size=min(n_timed, n - 1), replace=False)
    keys = r.random(idx.size) * 0.8
    o = fastfps(pts, seeds=[0], voxel_size=4.0, timed_seeds=(idx, keys))
    order, radius, parent = naive_euclidean_fps(pts, [0], timed=(idx, keys))
    assert np.array_equal(o.order, order)
    # stored radii carry the rounding bound of grid-unit arithmetic (sampling/precision.py): never
    # below the exact ones, and above by far less than 1e-9 relative plus the bound's absolute part
    # (ABS * S = 2^-49 * S, the coordinate scale S under 100 here; a radius of 8.5e-6 was 6e-9 relative above)
    assert (o.radius >= radius).all()
    np.testing.assert_allclose(o.radius, radius, rtol=1e-9, atol=1e-12)
    assert np.array_equal(o.parent, parent)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(200, 900), seed=st.integers(0, 2**31 - 1), weighted=st.booleans(), n_timed=st.integers(0, 12))
def test_the_tail_over_coarse_cells_matches_the_naive_reference(n, seed, weighted, n_timed):
    # the hand-over radius raised beyond the cloud: the grid phase orders the seed only and the
    # tail does the rest on a fine grid (balls of up to about 40 voxels: the coarse cells and
    # their hash probes, the voxel walk near the end, the heap of cells), with costs and timed
    # seeds (timed seeds and costs exclude each other); the ordering is then the exact (weighted)
    # Euclidean one of the naive reference
    from lodbuilder.sampling import band as band_mod

    r = np.random.default_rng(seed)
    pts = jittered_plane(n, r)
    pts[:, 2] = 0.05 * np.sin(4.0 * pts[:, 0])  # not flat: every axis of the coarse cells
    cost = r.uniform(0.5, 2.0, len(pts)) if weighted else None
    idx = r.choice(np.arange(1, len(pts)), size=n_timed, replace=False)
    keys = r.random(idx.size) * 0.5
    timed = (idx, keys) if n_timed and not weighted else None
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(band_mod, "TAIL_FACTOR", 1e6)
        mp.setattr(band_mod, "TAIL_FACTOR_THIN", 1e6)
        o = fastfps(pts, seeds=[0], voxel_size=1.0 / 30, cost=cost, timed_seeds=timed)
    assert o.stats["grid_points"] == 1
    order, radius, parent = naive_euclidean_fps(pts, [0], cost=cost, timed=timed)
    assert np.array_equal(o.order, order)
    assert (o.radius >= radius).all()
    np.testing.assert_allclose(o.radius, radius, rtol=1e-9, atol=1e-12)
    assert np.array_equal(o.parent, parent)


def test_timed_seeds_join_at_their_key_and_keep_later_points_away(rng):
    # a plane ordered in its band: the left half's points enter at given keys; every point of the
    # right half chosen after a timed seed joined lies at least (about) its radius from it
    pts = jittered_plane(6000, rng)
    left = np.flatnonzero(pts[:, 0] < 0.5)
    ref = fastfps(pts[left])
    keys = np.empty(left.size)
    keys[ref.order] = ref.radius
    keys[~np.isfinite(keys)] = 1.0
    o = fastfps(pts, seeds=[int(np.argmax(pts[:, 0]))], timed_seeds=(left, keys))
    pos = np.empty(len(pts), np.int64)
    pos[o.order] = np.arange(len(o))
    timed_pos = pos[left]
    np.testing.assert_allclose(o.radius[timed_pos], keys, rtol=1e-12)  # radius: the key (in grid units and back)
    # (radius = key and radii never increase: no timed seed joins early or late)
    right = np.flatnonzero(pts[:, 0] >= 0.5)
    # a right point is no nearer to a timed seed that joined before it than 0.97 x its radius
    tree = cKDTree(pts[left])
    for p in right[:: 7]:
        near = tree.query_ball_point(pts[p], 0.97 * o.radius[pos[p]] * (1 - 1e-9))
        assert all(pos[left[j]] > pos[p] for j in near)
    assert o.stats["n_timed_seeds"] == left.size


def test_a_timed_seed_that_is_a_seed_or_its_copy_is_ordered_once(rng):
    # seed 0 is also timed, and point 9 is an exact copy of the timed point 3: each comes once,
    # as the naive reference (which skips what is ordered already) has it
    pts = rng.random((60, 3))
    pts[9] = pts[3]
    idx, keys = np.array([0, 3, 5, 9]), np.array([0.5, 0.4, 0.3, 0.2])
    o = fastfps(pts, seeds=[0], voxel_size=4.0, timed_seeds=(idx, keys))
    assert np.array_equal(np.sort(o.order), np.arange(60))
    order, radius, _ = naive_euclidean_fps(np.delete(pts, 9, axis=0), [0], timed=(np.array([0, 3, 5]), keys[:3]))
    np.testing.assert_array_equal(o.order[:59], np.where(order >= 9, order + 1, order))
    np.testing.assert_allclose(o.radius[:59], radius, rtol=1e-9)  # + the rounding bound (precision.py)
    assert o.order[59] == 9 and o.radius[59] == 0.0  # the copy: after every distinct point
    assert o.stats["n_timed_seeds"] == 2


def test_timed_seeds_are_checked(rng):
    pts = rng.random((50, 3))
    with pytest.raises(InputError, match=r"^timed_seeds needs one non-negative key per index \(2 indices, 1 keys\); "):
        fastfps(pts, timed_seeds=([1, 2], [0.5]))
    with pytest.raises(InputError, match="^timed_seeds cannot be combined with cost; pass one or the other$"):
        fastfps(pts, timed_seeds=([1], [0.5]), cost=np.ones(50))


def test_plane_levels_are_as_good_as_exact_fps(rng):
    pts = jittered_plane(3000, rng)
    o = fastfps(pts)
    order, radius, _ = naive_euclidean_fps(pts, [int(o.order[0])])
    for k in (10, 50, 200, 1000):
        ours = covering_radius(pts, o.order[:k])
        exact = covering_radius(pts, order[:k])
        assert ours <= 1.25 * exact, (k, ours, exact)
        assert ours <= o.radius[k] * (1 + EPS)


def test_band_distance_on_a_plane_is_euclidean_within_one_voxel(rng):
    pts = jittered_plane(6400, rng)
    h = 0.02
    src = int(np.argmin(((pts - [0.5, 0.5, 0]) ** 2).sum(1)))
    d = band_distance(pts, [src], voxel_size=h)
    exact = np.linalg.norm(pts - pts[src], axis=1)
    err = d - exact
    assert np.abs(err).max() <= h, np.abs(err).max()


def test_band_distance_on_a_sphere_follows_the_surface(rng):
    pts = sphere(20000, rng)
    h = 0.04
    d = band_distance(pts, [0], voxel_size=h)
    geo = np.arccos(np.clip(pts @ pts[0], -1, 1))
    # within one voxel of the great-circle distance up to 15 voxels away ...
    near = geo <= 15 * h
    assert np.abs(d[near] - geo[near]).max() <= h
    # ... and beyond, first-order marching adds at most 2 % of the distance
    assert np.all(d - geo <= h + 0.02 * geo)
    # never shorter than the shortest path inside the band's shell (inner radius 1 - r)
    ri = 1 - 2.5 * h
    a = np.arccos(ri)
    shell = np.where(geo > 2 * a, 2 * np.sqrt(1 - ri * ri) + ri * (geo - 2 * a), 2 * np.sin(geo / 2))
    assert np.all(d >= shell - 1e-9)
    # the band follows the surface: across the sphere it is far longer than the chord
    far = geo > 2.5
    assert np.all(d[far] > 1.2 * np.linalg.norm(pts[far] - pts[0], axis=1))


def test_folded_sheet_levels_cover_both_sheets():
    s, gap = 0.01, 0.1
    pts, sheet = folded_sheet(s, gap)
    o = fastfps(pts, voxel_size=s)  # band radius 2.5 s: the sheets' bands stay apart
    check_invariants(pts, o)
    for rho in (1.5 * gap, 2 * gap, 3 * gap):
        k = o.size_for_rho(rho)
        lvl = sheet[o.order[:k]]
        lower, upper = (lvl == 0).sum(), (lvl == 1).sum()
        assert lower > 0 and upper > 0
        assert 0.6 < lower / upper < 1.6, (rho, lower, upper)
    # Euclidean FPS lets one sheet cover the other at such densities
    e = euclidean_fps(pts, rho=3 * gap)
    assert o.size_for_rho(3 * gap) > 1.5 * len(e)


def test_deterministic(rng):
    pts = sphere(3000, rng)
    a, b = fastfps(pts), fastfps(pts)
    assert np.array_equal(a.order, b.order)
    assert np.array_equal(a.radius, b.radius)
    assert np.array_equal(a.parent, b.parent)


def test_early_stop_by_rho_and_size(rng):
    pts = jittered_plane(2000, rng)
    full = fastfps(pts)
    by_rho = fastfps(pts, rho=0.1)
    k = full.size_for_rho(0.1)
    assert len(by_rho) == k
    assert np.array_equal(by_rho.order, full.order[:k])
    assert np.all(by_rho.radius > 0.1)
    check_covering(pts, full, [k])
    by_size = fastfps(pts, size=37)
    assert np.array_equal(by_size.order, full.order[:37])


def test_seeds_come_first_in_the_given_order(rng):
    pts = rng.random((500, 3))
    o = fastfps(pts, seeds=[42, 3, 99])
    assert list(o.order[:3]) == [42, 3, 99]
    assert np.isinf(o.radius[:3]).all() and (o.parent[:3] == -1).all()
    check_invariants(pts, o)
    check_covering(pts, o, [3, 10, 100])


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(shape=shapes, n=st.integers(40, 400), seed=st.integers(0, 2**31 - 1), nseeds=st.integers(2, 30))
def test_many_seeds_marched_together_keep_the_guarantees(shape, n, seed, nseeds):
    # several seeds are marched as one front (the tiled build's head points in a tile): the seeds
    # first, then every invariant, the brute-force covering, and a prefix by size is the full order's
    pts = make(shape, n, seed)
    n = len(pts)  # (a plane has a few points less)
    r = np.random.default_rng(seed)
    seeds = r.choice(n, size=min(nseeds, n - 1), replace=False)
    o = fastfps(pts, seeds=seeds)
    assert np.array_equal(o.order[: seeds.size], seeds)
    assert np.isinf(o.radius[: seeds.size]).all() and (o.parent[: seeds.size] == -1).all()
    check_invariants(pts, o)
    check_covering(pts, o, r.integers(seeds.size, n, 6))
    k = int(r.integers(seeds.size, n + 1))
    assert np.array_equal(fastfps(pts, seeds=seeds, size=k).order, o.order[:k])


def test_the_seeds_are_marched_in_one_round(rng):
    # one march from all the seeds pops each band voxel at most once; one march per seed re-popped
    # most voxels about ln(seeds) times (74 % of a survey tile's grid phase)
    pts = jittered_plane(20_000, rng)
    seeds = rng.choice(len(pts), size=64, replace=False)
    o = fastfps(pts, seeds=seeds, size=64)
    assert np.array_equal(o.order, seeds)
    assert 0 < o.stats["pops"] <= o.stats["band_voxels"]


@pytest.mark.parametrize("n", [1, 2])
def test_tiny_inputs(n):
    pts = np.arange(3 * n, dtype=float).reshape(n, 3)
    o = fastfps(pts)
    check_invariants(pts, o)
    if n == 2:
        assert o.radius[1] == pytest.approx(np.sqrt(27), rel=1e-9)
        assert o.parent[1] == 0


def test_all_identical_points():
    pts = np.ones((50, 3))
    o = fastfps(pts)
    check_invariants(pts, o)
    assert (o.radius[1:] == 0).all() and (o.parent[1:] == 0).all()


def test_exact_duplicates_come_last_with_radius_zero(rng):
    base = rng.random((300, 3))
    dup_of = rng.choice(300, 40, replace=False)
    pts = np.vstack([base, base[dup_of], base[dup_of[:5]]])
    o = fastfps(pts)
    check_invariants(pts, o)
    assert (o.radius[:300] > 0).all() and (o.radius[300:] == 0).all()
    rank = o.rank()
    tail = o.order[300:]
    assert set(tail.tolist()) == set(range(300, 345))
    # each copy points at its first copy, and copies follow the order of their first copy
    firsts = np.r_[dup_of, dup_of[:5]][tail - 300]
    assert np.array_equal(o.parent[300:], rank[firsts])
    assert np.all(np.diff(o.parent[300:]) >= 0)
    check_covering(pts, o, [1, 50, 299, 300, 320])


def test_distinct_float32_points_skip_the_duplicate_sort(rng, monkeypatch):
    """A million distinct points read from float32 files (29 zero bits at the bottom of every
    float64 mantissa) are told apart by the hash alone: the exact sort never runs. The hash before
    mixed those zero bits into nothing and gave a million such points about 14 shared hashes, so
    every float32 scan paid the sort (0.4 s CPU per million points)."""
    from lodbuilder.sampling import fastfps as F

    pts = np.unique(rng.random((1_000_000, 3)).astype(np.float32), axis=0).astype(np.float64)

    def no_sort(*a, **k):
        raise AssertionError("the exact duplicate sort ran on distinct points")

    monkeypatch.setattr(F.np, "lexsort", no_sort)
    assert F._duplicate_groups(pts, np.zeros(1, np.int64)) == (None, None)
    pts[7] = pts[3]  # one copy: the hash sees it, and the sort groups it
    monkeypatch.undo()
    gid, rep = F._duplicate_groups(pts, np.zeros(1, np.int64))
    assert gid is not None and rep is not None and gid[7] == gid[3] and len(rep) == len(pts) - 1


def test_disconnected_objects_are_all_covered(rng):
    a = jittered_plane(900, rng)
    b = jittered_plane(900, rng) + [10.0, 0, 0]
    pts = np.vstack([a, b])
    o = fastfps(pts)
    check_invariants(pts, o)
    # the seed's component is reached by the band; the other component enters at its Euclidean
    # distance to the seed, the largest there is (issue 20: it entered with radius inf before)
    assert np.isinf(o.radius[0]) and np.isfinite(o.radius[1:]).all()
    assert {o.order[0] < 900, o.order[1] < 900} == {True, False}
    d = np.sqrt(((pts - pts[o.order[0]]) ** 2).sum(axis=1))
    assert o.radius[1] == pytest.approx(d.max(), rel=1e-12) and o.parent[1] == 0
    check_covering(pts, o, [2, 10, 100, 1000])


def test_lidar_coordinates_far_from_the_origin(rng):
    pts = jittered_plane(4000, rng) * 20.0 + [500_000.0, 4_000_000.0, 120.0]  # 0.3 m spacing
    o = fastfps(pts)
    check_invariants(pts, o)
    check_covering(pts, o, [5, 100, 3000])
    mm = jittered_plane(2500, rng) * 0.05 + [500_000.0, 4_000_000.0, 120.0]  # 1 mm spacing
    o = fastfps(mm)
    check_invariants(mm, o)
    check_covering(mm, o, [5, 100, 2000])


def test_grid_that_cannot_be_indexed_is_refused(rng):
    pts = np.array([[0.0, 0, 0], [10_000.0, 0, 0], [0, 1e-3, 0]])
    with pytest.raises(InputError, match=r"voxel_size=0.001 would need .* use a voxel_size of at least"):
        fastfps(pts, voxel_size=1e-3)


def test_memory_budget_is_a_clear_error(rng):
    """Before: 'needs more than 18,413 voxels, more than max_memory=0.00 GiB allows (18,413)'."""
    pts = jittered_plane(2000, rng)
    with pytest.raises(MemoryBudgetError) as exc:  # the budget runs out while the band is built
        fastfps(pts, voxel_size=0.001, max_memory=2_000_000)
    assert str(exc.value) == ("voxel_size=0.001 with band_radius=0.0025 needs more voxels than max_memory=1.91 MiB "
                              "allows (18,413); increase voxel_size or max_memory")
    with pytest.raises(MemoryBudgetError) as exc:  # known before the band is built: the occupied cells
        fastfps(pts, voxel_size=0.01, max_memory=200_000)
    assert re.fullmatch(r"voxel_size=0.01 with band_radius=0.025 needs at least [\d,]+ voxels, more than "
                        r"max_memory=0.191 MiB allows \(0\); increase voxel_size or max_memory", str(exc.value))


@pytest.mark.parametrize(
    "points, message",
    [
        (np.zeros((5, 2)), r"points must have shape \(N, 3\), got \(5, 2\)"),
        (np.zeros((0, 3)), r"points is empty"),
        (np.array([[0, 0, np.nan], [1, 1, 1]]), r"1 point\(s\) with NaN or inf coordinates \(first at index 0\)"),
        (np.array([[0, 0, np.inf]]), r"NaN or inf"),
        (np.array([["a", "b", "c"]]), r"points must hold real numbers, got dtype <U1"),
    ],
)
def test_bad_points(points, message):
    with pytest.raises(InputError, match=message):
        fastfps(points)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(rho=0), r"rho must be a finite number > 0, got 0"),
        (dict(rho=float("nan")), r"rho must be a finite number > 0"),
        (dict(size=0), r"size must be between 1 and the number of points \(10\), got 0"),
        (dict(size=11), r"size must be between 1 and the number of points \(10\), got 11"),
        (dict(seeds=[3, 3]), r"seeds contains repeated indices"),
        (dict(seeds=[10]), r"seeds must be indices in \[0, 10\)"),
        (dict(voxel_size=-1), r"voxel_size must be a finite number > 0"),
        (dict(voxel_size=1.0, band_radius=1.0), r"band_radius=1 is too small for voxel_size=1"),
        (dict(cost=np.ones(9)), r"cost must have one value per point, shape \(10,\), got \(9,\)"),
        (dict(cost=-np.ones(10)), r"cost must be finite and > 0"),
    ],
)
def test_bad_options(kwargs, message):
    pts = np.random.default_rng(0).random((10, 3))
    with pytest.raises(InputError, match=message):
        fastfps(pts, **kwargs)


@pytest.mark.parametrize("n", [5, 40, 10_000])  # (a mask of the indices, or a sort where n is much larger)
def test_repeated_indices_are_found_either_way(n):
    from lodbuilder._validate import validate_indices

    rng = np.random.default_rng(n)
    for size in (1, 2, 3, 5):
        idx = rng.choice(n, size=size, replace=False)
        np.testing.assert_array_equal(validate_indices(idx, n, "seeds"), idx)
        with pytest.raises(InputError, match=r"^seeds contains repeated indices; list each point once$"):
            validate_indices(np.append(idx, idx[-1]), n, "seeds")


def test_import_is_light():
    import subprocess
    import sys

    code = (
        "import sys, lodbuilder; lodbuilder.Ordering; "
        "bad = [m for m in ('numba', 'pyvista', 'dask') if m in sys.modules]; print(bad)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_constant_cost_scales_distances_only(rng):
    pts = sphere(3000, rng)
    a = fastfps(pts)
    b = fastfps(pts, cost=np.full(len(pts), 0.5))
    assert np.array_equal(a.order, b.order)
    np.testing.assert_allclose(b.radius[1:], 0.5 * a.radius[1:], rtol=1e-6)
    assert b.stats["grid_points"] == a.stats["grid_points"]


@pytest.mark.data
@pytest.mark.parametrize("name", ["bun000.ply", "bun_zipper.ply", "igea.ply"])
def test_covering_on_real_scans(shared_data, name):
    from lodbuilder.io import read_scan

    pts = read_scan(shared_data / name).points
    o = fastfps(pts)
    check_invariants(pts, o)
    ks = np.r_[1, 2, 10, 100, 1000, np.random.default_rng(1).integers(1, len(pts), 5)]
    check_covering(pts, o, ks)


@settings(max_examples=15, deadline=None)
@given(n=st.integers(1, 40), seed=st.integers(0, 2**31 - 1), rad=st.floats(1.75, 3.5))
def test_band_is_every_voxel_within_r_with_a_true_neighbour_table(n, seed, rad):
    from naive import naive_band_voxels

    from lodbuilder.sampling.band import build_band

    pts = np.random.default_rng(seed).random((n, 3))
    h = 0.1
    band = build_band(pts, h, rad * h)
    got = {tuple(int(x) for x in c) for c in band.coord}
    want = naive_band_voxels(pts, h, rad * h, band.origin)
    for v in got ^ want:  # only voxels exactly on the band's boundary may differ by rounding
        d = np.linalg.norm(band.origin + h * np.array(v) - pts, axis=1).min()
        assert abs(d - rad * h) <= 1e-9 * rad * h, (v, d, rad * h)
    assert np.all(np.diff(band.keys) > 0)  # Morton order, no repeats
    index = {c: i for i, c in enumerate(map(tuple, band.coord.tolist()))}
    steps = [(-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)]
    for i, c in enumerate(map(tuple, band.coord.tolist())):
        for j, s in enumerate(steps):
            assert band.nbr[i, j] == index.get((c[0] + s[0], c[1] + s[1], c[2] + s[2]), -1)
    # every point lies in the cell of its voxel range
    for v in range(band.n_voxels):
        cell = np.floor(band.u[band.cs[v] : band.cs[v + 1]]).astype(int)
        assert np.all(cell == band.coord[v])
    assert band.cs[-1] == n


@settings(max_examples=40, deadline=None)
@given(keys=st.lists(st.integers(0, 300), max_size=60, unique=True), i=st.integers(0, 59), key=st.integers(0, 301))
def test_find_after_is_a_search_of_the_sorted_keys_after_a_position(keys, i, key):
    # the neighbour table's lookup (no hash table): any key after position i, found or -1
    from lodbuilder._kernels.grid import find_after

    arr = np.array(sorted(keys), dtype=np.int64)
    i = min(i, arr.size - 1) if arr.size else -1
    if i >= 0 and arr[i] >= key:
        return  # (only keys larger than the one at i are asked for)
    want = int(np.flatnonzero(arr == key)[0]) if key in keys else -1
    assert find_after(arr, np.int64(i), np.int64(key)) == want


@settings(max_examples=30, deadline=None)
@given(ops=st.lists(st.tuples(st.integers(0, 30), st.floats(0, 100)), min_size=1, max_size=200))
def test_indexed_min_heap_pops_in_key_order(ops):
    from lodbuilder._kernels.heaps import iheap_pop, iheap_push

    hkv = np.empty(31, np.int64)  # one slot per possible item
    hpos = np.full(31, -1, np.int32)
    n = 0
    best: dict[int, float] = {}  # the naive reference: each item's smallest key
    for item, key in ops:
        key = float(np.float32(key))
        if key < best.get(item, np.inf):  # keys only ever decrease, as in the marcher
            best[item] = key
            n = iheap_push(hkv, hpos, n, np.float32(key), item)
    out = []
    while n > 0:
        k, item, n = iheap_pop(hkv, hpos, n)
        out.append((float(k), int(item)))
    assert out == sorted(out)  # by key, equal keys by item
    assert {i: k for k, i in out} == best
    assert (hpos == -1).all()


def test_indexed_min_heap_pops_equal_keys_in_item_order():
    # the marcher's result depends on the order two voxels of equal T are accepted in: it must be
    # the voxel order, not the heap's layout (which depends on the order of the pushes)
    from lodbuilder._kernels.heaps import check_minheap, iheap_pop, iheap_push

    hkv = np.empty(8, np.int64)
    hpos = np.full(8, -1, np.int32)
    n = 0
    for item in [5, 7, 2, 6, 0, 3]:
        n = iheap_push(hkv, hpos, n, np.float32(1.5), item)
    n = iheap_push(hkv, hpos, n, np.float32(0.5), 4)
    n = iheap_push(hkv, hpos, n, np.float32(1.5), 1)
    assert check_minheap(hkv, hpos, n)
    out = []
    while n > 0:
        _, item, n = iheap_pop(hkv, hpos, n)
        out.append(int(item))
    assert out == [4, 0, 1, 2, 3, 5, 6, 7]


@settings(max_examples=30, deadline=None)
@given(
    keys=st.lists(st.floats(0, 100), min_size=1, max_size=60),
    drops=st.lists(st.tuples(st.integers(0, 59), st.floats(0, 1)), max_size=80),
)
def test_max_heap_with_decreasing_keys_pops_the_largest_first(keys, drops):
    from lodbuilder._kernels.heaps import maxheap_build, maxheap_decrease, maxheap_pop

    n = len(keys)
    heap = np.arange(n, dtype=np.int64)
    hkey = np.array(keys, dtype=np.float64)
    pos = np.empty(n, dtype=np.int64)
    maxheap_build(hkey, heap, pos, n)
    ref = dict(enumerate(keys))  # the naive reference: current key of every item
    for item, frac in drops:
        if item < n:
            ref[item] *= frac
            maxheap_decrease(hkey, heap, pos, item, ref[item], n)
    out = []
    while n > 0:
        out.append((hkey[0], int(heap[0])))
        n = maxheap_pop(hkey, heap, pos, n)
    # largest key first; ties by the smaller item
    assert out == sorted(((k, i) for i, k in ref.items()), key=lambda t: (-t[0], t[1]))


# ---- post-conditions, debug heap checks, the Euclidean kernel with cost --------------------------


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda o, r, p: o.__setitem__(3, o[2]), r"an index appears twice"),
        (lambda o, r, p: o.__setitem__(3, 10_000), r"an index out of range"),
        (lambda o, r, p: r.__setitem__(5, r[4] * 2), r"radius increases at position 5"),
        (lambda o, r, p: r.__setitem__(0, 1.0), r"radius\[0\] = 1.0 \(inf expected\)"),
        (lambda o, r, p: p.__setitem__(7, 7), r"parent of position 7 is 7, not an earlier position"),
        (lambda o, r, p: p.__setitem__(7, -2), r"parent of position 7 is -2"),
    ],
)
def test_post_conditions_catch_a_broken_ordering(rng, change, message):
    from lodbuilder.errors import EngineError
    from lodbuilder.sampling.fastfps import check_ordering
    from lodbuilder.sampling.ordering import Ordering

    pts = rng.random((200, 3))
    o = fastfps(pts)
    assert check_ordering(o) is o
    order, radius, parent = o.order.copy(), o.radius.copy(), o.parent.copy()
    change(order, radius, parent)
    broken = Ordering(order, radius, parent, o.voxel_size, o.band_radius, o.seeds, o.n_points)
    with pytest.raises(EngineError, match=r"ordering of 200 points failed its check: " + message):
        check_ordering(broken)


@pytest.mark.parametrize("seeds", [None, np.arange(0, 1500, 50)])
def test_debug_switch_checks_heaps_and_changes_nothing(rng, monkeypatch, seeds):
    # (30 seeds: marched together, in batches, before the checked samples)
    import lodbuilder.sampling.fastfps as ff

    pts = sphere(1500, rng)
    plain = fastfps(pts, seeds=seeds)
    monkeypatch.setattr(ff, "DEBUG", True)
    checked = fastfps(pts, seeds=seeds)
    assert np.array_equal(plain.order, checked.order)
    assert np.array_equal(plain.radius, checked.radius)


def test_heap_checks_notice_a_broken_heap():
    from lodbuilder._kernels.heaps import (
        check_maxheap,
        check_minheap,
        iheap_push,
        maxheap_build,
    )

    hkv = np.empty(10, np.int64)
    hpos = np.full(10, -1, np.int32)
    n = 0
    for item, key in enumerate([5.0, 3.0, 8.0, 1.0, 9.0, 2.0]):
        n = iheap_push(hkv, hpos, n, np.float32(key), item)
    assert check_minheap(hkv, hpos, n)
    swap = [0, n - 1]
    hkv[swap] = hkv[swap[::-1]]  # keys out of order (positions updated: only the order is wrong)
    hpos[hkv[swap] & 0xFFFFFFFF] = swap
    assert not check_minheap(hkv, hpos, n)
    hkv[swap] = hkv[swap[::-1]]
    hpos[hkv[swap] & 0xFFFFFFFF] = swap
    assert check_minheap(hkv, hpos, n)
    hpos[hkv[1] & 0xFFFFFFFF] = 0  # a stale position
    assert not check_minheap(hkv, hpos, n)

    keys = np.array([4.0, 7.0, 1.0, 9.0, 3.0, 6.0, 2.0])
    heap = np.arange(7, dtype=np.int32)
    pos = np.empty(7, np.int32)
    maxheap_build(keys, heap, pos, 7)
    assert check_maxheap(keys, heap, pos, 7)
    keys[0] = -1.0  # the top is no longer the largest
    assert not check_maxheap(keys, heap, pos, 7)


@settings(max_examples=20, deadline=None)
@given(n=st.integers(1, 120), seed=st.integers(0, 2**31 - 1), nseeds=st.integers(1, 3))
def test_euclidean_kernel_with_cost_matches_the_naive_reference(n, seed, nseeds):
    from naive import naive_euclidean_fps_cost

    rng = np.random.default_rng(seed)
    pts = rng.random((n, 3))
    cost = rng.uniform(0.1, 1.0, n)
    seeds = list(rng.choice(n, min(nseeds, n), replace=False))
    o = euclidean_fps(pts, seeds=seeds, cost=cost)
    order, radius, parent = naive_euclidean_fps_cost(pts, [int(s) for s in seeds], cost)
    assert np.array_equal(o.order, order)
    # stored radii carry the rounding bound of grid-unit arithmetic (sampling/precision.py): never
    # below the exact ones, and above by far less than 1e-9 relative plus the bound's absolute part
    # (ABS * S = 2^-49 * S, the coordinate scale S under 100 here; a radius of 8.5e-6 was 6e-9 relative above)
    assert (o.radius >= radius).all()
    np.testing.assert_allclose(o.radius, radius, rtol=1e-9, atol=1e-12)
    assert np.array_equal(o.parent, parent)


# ---- first-run compilation -------------------------------------------------------------------------


def test_every_kernel_is_compiled_for_one_signature_only(rng):
    # the warm-up compiles each kernel for one signature; an ordering (plain, weighted, thin) must
    # not need any other, or a cold first run would compile twice
    from lodbuilder._kernels.warm import _dispatcher, signatures
    from lodbuilder.datasets import folded_sheet

    fastfps(sphere(3000, rng))
    fastfps(sphere(3000, rng), cost=rng.uniform(0.2, 1.0, 3000))
    fastfps(folded_sheet(20000, seed=1, gap=0.05)[0])
    for group in ("band", "ordering", "thin"):
        for name, sig in signatures(group).items():
            assert _dispatcher(name).signatures == [sig], name


@pytest.mark.slow
def test_a_cold_cache_is_compiled_with_a_message(tmp_path):
    # a fresh numba cache: the first ordering compiles (both groups) and says so through the
    # progress callback; the second process finds everything cached
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    code = (
        "import numpy as np, lodbuilder\n"
        "stages = []\n"
        "o = lodbuilder.fastfps(np.random.default_rng(0).random((500, 3)), "
        "progress=lambda s, d, t: stages.append(s))\n"
        "print(o.stats['compiled_kernels'], stages[0])\n"
    )
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), PYTHONPATH=str(root))
    first = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert first.stdout.strip() == "True compiling kernels, first run only"
    second = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert second.stdout.strip() == "False band"


def test_the_cold_cache_check_runs_once_per_process(rng, monkeypatch):
    # the check reads every kernel's cache index: once known warm, later orderings skip it
    from lodbuilder._kernels import warm

    fastfps(sphere(300, rng))
    assert warm._WARM

    def fail() -> bool:
        raise AssertionError("is_cold called again")

    monkeypatch.setattr(warm, "is_cold", fail)
    assert fastfps(sphere(300, rng)).stats["compiled_kernels"] is False


def test_the_compile_child_runs_only_when_a_core_is_free(monkeypatch):
    # on a busy machine a second compiling process only competes with this one (and costs its own
    # start-up and the helpers both compile): compile here instead
    import os

    from lodbuilder._kernels import warm

    monkeypatch.delenv("LODBUILDER_COMPILE_CHILD", raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    monkeypatch.setattr(os, "getloadavg", lambda: (0.4, 0.4, 0.4))
    assert warm._child_helps()
    monkeypatch.setattr(os, "getloadavg", lambda: (1.6, 0.4, 0.4))
    assert not warm._child_helps()
    assert warm.start_ordering_compile() is None
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    monkeypatch.setattr(os, "getloadavg", lambda: (0.0, 0.0, 0.0))
    assert not warm._child_helps()
    monkeypatch.setenv("LODBUILDER_COMPILE_CHILD", "1")
    assert warm._child_helps()
    monkeypatch.setenv("LODBUILDER_COMPILE_CHILD", "0")
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    assert not warm._child_helps()


def test_small_orderings_do_not_trim_the_heap(rng, monkeypatch):
    # malloc_trim walks the heap and the next phase faults the pages in again: a fixed cost that
    # only pays off when the phases free hundreds of MB
    import lodbuilder._resources as F

    calls = []
    monkeypatch.setattr(F, "_LIBC", lambda pad: calls.append(pad))
    fastfps(sphere(500, rng))
    assert calls == []
    F.release_freed_memory(F.TRIM_MIN_POINTS)
    F.release_freed_memory()
    assert calls == [0, 0]


def test_compiling_collects_garbage_less_often_and_restores_the_collector(monkeypatch):
    # numba's compiler makes millions of objects: the collector runs every 10,000 allocations
    # (not 700) over the objects made since, while compiling only
    import gc

    from lodbuilder._kernels import warm

    before = gc.get_threshold(), gc.get_freeze_count()
    seen = []
    monkeypatch.setattr(warm, "signatures", lambda group: {"grid.cell_order": None})
    monkeypatch.setattr(warm, "_dispatcher", lambda name: type("D", (), {
        "compile": staticmethod(lambda sig: seen.append((gc.get_threshold(), gc.get_freeze_count())))
    }))
    warm.compile_group("band")
    assert seen[0][0] == (10_000, 10, 10) and seen[0][1] > 0
    assert (gc.get_threshold(), gc.get_freeze_count()) == before


def test_fewer_collections_nested_leaves_the_outer_freeze_in_place():
    # the build command holds the collector's settings for the whole build, and compiling the
    # kernels inside it holds them again: the inner one must not unfreeze what the outer froze
    import gc

    from lodbuilder._kernels.warm import fewer_collections

    before = gc.get_threshold(), gc.get_freeze_count()
    with fewer_collections():
        frozen = gc.get_freeze_count()
        assert frozen > 0 and gc.get_threshold() == (10_000, 10, 10)
        with fewer_collections():
            assert gc.get_freeze_count() >= frozen
        assert gc.get_freeze_count() >= frozen and gc.get_threshold() == (10_000, 10, 10)
    assert (gc.get_threshold(), gc.get_freeze_count()) == before


def test_progress_bars_print_the_compile_note_without_a_terminal(capsys):
    from lodbuilder.cli.progressbar import ProgressBars

    bars = ProgressBars()  # stderr is not a terminal under pytest: no bars
    assert not bars.enabled
    for stage in ("compiling kernels, first run only", "compiling kernels, first run only", "band"):
        bars(stage, 0, 1)
    assert capsys.readouterr().err == "compiling kernels, first run only ...\n"
    quiet = ProgressBars(enabled=False)  # --no-progress: nothing at all
    quiet("compiling kernels, first run only", 0, 1)
    assert capsys.readouterr().err == ""


def test_default_seed_is_the_point_nearest_the_centroid_lowest_index_first():
    """default_seed: the argmin of the squared distances to the centroid, summed over the axes
    from the left as ((points - c) ** 2).sum(axis=1) does (the same floats, so the same seed on
    near ties), the lowest index among exact ties."""
    from lodbuilder.sampling.fastfps import default_seed

    rng = np.random.default_rng(5)
    for pts in (rng.normal(size=(5000, 3)), rng.normal(size=(5000, 3)) * 1e5 + 4e6,
                np.round(rng.random((5000, 3)) * 8) / 8):
        c = pts.mean(axis=0)
        d2 = [float((p[0] - c[0]) ** 2 + (p[1] - c[1]) ** 2 + (p[2] - c[2]) ** 2) for p in pts]
        assert default_seed(pts) == d2.index(min(d2))
    sym = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    assert default_seed(sym) == 0


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(1, 3000), n_copies=st.integers(0, 3), seed=st.integers(0, 2**31 - 1),
       float32=st.booleans())
def test_hash_collisions_matches_the_naive_reference(n, n_copies, seed, float32):
    # the engine's quick duplicate check (a hash set in one pass) against the sorted hashes
    from naive import naive_hash_collisions

    from lodbuilder._kernels.grid import hash_collisions

    r = np.random.default_rng(seed)
    pts = r.normal(size=(n, 3)) * r.choice([1e-3, 1.0, 1e5])
    if float32:
        pts = pts.astype(np.float32).astype(np.float64)
    pts[r.random((n, 3)) < 0.05] = 0.0
    for _ in range(n_copies):  # exact copies, some with -0.0 for 0.0
        i, j = r.integers(0, n, 2)
        pts[j] = pts[i]
        pts[j][pts[j] == 0.0] = -0.0
    assert hash_collisions(pts) == naive_hash_collisions(pts)
    if n_copies and len(np.unique(pts + 0.0, axis=0)) < n:
        assert hash_collisions(pts)
