"""Level queries: rho/size/fraction prefixes, selective refinement guarantees, representatives."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import lodbuilder
from lodbuilder.archive.demo_surface import demo_scan
from lodbuilder.archive.levels import representatives
from lodbuilder.archive.writer import ScanRecord, update_archive
from lodbuilder.errors import InputError

RHOS = [0.2, 0.08, 0.03, 0.012]


@pytest.fixture(scope="module")
def arc(tmp_path_factory):
    scan = demo_scan(3000, kind="wavy", seed=11, name="s")
    ordg = lodbuilder.fastfps(scan.points)
    path = tmp_path_factory.mktemp("lv") / "l.h5"
    update_archive(path, [ScanRecord(scan, ordg)])
    with lodbuilder.open_archive(path) as a:
        yield scan, ordg, a.scan()


def cover(all_pts, kept_pts):
    return cKDTree(kept_pts).query(all_pts)[0]


@pytest.mark.parametrize("rho", RHOS)
def test_rho_level_is_the_prefix_and_covers(arc, rho):
    scan, ordg, v = arc
    lev = v.level(rho=rho)
    k = ordg.size_for_rho(rho)
    assert lev.size == k == lev.points.shape[0]
    np.testing.assert_array_equal(lev.source_index, ordg.order[:k])
    assert lev.rho <= rho and lev.rho == ordg.radius[k]
    assert cover(scan.points, lev.points).max() <= lev.rho + 1e-12
    for key, arr in lev.attributes.items():
        np.testing.assert_array_equal(arr, scan.attributes[key][lev.source_index])


@pytest.mark.parametrize("step", [1, 16, 1024, 5000])
def test_rho_level_for_any_radius_index_step(arc, tmp_path, monkeypatch, step):
    from lodbuilder.archive import layout

    scan, ordg, _ = arc
    monkeypatch.setattr(layout, "RADIUS_INDEX_STEP", step)
    update_archive(tmp_path / "s.h5", [ScanRecord(scan, ordg)])
    rad = ordg.radius
    with lodbuilder.open_archive(tmp_path / "s.h5") as a:
        v = a.scan()
        assert v._step == step
        for rho in np.unique(np.concatenate([rad[1:40], rad[1000:1030], rad[-5:], [1e-9, 10.0]])):
            if rho > 0:
                assert v.size_for_rho(rho) == max(1, int(np.sum(rad > rho))), rho


def test_size_and_fraction(arc):
    scan, ordg, v = arc
    assert v.level(size=1).size == 1
    assert v.level(size=3000).rho == 0.0
    lev = v.level(fraction=0.1)
    assert lev.size == 300
    np.testing.assert_array_equal(lev.rank, np.arange(300))
    assert v.level(size=77, attributes=["red"]).attributes.keys() == {"red"}
    assert v.level(size=77, attributes=False).attributes == {}


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"rho": 0}, "rho must be a finite number > 0"),
        ({"rho": -1}, "rho must be a finite number > 0"),
        ({"rho": float("nan")}, "rho must be a finite number > 0"),
        ({"size": 0}, r"size must be between 1 and the number of points \(3000\), got 0"),
        ({"size": 3001}, r"size must be between 1 and the number of points \(3000\), got 3001"),
        ({"fraction": 1.5}, r"fraction must be a number in \(0, 1\]"),
        ({}, "give exactly one of rho, size or fraction"),
        ({"rho": 0.1, "size": 3}, "give exactly one of rho, size or fraction"),
    ],
)
def test_bad_level_arguments(arc, kwargs, message):
    with pytest.raises(InputError, match=message):
        arc[2].level(**kwargs)


@pytest.mark.parametrize("box", [[0.2, 0.2, -1, 0.5, 0.6, 1], [0.0, 0.0, -1, 0.3, 1.0, 1]])
def test_box_refinement_guarantee(arc, box):
    scan, ordg, v = arc
    r_in, r_out = 0.015, 0.1
    lev = v.refine_box(box, r_in, r_out)
    b = np.asarray(box, float).reshape(2, 3)
    inside = np.all((scan.points >= b[0]) & (scan.points <= b[1]), axis=1)
    d = cover(scan.points, lev.points)
    assert d.max() <= r_out
    assert d[inside].max() <= r_in
    # strictly between the coarse and the fine prefix, and the fine prefix is needed inside
    assert v.level(rho=r_out).size < lev.size < v.level(rho=r_in).size
    assert len(np.unique(lev.rank)) == lev.size
    np.testing.assert_array_equal(lev.points, scan.points[lev.source_index])


def test_box_refinement_errors(arc):
    v = arc[2]
    with pytest.raises(InputError, match="must not be larger than the rho outside"):
        v.refine_box([0, 0, 0, 1, 1, 1], 0.2, 0.1)
    with pytest.raises(InputError, match="box must be 6 numbers"):
        v.refine_box([0, 0, 0, 1], 0.01, 0.1)
    with pytest.raises(InputError, match="min <= max"):
        v.refine_box([1, 0, 0, 0, 1, 1], 0.01, 0.1)


@pytest.mark.parametrize("slope,rho_max", [(0.1, None), (0.3, 0.15), (0.0, None)])
def test_viewpoint_refinement_guarantee(arc, slope, rho_max):
    scan, ordg, v = arc
    vp = np.array([0.1, 0.1, 0.3])
    rho0 = 0.02
    lev = v.refine_viewpoint(vp, rho0, slope, rho_max)
    rho_p = rho0 + slope * np.linalg.norm(scan.points - vp, axis=1)
    if rho_max is not None:
        rho_p = np.minimum(rho_p, rho_max)
    d = cover(scan.points, lev.points)
    assert np.all(d <= rho_p), float((d - rho_p).max())
    assert d.max() <= lev.rho
    if slope == 0.0:
        np.testing.assert_array_equal(lev.rank, np.arange(v.level(rho=rho0).size))
    else:
        assert lev.size < v.level(rho=rho0 / (1 + slope)).size


def naive_representative(parent, k, i):
    while i >= k and i >= 0:
        i = parent[i]
    return i


@pytest.mark.parametrize("k", [1, 5, 100, 2999, 3000])
def test_representatives_follow_parents(arc, k):
    scan, ordg, v = arc
    parent = v.parent
    rep_stored = v.representatives(k, input_order=False)
    expect = np.array([naive_representative(parent, k, i) for i in range(len(parent))])
    np.testing.assert_array_equal(rep_stored, expect)
    assert (rep_stored < k).all()
    rep_input = v.representatives(k)
    np.testing.assert_array_equal(rep_input[v.source_index], rep_stored)


def test_representatives_with_roots_beyond_k():
    parent = np.array([-1, 0, -1, 2, 1, 3])
    np.testing.assert_array_equal(representatives(parent, 2), [0, 1, -1, -1, 1, -1])


def test_cell_averaged_attributes(arc):
    scan, ordg, v = arc
    k = 50
    avg, counts = v.cell_averaged_attributes(k, ["red", "nx"])
    assert counts.sum() == 3000 and (counts >= 1).all()
    rep = v.representatives(k)
    for j in [0, 7, 49]:
        members = rep == j
        assert counts[j] == members.sum()
        assert avg["red"][j] == np.rint(scan.attributes["red"][members].mean())
        np.testing.assert_allclose(avg["nx"][j], scan.attributes["nx"][members].mean(), rtol=1e-5)
    assert avg["red"].dtype == np.uint8


@pytest.mark.parametrize("kind", ["wavy", "sphere", "torus", "folded"])
def test_generated_surfaces_lie_on_their_surface(kind):
    from lodbuilder.archive.demo_surface import make_surface

    pts, nrm = make_surface(kind, 2000, seed=4)
    assert pts.shape == (2000, 3) and np.isfinite(pts).all()
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0)
    again, _ = make_surface(kind, 2000, seed=4)
    np.testing.assert_array_equal(pts, again)
    if kind == "sphere":
        np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 0.5)
    if kind == "torus":
        ring = np.hypot(pts[:, 0], pts[:, 1])
        np.testing.assert_allclose(np.hypot(ring - 0.5, pts[:, 2]), 0.18, atol=1e-12)
    if kind == "folded":
        flat = (pts[:, 0] < 1.0) & ~np.isclose(pts[:, 2], 0) & ~np.isclose(pts[:, 2], 0.05)
        assert not flat[pts[:, 0] < 0.99].any()  # away from the fold only the two layers
    noisy, _ = make_surface(kind, 2000, seed=4, noise=0.01)
    assert 0.005 < np.abs(noisy - pts).max() < 0.1
    with pytest.raises(InputError, match="unknown surface 'cube'"):
        make_surface("cube", 10)


def test_to_polydata(arc):
    pytest.importorskip("pyvista")
    lev = arc[2].level(size=200)
    poly = lev.to_polydata()
    assert poly.n_points == 200
    np.testing.assert_array_equal(np.asarray(poly.points, dtype=np.float64), lev.points)
    assert {"red", "nx", "radius", "rank", "source_index"} <= set(poly.point_data.keys())
