"""Colour modes of the viewer for surveys: elevation (along the up axis), intensity,
classification (ASPRS names and colours, a legend of swatches), scan (distinct colours and a
legend, joint archives included); and a first camera that faces the scan."""

from __future__ import annotations

import numpy as np
import pytest

from lodbuilder.viewer.data import (
    ASPRS_COLOURS,
    SCAN_PALETTE,
    Categories,
    facing_camera,
    from_arrays,
)


def survey(rng, n=800):
    from lodbuilder import euclidean_fps

    pts = rng.random((n, 3)) * np.array([100.0, 60.0, 4.0])
    o = euclidean_fps(pts)
    cls = rng.choice([2, 5, 6, 9, 77], n).astype(np.uint8)
    inten = rng.integers(0, 3000, n).astype(np.uint16)
    return from_arrays(pts[o.order], o.radius, o.parent, name="tile", units="metre",
                       attributes={"classification": cls[o.order], "intensity": inten[o.order]})


def test_survey_modes_legends_and_colours(rng):
    d = survey(rng)
    assert d.colour_modes() == ["radius", "rank", "elevation", "intensity", "classification", "voronoi"]
    cls = d.attributes["classification"]
    legend = d.legend("classification")
    assert isinstance(legend, Categories) and legend.title == "classification"
    assert legend.names == ("2 ground", "5 high vegetation", "6 building", "9 water", "77 user class")
    c = d.colours("classification", 10)
    for code in (2, 5, 6, 9):
        assert np.all(c[cls == code] == ASPRS_COLOURS[code])
    assert len({tuple(x) for x in c[cls == 77]}) == 1  # a user class: one colour of its own
    elev = d.legend("elevation")
    assert elev.title == "elevation z (metre)" and not elev.log
    lo, hi = np.percentile(d.points[:, 2], [1, 99])
    assert (elev.lo, elev.hi) == pytest.approx((lo, hi))
    assert d.legend("intensity").title == "intensity"
    e = d.colours("elevation", 10)
    top, low = int(np.argmax(d.points[:, 2])), int(np.argmin(d.points[:, 2]))
    assert e[top][0] > 200 and e[low][2] > e[low][1]  # viridis: yellow high, purple-blue low
    d.up = "-x"  # elevation follows the up axis (and its sign)
    assert d.legend("elevation").title == "elevation -x (metre)"
    assert np.array_equal(d.elevation(), -d.points[:, 0])


def test_scans_get_distinct_colours_and_a_legend(rng):
    from lodbuilder.viewer.data import ViewData

    parts = [survey(rng, 200) for _ in range(4)]
    merged = ViewData.merge(parts, ["a", "b", "c", "d"])
    legend = merged.legend("scan")
    assert legend.names == ("a", "b", "c", "d") and legend.colours == SCAN_PALETTE[:4]
    c = merged.colours("scan", 10)
    for i in range(4):
        assert np.all(c[merged.scan_id == i] == SCAN_PALETTE[i])
    # neighbours in the palette are far apart (the hashed colours of before could be near-equal)
    pal = np.asarray(SCAN_PALETTE[:10], dtype=float)
    gaps = np.linalg.norm(pal[:, None] - pal[None], axis=2)[~np.eye(10, dtype=bool)]
    assert gaps.min() > 60


def test_joint_archive_colours_by_member_scan(tmp_path):
    """A joint archive is one scan whose points keep their member scan: colour mode scan works
    on it (it was refused before), with the members' names."""
    from lodbuilder.cli.main import main
    from lodbuilder.datasets import demo_scan
    from lodbuilder.io import write_points
    from lodbuilder.viewer.source import load_view_data

    files = []
    for i in range(3):
        s = demo_scan(1500, seed=i)
        f = tmp_path / f"part{i}.ply"
        write_points(f, s.points + [i * 1.5, 0, 0], {})
        files.append(str(f))
    arc = tmp_path / "joint.h5"
    assert main(["build", *files, "-o", str(arc), "--joint", "site", "-q"]) == 0
    data = load_view_data(arc)
    assert data.scan_names == ("part0", "part1", "part2")
    assert "scan" in data.colour_modes()
    c = data.colours("scan", 100)
    for i in range(3):
        mine = data.scan_id == i
        assert mine.sum() == 1500 and np.all(c[mine] == SCAN_PALETTE[i])
        # the member's points are the ones moved by i * 1.5 in x
        assert np.all(np.abs(data.points[mine, 0].mean() - (i * 1.5 + data.points[data.scan_id == 0, 0].mean())) < 0.2)


def test_first_camera_faces_the_scan(rng):
    flat = rng.random((2000, 3)) * [100, 60, 2]  # an airborne tile, z up
    d, up = facing_camera(flat, "z")
    assert up.tolist() == [0, 0, 1] and d[2] > 0.8 and d[1] < -0.3 and abs(d[0]) < 1e-9
    wall = rng.random((2000, 3)) * [10, 0.5, 6]  # a facade, thin along y, z up: from -y
    d, _ = facing_camera(wall, "z")
    assert d[1] < -0.9 and 0.2 < d[2] < 0.45
    statue = rng.random((2000, 3)) * [4, 10, 1]  # thin along z, y up: from +z, raised
    d, up = facing_camera(statue, "y")
    assert up.tolist() == [0, 1, 0] and d[2] > 0.9 and 0.2 < d[1] < 0.45
    d, up = facing_camera(statue, "-y")
    assert up.tolist() == [0, -1, 0] and d[1] < 0


def test_legends_are_drawn(rng):
    """The classification legend draws its swatches at the top right of the right pane; a
    scale mode hides it and shows the bar (pixel checks)."""
    pytest.importorskip("pyvista")
    from lodbuilder.viewer.app import LevelViewer

    d = survey(rng, 3000)
    vw = LevelViewer(d, off_screen=True, size=500, colour="classification", window_size=(800, 400))
    try:
        img = vw.image()
        corner = img[: img.shape[0] // 3, int(img.shape[1] * 0.85):]

        def has(colour):
            return bool(np.any(np.all(np.abs(corner.astype(int) - colour) <= 8, axis=2)))

        assert vw.legend_box.GetVisibility() and not vw.scalar_bar.GetVisibility()
        assert has(ASPRS_COLOURS[6]) and has(ASPRS_COLOURS[9])  # building red, water blue swatches
        vw.set_colour("elevation")
        img = vw.image()
        corner = img[: img.shape[0] // 3, int(img.shape[1] * 0.85):]
        assert not vw.legend_box.GetVisibility() and vw.scalar_bar.GetVisibility()
        assert not has(ASPRS_COLOURS[9])
    finally:
        vw.close()
