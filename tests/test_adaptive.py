"""Weighted FastFPS, the density floor and its instant query, outlier exclusion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lodbuilder import fastfps
from lodbuilder.errors import InputError
from lodbuilder.features import combine_maps, cost_from_weights, noise_score, surface_variation
from lodbuilder.sampling.adaptive import (
    build_orderings,
    density_floor_ordering,
    floor_query,
    floor_query_arrays,
    weighted_ordering,
)


def flat_and_curved(half=48, r=6.0, jitter=0.2, seed=0):
    """A flat half (x < 0) joined to a corrugated half (x > 0) of alternating half-cylinders of
    radius ``r``, both sampled evenly by area (unit spacing, jittered), with equal areas.

    Returns (points, curved mask).
    """
    rng = np.random.default_rng(seed)
    u = np.arange(half) + 0.5
    uu, yy = np.meshgrid(u, u, indexing="ij")
    uu = (uu + rng.uniform(-jitter, jitter, uu.shape)).ravel()
    yy = (yy + rng.uniform(-jitter, jitter, yy.shape)).ravel()
    flat = np.c_[-uu, yy, np.zeros_like(uu)]
    j = np.floor(uu / (np.pi * r))  # which half-cylinder, by arc length along the profile
    th = (uu - j * np.pi * r) / r
    x = (2 * j + 1) * r - r * np.cos(th)
    z = np.where(j % 2 == 0, 1.0, -1.0) * r * np.sin(th)
    curved = np.c_[x, yy, z]
    return np.vstack([flat, curved]), np.r_[np.zeros(uu.size, bool), np.ones(uu.size, bool)]


@pytest.fixture(scope="module")
def shape():
    pts, curved = flat_and_curved()
    v, _ = surface_variation(pts, k=16)
    w = combine_maps({"curvature": v}, len(pts))
    return pts, curved, w


def covering(points, kept):
    d, _ = cKDTree(points[kept]).query(points)
    return float(d.max())


def test_curvature_map_separates_the_halves(shape):
    _, curved, w = shape
    assert np.median(w[~curved]) == 0
    assert np.median(w[curved]) > 0.4


@pytest.mark.parametrize("frac", [0.05, 0.1])
def test_density_follows_curvature_at_a1_and_is_even_at_a0(shape, frac):
    pts, curved, w = shape
    size = int(frac * len(pts))  # both halves have the same area: density ratio = count ratio
    ratios = {}
    for a in (0.0, 1.0):
        o = weighted_ordering(pts, cost_from_weights(w, a))
        assert sorted(o.order) == list(range(len(pts)))  # a full ordering
        assert (np.diff(o.radius[1:]) <= 0).all()
        kept = o.order[:size]
        ratios[a] = curved[kept].sum() / (~curved[kept]).sum()
    assert ratios[1.0] >= 3.0
    assert 0.8 <= ratios[0.0] <= 1.25


def test_weighted_radius_is_not_euclidean_covering(shape):
    # documented: with F <= 1 a weighted radius understates the Euclidean covering radius
    pts, _, w = shape
    o = weighted_ordering(pts, cost_from_weights(w, 1.0, eps=0.1))
    k = 300
    cov = covering(pts, o.order[:k])
    assert cov > o.radius[k]
    assert cov <= o.radius[k] / 0.1 + 1e-9  # ... but within radius / F_min


def test_density_floor_ordering_keeps_rho0(shape):
    pts, curved, w = shape
    rho0 = 4.0
    uniform = fastfps(pts)
    cost = cost_from_weights(w, 1.0)
    for given in (uniform, None):
        fl = density_floor_ordering(pts, cost, rho0, uniform=given)
        n0 = fl.stats["n_floor"]
        assert n0 == uniform.size_for_rho(rho0)
        assert sorted(fl.order) == list(range(len(pts)))  # one full ordering
        np.testing.assert_array_equal(fl.order[:n0], uniform.order[:n0])
        np.testing.assert_array_equal(fl.radius[:n0], uniform.radius[:n0])
        assert (np.diff(fl.radius[1:]) <= 0).all()  # non-increasing, as an archive requires
        assert fl.radius[n0] <= rho0
        for k in (n0, n0 + 50, 2 * n0, 4 * n0):
            assert covering(pts, fl.order[:k]) <= rho0  # brute-force covering check
        # beyond the floor the budget goes to the curved half
        extra = fl.order[n0 : 3 * n0]
        assert curved[extra].sum() >= 3 * (~curved[extra]).sum()


def test_floor_query_exact_size_and_covering(shape):
    pts, curved, w = shape
    uniform = fastfps(pts)
    weighted = weighted_ordering(pts, cost_from_weights(w, 1.0))
    for rho in (2.5, 4.0, 8.0):
        n_u = uniform.size_for_rho(rho)
        for size in (n_u, n_u + 1, n_u + 400, len(pts)):
            sel = floor_query(uniform, weighted, rho, size)
            assert sel.shape == (size,) and np.unique(sel).size == size
            np.testing.assert_array_equal(sel[:n_u], uniform.order[:n_u])
            assert covering(pts, sel) <= rho
        # the fill comes from the weighted ordering: mostly the curved half
        sel = floor_query(uniform, weighted, rho, n_u + 300)
        assert curved[sel[n_u:]].mean() > 0.75
    n_u = uniform.size_for_rho(4.0)
    with pytest.raises(
        InputError,
        match=f"size {n_u - 1} is too small for rho = 4: the uniform prefix covering within rho has "
        f"{n_u} points; ask for at least {n_u} points or a larger rho",
    ):
        floor_query(uniform, weighted, 4.0, n_u - 1)
    with pytest.raises(InputError, match="rho must be a finite number > 0, got -1"):
        floor_query(uniform, weighted, -1, 100)
    with pytest.raises(InputError, match="size must be between 1 and the number of points"):
        floor_query(uniform, weighted, 4.0, len(pts) + 1)
    part = fastfps(pts, size=50)
    with pytest.raises(InputError, match="the uniform ordering stops at radius .*, above rho = 1"):
        floor_query_arrays(part.order, part.radius, weighted.order, len(pts), 1.0, 2000)


def test_outliers_left_out_of_every_ordering(shape):
    pts, _, w = shape
    pts = pts.copy()
    rng = np.random.default_rng(2)
    pts[:, 2] += rng.normal(scale=0.01, size=len(pts))
    out_idx = np.array([100, 900, 3000])
    pts[out_idx, 2] += 5.0
    noise, _ = noise_score(pts)
    exclude = noise > 20
    assert set(np.flatnonzero(exclude)) == set(out_idx)
    maps = {"curvature": w, "noise": noise}
    uniform = weighted_ordering(pts, np.ones(len(pts)), exclude=exclude)
    res = build_orderings(pts, maps, 0.8, 4.0, exclude=exclude, uniform=uniform)
    assert set(res) == {"weighted", "floor"}
    for o in res.values():
        assert len(o) == len(pts) - 3 and o.n_points == len(pts)
        assert not exclude[o.order].any()
        assert o.stats["excluded"] == 3
        assert o.stats["maps"] == ["curvature"]  # noise flags outliers, it does not weight
        assert o.stats["adaptivity"] == 0.8
    kept = ~exclude
    assert (
        covering(pts[kept], np.searchsorted(np.flatnonzero(kept), res["floor"].order[:500])) <= 4.0
    )


def test_build_orderings_options_and_errors(shape):
    pts, _, w = shape
    assert build_orderings(pts, {"curvature": w}, None, None) == {}
    only = build_orderings(pts, {"curvature": (w, {"k": 16})}, 0.5, None)
    assert set(only) == {"weighted"} and only["weighted"].stats["kind"] == "weighted"
    with pytest.raises(
        InputError, match="an adaptive ordering needs an importance map other than noise"
    ):
        build_orderings(pts, {"noise": w}, 0.5, None)
    with pytest.raises(InputError, match="adaptivity must be a number in \\[0, 1\\], got 2"):
        build_orderings(pts, {"curvature": w}, 2, None)
    with pytest.raises(InputError, match="importance map 'curvature' has 1 NaN or inf"):
        build_orderings(pts, {"curvature": np.r_[np.nan, w[1:]]}, 0.5, None)
    with pytest.raises(InputError, match="importance map 'curvature' has 1 negative value"):
        build_orderings(pts, {"curvature": np.r_[-1.0, w[1:]]}, 0.5, None)
    with pytest.raises(
        InputError, match="importance map 'curvature' has 10 values but the scan has"
    ):
        build_orderings(pts, {"curvature": w[:10]}, 0.5, None)
    with pytest.raises(InputError, match="rho0 must be a finite number > 0, got 0"):
        density_floor_ordering(pts, np.ones(len(pts)), 0)
    with pytest.raises(InputError, match="cost must be <= 1 for a density floor, got max 2"):
        density_floor_ordering(pts, np.full(len(pts), 2.0), 3.0)
    with pytest.raises(InputError, match=r"exclude must be a boolean mask of shape \(4608,\)"):
        weighted_ordering(pts, np.ones(len(pts)), exclude=np.zeros(len(pts), int))


# ---------------------------------------------------------------- archive round trip


def test_build_archive_with_features_round_trip(tmp_path, shape):
    from lodbuilder.api import build_archive, open_archive
    from lodbuilder.archive.validate import validate_archive
    from lodbuilder.io.base import Scan
    from lodbuilder.sampling.adaptive import floor_positions

    pts, curved, _ = shape
    pts = pts.copy()
    pts[[10, 2000], 2] += 6.0  # two points far off the surface
    rgb = np.where(curved, 200, 30).astype(np.uint8)
    scan = Scan(points=pts, attributes={"red": rgb, "green": rgb, "blue": rgb}, name="halves")
    out = tmp_path / "a.h5"
    build_archive(
        scan,
        out,
        importance="curvature,colour",
        adaptive=1.0,
        density_floor=4.0,
        outlier_threshold=20.0,
    )
    assert validate_archive(out) == []
    with open_archive(out) as arc:
        v = arc.scan("halves")
        assert v.n_points == len(pts) and v.n_ordered == len(pts) - 2
        assert sorted(v.importance_names) == ["colour", "curvature", "noise"]
        assert sorted(v.ordering_names) == ["floor", "weighted"]
        flag = v.attributes()["outlier"]
        src = v.source_index
        assert flag.dtype == bool and set(src[flag]) == {10, 2000}
        assert flag[v.n_ordered :].all() and not flag[: v.n_ordered].any()  # stored last
        assert v.build["outliers"] == {"map": "noise", "threshold": 20.0, "count": 2}
        p = v.ordering_parameters("floor")
        assert p["kind"] == "density_floor" and p["rho0"] == 4.0
        assert p["maps"] == ["curvature", "colour"] and p["adaptivity"] == 1.0
        # the stored noise map is in stored order and flags the two points
        noise = v.importance("noise")
        assert (noise[flag] > 20).all() and (noise[~flag] <= 20).all()
        # a level of the floor ordering of any size >= n_floor covers within rho0
        for size in (p["n_floor"], 1000):
            lvl = v.level(size=size, ordering="floor")
            assert not lvl.attributes["outlier"].any()
            assert (
                covering(
                    np.delete(pts, [10, 2000], 0),
                    np.searchsorted(
                        np.setdiff1d(np.arange(len(pts)), [10, 2000]), lvl.source_index
                    ),
                )
                <= 4.0
            )
        # the instant query on stored arrays: exact size, covering <= rho
        w_pos = arc.file["scans/halves/orderings/weighted/order"][:]
        sel = floor_positions(v.radius, v.n_ordered, w_pos, 3.0, 1500)
        assert sel.size == 1500 and np.unique(sel).size == 1500
        kept_src = src[sel]
        inl = np.setdiff1d(np.arange(len(pts)), [10, 2000])
        d, _ = cKDTree(pts[kept_src]).query(pts[inl])
        assert d.max() <= 3.0


def naive_floor_query(u_order, u_radius, w_order, rho, size):
    n_u = sum(1 for r in u_radius if r > rho)
    out = list(u_order[:n_u])
    for i in w_order:
        if len(out) == size:
            break
        if i not in out:
            out.append(i)
    return out


@pytest.mark.parametrize("seed", range(20))
def test_floor_query_matches_naive(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 60))
    u_order = rng.permutation(n)
    u_radius = np.r_[np.inf, np.sort(rng.uniform(0, 10, n - 1))[::-1]]
    w_order = rng.permutation(n)
    rho = float(rng.uniform(0.1, 12))
    n_u = int((u_radius > rho).sum())
    size = int(rng.integers(n_u, n + 1)) if n_u else int(rng.integers(1, n + 1))
    size = max(size, 1)
    got = floor_query_arrays(u_order, u_radius, w_order, n, rho, size)
    assert list(got) == naive_floor_query(u_order, u_radius, w_order, rho, size)
