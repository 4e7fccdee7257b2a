"""Importance maps against hand-computable cases, the CIELAB conversion, and input validation."""

from __future__ import annotations

import numpy as np
import pytest
from surfaces import fibonacci_sphere

from lodbuilder.errors import InputError, ScanFileError
from lodbuilder.features import (
    colour_difference,
    combine_maps,
    compute_importance,
    cost_from_weights,
    noise_score,
    normal_variation,
    normalise,
    srgb_to_lab,
    surface_variation,
    validate_weights,
)
from lodbuilder.features.neighbours import knn, median_over_neighbours, radius_neighbours
from lodbuilder.io.base import Scan


def grid_plane(n=30, spacing=1.0, jitter=0.0, seed=0):
    rng = np.random.default_rng(seed)
    g = (
        np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
        * spacing
    )
    g = g + rng.uniform(-jitter, jitter, g.shape) * spacing
    return np.c_[g, np.zeros(len(g))]


# ---------------------------------------------------------------- surface variation


@pytest.mark.parametrize("kw", [{"k": 16}, {"radius": 2.5}, {"k": [8, 16, 32]}])
def test_plane_has_zero_surface_variation(kw):
    pts = grid_plane(jitter=0.3)
    # tilt and shift the plane far from the origin: the result must not depend on placement
    rot = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    pts = pts @ rot.T + [5e5, 4e6, 100.0]
    v, params = surface_variation(pts, **kw)
    assert v.shape == (len(pts),)
    assert v.max() < 1e-9
    assert params == (
        {"radius": 2.5}
        if "radius" in kw
        else {"k": kw["k"]}
        if kw["k"] == 16
        else {"k": [8, 16, 32], "combine": "mean"}
    )


def test_sphere_surface_variation_is_small_and_constant():
    # a disc of geodesic radius s on a sphere of radius R: lambda0 / sum ~ s^2 / (24 R^2)
    pts = fibonacci_sphere(8000, radius=2.0)
    s = 0.3
    v, _ = surface_variation(pts, radius=s)
    expected = s**2 / (24 * 2.0**2)
    assert np.median(v) == pytest.approx(expected, rel=0.1)
    assert v.std() / v.mean() < 0.15  # the same everywhere
    vk, _ = surface_variation(pts, k=16)
    assert vk.max() < 0.01 and vk.std() / vk.mean() < 0.3


def test_multiscale_max_is_at_least_mean():
    pts = fibonacci_sphere(2000)
    vmax, p = surface_variation(pts, k=[8, 24], combine="max")
    vmean, _ = surface_variation(pts, k=[8, 24], combine="mean")
    assert p == {"k": [8, 24], "combine": "max"}
    assert (vmax >= vmean - 1e-15).all() and (vmax > vmean).any()
    with pytest.raises(InputError, match="combine must be one of mean, max, got 'median'"):
        surface_variation(pts, k=[8, 24], combine="median")
    with pytest.raises(
        InputError, match=r"k \(neighbours per point\) must be a whole number >= 3, got 2"
    ):
        surface_variation(pts, k=2)


def test_knn_and_radius_covariances_agree():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(500, 3))
    from lodbuilder.features.neighbours import local_pca

    nb = knn(pts, 12)
    ev, nrm, cen = local_pca(pts, nb)
    # the same neighbourhoods in CSR form go through the reduceat/bincount path
    from lodbuilder.features.neighbours import Neighbourhoods

    csr = Neighbourhoods(len(pts), indptr=np.arange(0, 12 * 501, 12), indices=nb.knn.reshape(-1))
    ev2, nrm2, cen2 = local_pca(pts, csr)
    np.testing.assert_allclose(ev, ev2, atol=1e-12)
    np.testing.assert_allclose(cen, cen2, atol=1e-12)
    np.testing.assert_allclose(np.abs((nrm * nrm2).sum(1)), 1, atol=1e-8)
    # and against a plain per-point np.cov
    for i in (0, 17, 499):
        c = np.cov(pts[nb.knn[i]].T, bias=True)
        np.testing.assert_allclose(ev[i], np.linalg.eigvalsh(c), atol=1e-12)


def test_median_over_radius_neighbourhoods_matches_numpy():
    rng = np.random.default_rng(4)
    pts = rng.uniform(size=(300, 3))
    vals = rng.normal(size=300)
    nb = radius_neighbours(pts, 0.2)
    got = median_over_neighbours(vals, nb)
    for i in range(0, 300, 37):
        idx = nb.indices[nb.indptr[i] : nb.indptr[i + 1]]
        assert got[i] == pytest.approx(np.median(vals[idx]))


# ---------------------------------------------------------------- normal variation


def test_normal_variation_plane_zero_and_sphere_exact():
    v, p = normal_variation(grid_plane(jitter=0.2))
    assert v.max() < 1e-6 and p["normals"] == "pca"
    pts = fibonacci_sphere(1500)
    v, p = normal_variation(pts, pts.copy(), radius=0.2)  # true normals given
    assert p == {"radius": 0.2, "normals": "scan", "oriented": False}
    # by hand: the angle between unit normals at p and q of the unit sphere is 2 asin(|p - q| / 2)
    for i in (0, 500, 1499):
        d = np.linalg.norm(pts - pts[i], axis=1)
        nbr = (d <= 0.2) & (np.arange(len(pts)) != i)
        assert v[i] == pytest.approx(np.mean(2 * np.arcsin(d[nbr] / 2)), rel=1e-9)


def test_normal_variation_flipped_normals_unless_oriented():
    pts = grid_plane(n=10)
    nrm = np.tile([0.0, 0.0, 1.0], (100, 1))
    nrm[::2] *= -1
    assert normal_variation(pts, nrm, k=8)[0].max() < 1e-6
    assert normal_variation(pts, nrm, k=8, oriented=True)[0].min() > 1.0
    with pytest.raises(
        InputError,
        match=r"normals has 1 zero-length or non-finite vector\(s\) \(first at index 3\)",
    ):
        bad = nrm.copy()
        bad[3] = 0
        normal_variation(pts, bad)


# ---------------------------------------------------------------- colour


def test_srgb_to_lab_reference_values():
    lab = srgb_to_lab(np.array([[255, 255, 255], [0, 0, 0], [255, 0, 0], [0, 0, 255]], np.uint8))
    np.testing.assert_allclose(lab[0], [100, 0, 0], atol=1e-3)
    np.testing.assert_allclose(lab[1], [0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(lab[2], [53.2408, 80.0925, 67.2032], atol=2e-3)
    np.testing.assert_allclose(lab[3], [32.2970, 79.1875, -107.8602], atol=2e-3)
    # the same colours as floats in [0, 1] and as 16-bit values
    f = srgb_to_lab(np.array([[1.0, 0, 0]]))
    u16 = srgb_to_lab(np.array([[65535, 0, 0]], np.uint16))
    u16_8bit = srgb_to_lab(np.array([[255, 0, 0]], np.uint16))  # LAS: 8-bit values in 16-bit fields
    np.testing.assert_allclose(f[0], lab[2])
    np.testing.assert_allclose(u16[0], lab[2])
    np.testing.assert_allclose(u16_8bit[0], lab[2])


def test_colour_difference_hand_case():
    pts = grid_plane(n=12)
    rgb = np.tile(np.array([0, 0, 255], np.uint8), (len(pts), 1))
    red = 6 * 12 + 6  # one red point amid blue
    rgb[red] = [255, 0, 0]
    v, p = colour_difference(pts, rgb, k=9)
    de = np.linalg.norm(srgb_to_lab(rgb[[red]])[0] - srgb_to_lab(rgb[[0]])[0])
    assert de == pytest.approx(176.3, abs=0.1)
    assert v[red] == pytest.approx(de)  # all 8 neighbours differ by de
    assert v[red + 1] == pytest.approx(de / 8)  # one of 8 neighbours is red
    assert v[0] == 0
    assert p["space"] == "CIELAB D65" and p["k"] == 9
    with pytest.raises(
        InputError, match="colours has 3 rows but points has 144; give one colour per point"
    ):
        colour_difference(pts, rgb[:3])


# ---------------------------------------------------------------- noise


def test_noise_score_flags_an_off_surface_point():
    rng = np.random.default_rng(7)
    pts = grid_plane(n=40)
    pts[:, 2] += rng.normal(scale=0.05, size=len(pts))  # noise of 5 % of the spacing
    out = 20 * 40 + 20
    pts[out, 2] += 2.0  # 40 sigma off the surface
    for kw in ({"k": 16}, {"radius": 2.5}):
        s, params = noise_score(pts, **kw)
        others = np.delete(s, out)
        assert np.argmax(s) == out
        assert s[out] > 5 * others.max()
        assert 0.5 < np.median(others) < 2.0  # about 1 on evenly noisy surface
    pts[out, 2] += 1.0  # alone within the radius: no plane to compare with
    assert noise_score(pts, radius=2.5)[0][out] == 1e6
    assert noise_score(pts, k=16)[0][out] > 50
    assert noise_score(grid_plane(n=20))[0].max() < 1e-6  # an exact plane: no noise at all
    # below the floor (1 % of the spacing) distances count as noise-free
    quiet = grid_plane(n=40)
    quiet[:, 2] += rng.normal(scale=1e-4, size=len(quiet))
    assert noise_score(quiet)[0].max() < 0.1
    quiet[out, 2] += 0.5
    assert noise_score(quiet)[0][out] > 20


# ---------------------------------------------------------------- weights and validation


def test_weights_validation_messages():
    with pytest.raises(
        InputError,
        match=r"importance map 'w' has 2 NaN or inf value\(s\) \(first at index 1\); fill them",
    ):
        validate_weights([1.0, np.nan, 2.0, np.inf], 4, "w")
    with pytest.raises(
        InputError,
        match=r"importance map 'w' has 1 negative value\(s\) \(min -0.5 at index 2\); importance must be >= 0",
    ):
        validate_weights([1.0, 0.0, -0.5], 3, "w")
    with pytest.raises(
        InputError,
        match="importance map 'w' has 3 values but the scan has 4 points; give one value per point",
    ):
        validate_weights([1, 2, 3], 4, "w")
    with pytest.raises(
        InputError, match=r"importance map 'w' has shape \(2, 2\) but the scan has 4 points"
    ):
        validate_weights(np.ones((2, 2)), 4, "w")
    with pytest.raises(
        InputError, match="importance map 'w' must hold real numbers, got dtype <U1"
    ):
        validate_weights(["a", "b"], 2, "w")
    assert validate_weights(np.arange(3, dtype=np.uint8), 3).dtype == np.float64


def test_normalise_combine_and_cost():
    w = np.r_[np.zeros(90), np.linspace(0, 10, 10)]
    nw = normalise(w, (5, 95))
    assert nw.min() == 0 and nw.max() == 1 and ((nw >= 0) & (nw <= 1)).all()
    assert (normalise(np.full(5, 3.0)) == 0).all()  # no contrast
    other = np.linspace(1, 0, 100)
    both_max = combine_maps({"a": w, "b": (other, {})}, 100, combine="max")
    both_mean = combine_maps([w, other], 100)
    assert (both_max >= both_mean).all()
    np.testing.assert_allclose(both_mean, (normalise(w) + normalise(other)) / 2)
    f0 = cost_from_weights(both_mean, 0.0)
    f1 = cost_from_weights(both_mean, 1.0, eps=0.05)
    assert (f0 == 1).all()
    assert f1.min() == 0.05 and f1.max() <= 1
    with pytest.raises(InputError, match="adaptivity must be a number in \\[0, 1\\], got 1.5"):
        cost_from_weights(both_mean, 1.5)
    with pytest.raises(InputError, match="adaptivity must be a number in \\[0, 1\\], got nan"):
        cost_from_weights(both_mean, float("nan"))
    with pytest.raises(InputError, match="importance map 'a' has 1 NaN"):
        combine_maps({"a": np.r_[np.nan, w[1:]]}, 100)


# ---------------------------------------------------------------- registry


def _scan():
    pts = grid_plane(n=20, jitter=0.1)
    pts[:, 2] = 0.05 * np.sin(pts[:, 0])
    rng = np.random.default_rng(0)
    attrs = {
        "red": rng.integers(0, 255, len(pts)).astype(np.uint8),
        "green": np.full(len(pts), 100, np.uint8),
        "blue": np.full(len(pts), 50, np.uint8),
        "intensity": rng.uniform(0, 5, len(pts)).astype(np.float32),
        "nx": np.zeros(len(pts), np.float32),
        "ny": np.zeros(len(pts), np.float32),
        "nz": np.ones(len(pts), np.float32),
    }
    return Scan(points=pts, attributes=attrs, name="t")


def test_compute_importance_by_name(tmp_path):
    scan = _scan()
    user = np.linspace(0, 1, len(scan.points))
    np.save(tmp_path / "mine.npy", user)
    maps = compute_importance(
        scan, f"curvature,color,noise,normal,attr:intensity,{tmp_path / 'mine.npy'}", k=10
    )
    assert list(maps) == ["curvature", "colour", "noise", "normal", "intensity", "mine"]
    for values, _ in maps.values():
        assert values.shape == (len(scan.points),) and values.dtype == np.float64
        assert np.isfinite(values).all() and (values >= 0).all()
    assert maps["curvature"][1] == {"kind": "curvature", "k": 10}
    assert maps["normal"][1]["normals"] == "scan"
    assert maps["normal"][0].max() < 1e-6  # the file's normals are all +z
    np.testing.assert_allclose(maps["intensity"][0], scan.attributes["intensity"])
    np.testing.assert_array_equal(maps["mine"][0], user)
    assert maps["mine"][1] == {"kind": "user", "source": "npy", "file": "mine.npy"}
    ms = compute_importance(scan, ["curvature"], options={"curvature": {"k": [6, 12]}})
    assert ms["curvature"][1]["k"] == [6, 12]


def test_compute_importance_errors(tmp_path):
    scan = _scan()
    with pytest.raises(
        InputError, match="unknown importance map 'wiggle'; use one of colour, curvature"
    ):
        compute_importance(scan, "curvature,wiggle")
    with pytest.raises(
        InputError,
        match=r"scan 't' has no attribute 'gps_time' for importance map 'attr:gps_time' \(attributes: blue, green",
    ):
        compute_importance(scan, "attr:gps_time")
    with pytest.raises(
        ScanFileError, match="importance map file '.*nope.npy' not found; check the path"
    ):
        compute_importance(scan, str(tmp_path / "nope.npy"))
    np.save(tmp_path / "short.npy", np.ones(5))
    with pytest.raises(
        InputError, match="importance map 'short' has 5 values but the scan has 400 points"
    ):
        compute_importance(scan, f"npy:{tmp_path / 'short.npy'}")
    with pytest.raises(InputError, match=r"importance maps \['colour'\] are named twice"):
        compute_importance(scan, "colour,color")
    with pytest.raises(InputError, match="no importance map named"):
        compute_importance(scan, " , ")
    bare = Scan(points=scan.points, attributes={}, name="bare")
    with pytest.raises(
        InputError, match="scan 'bare' has no colours .*; leave 'colour' out of the importance maps"
    ):
        compute_importance(bare, "colour")


@pytest.mark.data
def test_real_coloured_scan_maps(shared_data):
    from lodbuilder.io import read_scan

    scan = read_scan(shared_data / "bun_zipper_res2.ply")
    maps = compute_importance(scan, "curvature,noise,normal,attr:confidence")
    for values, _ in maps.values():
        assert values.shape == (len(scan.points),) and np.isfinite(values).all()
    # the bunny is curved everywhere but mostly smooth: small median variation, a few sharp spots
    v = maps["curvature"][0]
    assert np.median(v) < 0.05 and v.max() > 3 * np.median(v)


def test_rare_features_keep_their_contrast():
    from lodbuilder.features.weights import normalise

    w = np.zeros(1000)
    w[:20] = np.linspace(1, 2, 20)  # 2 % of the points: above the 95th percentile
    out = normalise(w)
    assert out[:20].min() > 0 and out[19] == 1.0 and (out[20:] == 0).all()
    assert (normalise(np.full(50, 3.0)) == 0).all()
