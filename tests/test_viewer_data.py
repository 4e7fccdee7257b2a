"""The viewer's array side (no rendering): levels, Voronoi cells, merging, colours, legends,
imports."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from lodbuilder.errors import InputError
from lodbuilder.viewer.data import ViewData, categorical, colormap, from_arrays


def ordered(rng, n=600, name="scan", rgb=False):
    from lodbuilder import euclidean_fps

    pts = rng.random((n, 3)) * np.array([1.0, 1.0, 0.05])
    o = euclidean_fps(pts)
    attrs = {}
    if rgb:
        col = (rng.random((n, 3)) * 255).astype(np.uint8)
        attrs = {"red": col[o.order, 0], "green": col[o.order, 1], "blue": col[o.order, 2]}
    return from_arrays(
        pts[o.order],
        o.radius,
        o.parent,
        attributes=attrs,
        importance={"z": pts[o.order, 2]},
        name=name,
    )


def naive_cells(points: np.ndarray, shown: np.ndarray) -> np.ndarray:
    """Stored position of the nearest shown point of every point, by brute force."""
    d = np.linalg.norm(points[:, None, :] - points[shown][None, :, :], axis=2)
    return shown[np.argmin(d, axis=1)]


def test_levels_by_size_and_rho(rng):
    d = ordered(rng)
    for k in (1, 7, 100, 599):
        rho = d.rho_for_size(k)
        assert rho == d.radius[k]
        assert (
            d.size_for_rho(rho) <= k
        )  # the prefix of k covers within rho, maybe a shorter one too
        assert d.radius[d.size_for_rho(rho)] <= rho
    assert d.rho_for_size(len(d)) == 0.0
    assert d.clamp_size(0) == 1 and d.clamp_size(10**9) == len(d)


@pytest.mark.parametrize("k", [1, 2, 17, 300, 600])
def test_cells_are_the_voronoi_cells_of_the_level(rng, k):
    d = ordered(rng)
    cells = d.cells(k)
    np.testing.assert_array_equal(cells, naive_cells(d.points, np.arange(k)))
    np.testing.assert_array_equal(cells[:k], np.arange(k))  # a shown point is its own cell
    assert d.cells(k) is cells  # cached for the level shown


def test_cells_follow_the_level_up_and_down(rng):
    """The cells are updated from the previous level (points of a removed cell assigned again,
    points nearer a new point moved): the same as from scratch at every step."""
    d = ordered(rng, n=800)
    box = d.selective(60, [0.0, 0.0, -1.0], [0.5, 0.5, 1.0], 4.0)
    for shown in (5, 40, 41, 300, 120, 7, 799, 800, 1, box, 60, box, 500):
        pos = np.arange(shown) if np.isscalar(shown) else shown
        np.testing.assert_array_equal(d.cells(shown), naive_cells(d.points, pos))


def test_cells_of_a_level_refined_in_a_box(rng):
    d = ordered(rng)
    pos = d.selective(40, [0.0, 0.0, -1.0], [0.4, 0.4, 1.0], 4.0)
    assert pos.size > 40
    np.testing.assert_array_equal(d.cells(pos), naive_cells(d.points, pos))
    np.testing.assert_array_equal(d.colours("voronoi", pos), categorical(naive_cells(d.points, pos)))


def test_selective_refinement_is_finer_inside_the_box(rng):
    d = ordered(rng)
    k = 50
    lo, hi = np.array([0.0, 0.0, -1.0]), np.array([0.5, 0.5, 1.0])
    pos = d.selective(k, lo, hi, factor=4.0)
    np.testing.assert_array_equal(pos[:k], np.arange(k))  # the level itself is kept
    extra = d.points[pos[k:]]
    assert extra.shape[0] > 0
    r_in = d.rho_for_size(k) / 4.0
    assert np.all((extra >= lo - r_in) & (extra <= hi + r_in))  # the box grown by rho / 4
    assert np.all(d.radius[pos[k:]] > r_in)
    # the guarantee: every point inside the box is within rho / 4 of a shown point
    from lodbuilder.quality import nearest_distances

    inside = np.all((d.points >= lo) & (d.points <= hi), axis=1)
    assert nearest_distances(d.points[inside], d.points[pos]).max() <= r_in
    assert nearest_distances(d.points, d.points[pos]).max() <= d.rho_for_size(k)


def test_merge_keeps_each_scans_levels(rng):
    a, b = ordered(rng, 300, "a"), ordered(rng, 200, "b")
    m = ViewData.merge([a, b])
    assert len(m) == 500 and m.scan_names == ("a", "b")
    assert np.all(np.diff(m.radius[2:]) <= 0)  # non-increasing after the two seeds
    assert np.all(m.parent < np.arange(500))
    # a prefix of the merged ordering is each scan's level at the same rho
    cut = m.radius[120]
    assert (m.scan_id[:120] == 0).sum() == (a.radius > cut).sum()
    assert (m.scan_id[:120] == 1).sum() == (b.radius > cut).sum()
    # the parents still point into the same scan, at the same points
    child = np.flatnonzero(m.parent >= 0)
    assert np.all(m.scan_id[m.parent[child]] == m.scan_id[child])
    assert "scan" in m.colour_modes()
    assert m.importance.keys() == {"z"}


def test_colour_modes(rng):
    d = ordered(rng, rgb=True)
    assert d.colour_modes() == ["rgb", "radius", "rank", "elevation", "importance:z", "voronoi"]
    for mode in d.colour_modes() + ["importance"]:
        c = d.colours(mode, 40)
        assert c.shape == (len(d), 3) and c.dtype == np.uint8
    np.testing.assert_array_equal(d.colours("rgb", 1)[:, 0], d.attributes["red"])
    vor = d.colours("voronoi", 40)
    cells = naive_cells(d.points, np.arange(40))
    assert len({tuple(x) for x in vor}) > 30  # distinct cells get distinct colours
    np.testing.assert_array_equal(vor, vor[cells])  # a point has its cell's colour
    with pytest.raises(
        InputError, match="colour mode 'scan' is not available here; choose one of rgb"
    ):
        d.colours("scan", 10)
    plain = ordered(rng)
    with pytest.raises(InputError, match="colour mode 'rgb' is not available"):
        plain.check_mode("rgb")


def test_legends_name_the_unit_and_match_the_colours(rng):
    d = ordered(rng)
    d.units = "metre"
    radius = d.legend("radius")
    assert radius.title == "radius (metre, log)" and radius.log
    finite = d.radius[np.isfinite(d.radius)]
    assert radius.lo == pytest.approx(np.percentile(finite, 1)) and radius.hi == finite.max()
    rank = d.legend("rank")
    assert (rank.title, rank.lo, rank.hi, rank.log) == ("rank (log)", 1, 600, True)
    imp = d.legend("importance")
    assert imp.title == "importance: z" and not imp.log
    assert d.legend("voronoi") is None
    d.importance["curvature"] = d.importance["z"]
    assert d.legend("importance:curvature").title == "importance: curvature"
    # the colours are the colour map of the legend's normalised values
    np.testing.assert_array_equal(d.colours("rank", 1)[[0, 599]], colormap(np.array([0.0, 1.0])))
    values = np.where(np.isinf(d.radius), finite.max(), d.radius)
    at = d.legend("radius", shown=300)  # the scale of the level shown: rho .. the largest radius
    assert (at.lo, at.hi) == (d.rho_for_size(300), d.rho_for_size(300 // 64))
    np.testing.assert_array_equal(d.colours("radius", 300), colormap(at.normalise(values)))
    # the level's own points spread over the scale (with the scan-wide scale they were one
    # flat colour: a uniform level's radii lie within a factor of about 2)
    assert np.std(at.normalise(values[:300])) > 0.15
    assert np.std(radius.normalise(values[:300])) < 0.15
    plain = ordered(rng)
    assert plain.legend("radius").title == "radius (scan units, log)"


def test_merge_keeps_a_common_crs(rng):
    a, b = ordered(rng, 50, "a"), ordered(rng, 40, "b")
    a.crs = b.crs = 'PROJCS["x"]'
    a.units = b.units = "foot"
    m = ViewData.merge([a, b])
    assert (m.crs, m.units) == ('PROJCS["x"]', "foot")
    b.crs, b.units = None, None
    m = ViewData.merge([a, b])
    assert (m.crs, m.units) == (None, None)


def test_colour_helpers():
    c = colormap(np.array([0.0, 0.5, 1.0, np.nan, 7.0]))
    assert c.dtype == np.uint8 and c.shape == (5, 3)
    assert (
        not np.array_equal(c[0], c[2]) and np.array_equal(c[3], c[0]) and np.array_equal(c[4], c[2])
    )
    cat = categorical(np.array([3, 3, 4]))
    assert np.array_equal(cat[0], cat[1]) and not np.array_equal(cat[0], cat[2])


def test_viewdata_checks_shapes():
    with pytest.raises(
        InputError, match=r"radius must have shape \(3,\) like the points, got \(2,\)"
    ):
        ViewData(np.zeros((3, 3)), np.ones(2), -np.ones(3))
    with pytest.raises(InputError, match="per-point array 'red' has 2 rows, expected 3"):
        ViewData(np.zeros((3, 3)), np.ones(3), -np.ones(3), attributes={"red": np.zeros(2)})


def test_viewer_package_import_is_light():
    code = (
        "import sys, lodbuilder, lodbuilder.viewer, lodbuilder.viewer.data, lodbuilder.cli.main; "
        "lodbuilder.cli.main.build_parser(); "
        "bad = [m for m in ('pyvista', 'vtk', 'vtkmodules', 'numba', 'dask', 'matplotlib') "
        "if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
