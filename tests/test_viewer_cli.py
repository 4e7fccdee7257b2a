"""``lodbuilder view`` off screen on real archives, and the import boundaries of the viewer."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from lodbuilder.cli.main import main
from lodbuilder.errors import InputError


@pytest.fixture(scope="module")
def bunny_archive(shared_data, tmp_path_factory):
    import lodbuilder

    out = tmp_path_factory.mktemp("arc") / "bunny.h5"
    lodbuilder.build_archive(shared_data / "bun_zipper_res3.ply", out, name="res3")
    lodbuilder.build_archive(shared_data / "bun_zipper_res4.ply", out, name="res4")
    return out


@pytest.fixture(scope="module")
def colour_archive(small_archive):
    return small_archive(3000)


@pytest.mark.viewer
def test_view_screenshot_cli(bunny_archive, tmp_path, capsys):
    from PIL import Image

    out = tmp_path / "res3.png"
    rc = main(
        ["view", str(bunny_archive), "--scan", "res3", "--size", "400", "--colour", "radius"]
        + ["--screenshot", str(out), "--window-size", "500", "250", "--view", "xy"]
    )
    assert rc == 0
    assert "wrote" in capsys.readouterr().out
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape == (250, 500, 3)
    assert np.count_nonzero(np.any(img[40:, :250] < 245, axis=2)) > 500


@pytest.mark.viewer
def test_view_merges_scans_and_colours_by_scan(bunny_archive, tmp_path):
    from lodbuilder.viewer.source import load_view_data

    data = load_view_data(bunny_archive)
    assert len(data) == 1889 + 453 and data.scan_names == ("res3", "res4")
    assert "scan" in data.colour_modes()
    out = tmp_path / "both.png"
    assert (
        main(
            ["view", str(bunny_archive), "--colour", "scan", "--rho", "0.01"]
            + ["--screenshot", str(out), "--window-size", "300", "150"]
        )
        == 0
    )
    assert out.stat().st_size > 0


@pytest.mark.viewer
def test_view_rgb_box_surface_animation(colour_archive, tmp_path):
    from PIL import Image

    from lodbuilder.viewer.source import load_view_data

    data = load_view_data(colour_archive)
    assert data.colour_modes()[0] == "rgb"
    png = tmp_path / "box.png"
    rc = main(
        [
            "view",
            str(colour_archive),
            "--fraction",
            "0.05",
            "--box",
            "0",
            "0",
            "-1",
            "0.5",
            "0.5",
            "1",
        ]
        + ["--surface", "--edl", "--screenshot", str(png), "--window-size", "300", "150"]
    )
    assert rc == 0 and png.stat().st_size > 0
    gif = tmp_path / "a.gif"
    assert (
        main(
            [
                "view",
                str(colour_archive),
                "--animate",
                str(gif),
                "--frames",
                "5",
                "--window-size",
                "200",
                "100",
            ]
        )
        == 0
    )
    with Image.open(gif) as im:
        assert im.n_frames == 5


def test_view_errors(bunny_archive, tmp_path, capsys, monkeypatch):
    arc = str(bunny_archive)
    assert main(["view", arc, "--screenshot", str(tmp_path / "x.jpg")]) == 2
    assert "--screenshot" in capsys.readouterr().err
    assert main(["view", arc, "--scan", "nope", "--screenshot", str(tmp_path / "x.png")]) == 2
    assert "has no scan 'nope'" in capsys.readouterr().err
    assert (
        main(
            [
                "view",
                arc,
                "--scan",
                "res4",
                "--colour",
                "rgb",
                "--screenshot",
                str(tmp_path / "x.png"),
            ]
        )
        == 2
    )
    assert "colour mode 'rgb' is not available" in capsys.readouterr().err
    assert (
        main(
            [
                "view",
                arc,
                "--scan",
                "res4",
                "--size",
                "454",
                "--screenshot",
                str(tmp_path / "x.png"),
            ]
        )
        == 2
    )
    assert (
        "size must be between 1 and the number of points (453), got 454" in capsys.readouterr().err
    )
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    assert main(["view", arc]) == 2
    assert "no display" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_slice_path_does_not_import_pyvista(bunny_archive, tmp_path):
    out = tmp_path / "lvl.npy"
    code = (
        "import sys; from lodbuilder.cli.main import main; "
        f"rc = main(['slice', {str(bunny_archive)!r}, '--scan', 'res3', '--size', '100', '-o', {str(out)!r}]); "
        "bad = [m for m in ('pyvista', 'vtkmodules', 'matplotlib', 'numba', 'dask') if m in sys.modules]; "
        "print(rc, bad); sys.exit(rc or (3 if bad else 0))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert out.exists()


@pytest.mark.viewer
def test_view_extra_ordering(shared_data, tmp_path, capsys):
    import lodbuilder
    from lodbuilder.viewer.source import load_view_data

    arc = tmp_path / "weighted.h5"
    lodbuilder.build_archive(shared_data / "bun_zipper_res3.ply", arc, name="res3", adaptive=0.8)
    uniform = load_view_data(arc)
    weighted = load_view_data(arc, ordering="weighted")
    assert weighted.scan_names == ("res3 (weighted)",) and len(weighted) == len(uniform)
    # the same points, another order: its prefixes are the weighted levels
    assert np.array_equal(np.unique(weighted.points, axis=0), np.unique(uniform.points, axis=0))
    assert not np.array_equal(weighted.points[:100], uniform.points[:100])
    finite = weighted.radius[np.isfinite(weighted.radius)]
    assert np.all(np.diff(finite) <= 0)
    assert np.all(weighted.parent < np.arange(len(weighted)))
    with lodbuilder.open_archive(arc) as a:
        lvl = a.scan().level(size=100, ordering="weighted", attributes=False)
    np.testing.assert_array_equal(weighted.points[:100], lvl.points)
    png = tmp_path / "w.png"
    rc = main(
        ["view", str(arc), "--ordering", "weighted", "--size", "300", "--colour", "importance"]
        + ["--screenshot", str(png), "--window-size", "300", "150"]
    )
    assert rc == 0 and png.stat().st_size > 0
    assert main(["view", str(arc), "--ordering", "nope", "--screenshot", str(png)]) == 2
    assert "has no ordering 'nope'; it has 'uniform', 'weighted'" in capsys.readouterr().err


@pytest.mark.viewer
def test_view_up_axis_turns_the_camera(bunny_archive, tmp_path):
    from lodbuilder.viewer.app import LevelViewer
    from lodbuilder.viewer.source import load_view_data

    data = load_view_data(bunny_archive, scan="res3")
    ups = {}
    for up in ("z", "y"):
        viewer = LevelViewer(data, size=400, off_screen=True, full_scan=False, up=up,
                             window_size=(300, 300))
        try:
            ups[up] = np.asarray(viewer.plotter.camera.up)
        finally:
            viewer.close()
    assert ups["y"][1] > 0.9  # the bunny's own up axis points up on screen
    assert ups["z"][2] > 0.5
    with pytest.raises(InputError, match=r"up must be one of x, y, z, -x, -y, -z, got 'w'"):
        LevelViewer(data, size=400, off_screen=True, up="w")


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["--window-size", "0", "0"],
            "--window-size must be two whole numbers of pixels between 32 and 8192 "
            "(WIDTH HEIGHT), got 0 0",
        ),
        (
            ["--window-size", "800", "-5"],
            "--window-size must be two whole numbers of pixels between 32 and 8192 "
            "(WIDTH HEIGHT), got 800 -5",
        ),
        (
            ["--window-size", "100000", "100000"],
            "--window-size must be two whole numbers of pixels between 32 and 8192 "
            "(WIDTH HEIGHT), got 100000 100000",
        ),
        (["--point-scale", "-1"], "--point-scale must be a finite number > 0, got -1.0"),
        (["--point-scale", "0"], "--point-scale must be a finite number > 0, got 0.0"),
        (["--point-scale", "nan"], "--point-scale must be a finite number > 0, got nan"),
    ],
)
def test_view_bounds_window_size_and_point_scale(bunny_archive, tmp_path, args, message):
    """Finding 9: 100000x100000 aborted in VTK (std::bad_alloc), 0 0 rendered 300x300, a negative
    point scale was accepted. Each is refused before anything is rendered or written. A
    subprocess, so that a regression that reaches VTK's abort fails this test, not the run."""
    out = tmp_path / "x.png"
    r = subprocess.run(
        [sys.executable, "-m", "lodbuilder.cli.main", "view", str(bunny_archive)]
        + ["--scan", "res4", "--screenshot", str(out)] + args,
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2, r.stderr
    assert r.stderr == f"lodbuilder view: error: {message}\n"
    assert not out.exists()


def test_viewer_bounds_window_size_and_point_scale_in_the_library():
    from lodbuilder.viewer.data import from_arrays
    from lodbuilder.viewer.options import check_window_size

    assert check_window_size((32, 8192)) == (32, 8192)
    with pytest.raises(InputError, match=r"^window_size must be two whole numbers of pixels "
                       r"between 32 and 8192 \(WIDTH HEIGHT\), got 9000 10$"):
        check_window_size((9000, 10), "window_size")
    with pytest.raises(InputError, match=r"got 1.5 100$"):
        check_window_size((1.5, 100), "window_size")
    with pytest.raises(InputError, match=r"got \(100,\)$"):
        check_window_size((100,), "window_size")
    from lodbuilder.viewer.app import LevelViewer

    data = from_arrays(np.eye(3), [np.inf, 1.0, 0.5], [-1, 0, 0])
    with pytest.raises(InputError, match=r"^point_scale must be a finite number > 0, got -1$"):
        LevelViewer(data, off_screen=True, point_scale=-1)


@pytest.mark.viewer
def test_view_names_the_crs_and_units(shared_data, tmp_path):
    """A scan with a CRS (autzen_trim.laz: NAD83(HARN) Lambert, feet): the viewer's corner, the
    window title and the radius scale name it and its unit."""
    pytest.importorskip("pyproj")
    import lodbuilder
    from lodbuilder.viewer.app import LevelViewer
    from lodbuilder.viewer.source import load_view_data

    arc = tmp_path / "autzen.h5"
    lodbuilder.build_archive(shared_data / "autzen_trim.laz", arc, name="autzen")
    data = load_view_data(arc)
    assert data.units == "foot" and data.crs.startswith("PROJCS[")
    viewer = LevelViewer(data, size=2000, colour="radius", off_screen=True,
                         window_size=(400, 200))
    try:
        label = "CRS NAD_1983_HARN_Lambert_Conformal_Conic, coordinates in foot"
        assert viewer.crs_label == label
        assert viewer._crs_text.GetText(1) == label  # the lower-right corner of the level pane
        assert " ".join(viewer.scalar_bar.GetTitle().split()) == "radius (foot, log)"
    finally:
        viewer.close()
