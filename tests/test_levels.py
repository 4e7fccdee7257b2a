"""Level queries: rho/size/fraction prefixes, selective refinement guarantees, representatives."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

import lodbuilder
from lodbuilder import levels as LV
from lodbuilder.archive.writer import ScanRecord, update_archive
from lodbuilder.datasets import demo_scan
from lodbuilder.errors import InputError
from lodbuilder.levels import representatives

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
    from lodbuilder.datasets import make_surface

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


# --- the level arithmetic of lodbuilder.levels against brute force -------------------


def radius_arrays():
    """Non-increasing radius arrays with seeds (inf), ties and zeros, as the builds store them."""
    return st.tuples(
        st.integers(1, 3),
        st.lists(st.sampled_from([0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 7.0]), max_size=60),
    ).map(lambda t: np.array([np.inf] * t[0] + sorted(t[1], reverse=True)))


def rhos_for(radius):
    finite = sorted({float(r) for r in radius if np.isfinite(r)})
    mids = [(a + b) / 2 for a, b in zip(finite, finite[1:], strict=False)]
    return [r for r in finite + mids + [1e-9, 0.1, 100.0] if r > 0]


@settings(max_examples=200, deadline=None)
@given(radius_arrays())
def test_count_above_and_size_for_rho_brute_force(radius):
    for rho in rhos_for(radius):
        k = int(np.sum(radius > rho))  # brute force: every entry, not only a prefix
        assert LV.count_above(radius, rho) == k
        assert LV.size_for_rho(radius, rho) == max(1, k)
        # the guarantee: the shortest prefix whose covering bound is <= rho
        bounds = [
            LV.covering_bound(j, len(radius), radius.__getitem__) for j in range(len(radius) + 1)
        ]
        assert k == min(j for j, b in enumerate(bounds) if b <= rho)


@settings(max_examples=200, deadline=None)
@given(radius_arrays(), st.integers(1, 70))
def test_prefix_for_rho_reads_one_block(radius, step):
    index = radius[::step]
    reads = []

    def read_block(lo, hi):
        reads.append((lo, hi))
        return radius[lo:hi]

    for rho in rhos_for(radius):
        reads.clear()
        assert LV.prefix_for_rho(index, step, read_block, len(radius), rho) == np.sum(radius > rho)
        assert len(reads) <= 1 and all(hi - lo <= step for lo, hi in reads)


def decimal_fractions():
    return (
        st.tuples(st.integers(1, 10**6), st.integers(0, 6))
        .map(lambda t: f"{t[0]}e-{t[1] + 6}" if t[0] else "1")
        .filter(lambda s: 0 < float(s) <= 1)
    )


@settings(max_examples=300, deadline=None)
@given(decimal_fractions(), st.integers(1, 10**7))
def test_size_for_fraction_rounds_the_decimal_half_up(text, n):
    exact = Fraction(text) * n  # the decimal the user typed, times n, exactly
    want = min(n, max(1, int(exact + Fraction(1, 2)) if exact >= 0 else 0))
    got = LV.size_for_fraction(float(text), n)
    assert got == want
    if 1 < got < n:
        assert abs(got - exact) <= Fraction(1, 2)
        if abs(got - exact) == Fraction(1, 2):
            assert got > exact  # a tie goes up


@pytest.mark.parametrize(
    "fraction,n,size",
    [
        (0.5, 1889, 945),
        (0.35, 10, 4),
        (0.25, 10, 3),
        (0.15, 10, 2),
        (0.001, 1889, 2),
        (0.0002, 1889, 1),
        (1.0, 1889, 1889),
        (1 / 3, 3, 1),
        (0.1, 3000, 300),
    ],
)
def test_size_for_fraction_examples(fraction, n, size):
    assert LV.size_for_fraction(fraction, n) == size


def test_round_size():
    assert [LV.round_size(x, 10) for x in (0, 0.49, 0.5, 1.5, 2.5, 9.5, 10.4, 1e9)] == [
        1,
        1,
        1,
        2,
        3,
        10,
        10,
        10,
    ]


def test_resolve_size_checks_and_dispatches():
    radius = np.array([np.inf, 4.0, 3.0, 3.0, 1.0])
    rho_size = lambda r: LV.size_for_rho(radius, r)  # noqa: E731
    assert LV.resolve_size(5, rho=3.0, rho_size=rho_size) == 2
    assert LV.resolve_size(5, size=4, rho_size=rho_size) == 4
    assert LV.resolve_size(5, fraction=0.5, rho_size=rho_size) == 3
    for kw, msg in [
        ({}, "give exactly one"),
        ({"rho": 1, "size": 2}, "give exactly one"),
        ({"rho": -1}, "rho must be a finite number > 0"),
        ({"size": 6}, r"between 1 and the number of points \(5\), got 6"),
        ({"fraction": 0}, r"fraction must be a number in \(0, 1\]"),
    ]:
        with pytest.raises(InputError, match=msg):
            LV.resolve_size(5, rho_size=rho_size, **kw)


def test_covering_bound_is_a_covering_radius(arc):
    """Brute force: the Euclidean distance from every input point to the prefix is <= the bound
    (the band metric of the build bounds the Euclidean distance from above)."""
    scan, ordg, v = arc
    for k in [1, 2, 10, 300, 1500, 2999, 3000]:
        bound = LV.covering_bound(k, v.n_ordered, ordg.radius.__getitem__)
        lev = v.level(size=k)
        assert lev.rho == bound
        assert cover(scan.points, lev.points).max() <= bound + 1e-12


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 60))
def test_box_positions_brute_force(seed, k_out):
    rng = np.random.default_rng(seed)
    pts = rng.random((80, 3))
    box = np.sort(rng.random((2, 3)), axis=0)
    r = float(rng.random() * 0.2)
    k_out = min(k_out, 80)
    want = [
        i
        for i in range(80)
        if i < k_out or all(box[0][a] - r <= pts[i][a] <= box[1][a] + r for a in range(3))
    ]
    assert LV.box_positions(pts, k_out, box, r).tolist() == want


@pytest.mark.parametrize("slope,rho_max", [(0.0, None), (0.2, None), (0.5, 0.06), (2.0, 0.03)])
def test_viewpoint_prefixes_brute_force(arc, slope, rho_max):
    """The rule applied to every stored point keeps exactly what the prefix bounds predict: no
    point past k_fine, every point before k_coarse; the bound is the largest rho(p)."""
    scan, ordg, v = arc
    vp = np.array([0.3, 0.2, 0.1])
    rho0 = 0.01
    every = LV.viewpoint_keep(v.points(), v.radius, vp, rho0, slope, rho_max)
    every[0] = True  # a level is never empty
    k_coarse, k_fine = LV.viewpoint_sizes(v.size_for_rho, rho0, slope, rho_max)
    assert not every[k_fine:].any() and every[:k_coarse].all()
    pos = LV.viewpoint_positions(
        v.points(k_fine), v.radius[:k_fine], vp, rho0, slope, rho_max, k_coarse
    )
    np.testing.assert_array_equal(pos, np.flatnonzero(every))
    np.testing.assert_array_equal(v.refine_viewpoint(vp, rho0, slope, rho_max).rank, pos)
    rho_p = rho0 + slope * np.linalg.norm(scan.points - vp, axis=1)
    if rho_max is not None:
        rho_p = np.minimum(rho_p, rho_max)
    assert rho_p.max() <= LV.viewpoint_bound(v.bounds, vp, rho0, slope, rho_max) + 1e-12


@settings(max_examples=100, deadline=None)
@given(st.floats(0.0, 5000.0), st.integers(1, 10**6), st.integers(1, 50))
def test_log_sizes(lo, n, count):
    sizes = LV.log_sizes(lo, n, count)
    assert sizes == sorted(set(sizes)) and sizes[-1] == n and 1 <= sizes[0]
    assert len(sizes) <= count + 1
    assert sizes[0] == LV.round_size(max(1.0, lo), n)
    geo = np.geomspace(max(1.0, lo), n, count)
    assert set(sizes) == {LV.round_size(float(v), n) for v in geo} | {n}


@settings(max_examples=300, deadline=None)
@given(st.floats(0.0, 1e7, allow_nan=False), st.integers(1, 10**7))
def test_round_size_against_decimal_half_up(x, n):
    """An independent oracle: the decimal module's ROUND_HALF_UP on the shortest decimal."""
    from decimal import ROUND_HALF_UP, Decimal, localcontext

    with localcontext() as ctx:
        ctx.prec = 60
        want = int(Decimal(repr(x)).quantize(Decimal(1), rounding=ROUND_HALF_UP))
    assert LV.round_size(x, n) == min(n, max(1, want))
