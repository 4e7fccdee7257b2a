"""Off-screen rendering of the level viewer (EGL, no X): screenshots, slider, modes, animation."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytestmark = pytest.mark.viewer


@pytest.fixture(scope="module")
def bunny_view(shared_data):
    """bun_zipper_res3 (1,889 points) in Euclidean farthest-point order, as ViewData."""
    from plyfile import PlyData

    from lodbuilder import euclidean_fps
    from lodbuilder.viewer.data import from_arrays

    v = PlyData.read(str(shared_data / "bun_zipper_res3.ply"))["vertex"].data
    pts = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    o = euclidean_fps(pts)
    p = pts[o.order]
    return from_arrays(p, o.radius, o.parent, importance={"height": p[:, 1]}, name="bunny")


@pytest.fixture
def viewer(bunny_view):
    from lodbuilder.viewer.app import LevelViewer

    vw = LevelViewer(
        bunny_view, off_screen=True, size=200, colour="radius", view="xy", window_size=(400, 200)
    )
    yield vw
    vw.close()


def non_background(img: np.ndarray) -> int:
    return int(np.count_nonzero(np.any(img < 245, axis=2)))


def test_screenshot_is_not_blank(viewer, tmp_path):
    from PIL import Image

    out = viewer.screenshot(tmp_path / "level.png")
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape == (200, 400, 3)
    left, right = img[:, :200], img[:, 200:]
    # both panels show points: a few hundred coloured pixels at least, in many colours
    assert non_background(left) > 500 and non_background(right) > 500
    assert len(np.unique(left.reshape(-1, 3), axis=0)) > 20
    assert [p.name for p in tmp_path.iterdir()] == ["level.png"]


def test_screenshot_differs_between_levels_and_modes(viewer):
    viewer.set_level(20)
    coarse = viewer.image().astype(int)
    viewer.set_level(1500)
    fine = viewer.image().astype(int)
    assert np.abs(fine - coarse)[:, :200].mean() > 1.0
    # near the full size, the level panel looks like the full-scan panel; a coarse level does not
    below_text = slice(40, 200)
    full_panel = fine[below_text, 200:]
    assert (
        np.abs(fine[below_text, :200] - full_panel).mean()
        < np.abs(coarse[below_text, :200] - full_panel).mean()
    )
    # radius colours follow the level (its rho is the bottom of the scale), so the full-scan
    # panel changes with it too (the scan-wide scale drew a uniform level in one colour)
    assert np.abs(fine - coarse)[:, 200:].mean() > 0.5
    by_rank = (viewer.set_colour("rank"), viewer.image().astype(int))[1]
    by_height = (viewer.set_colour("importance"), viewer.image().astype(int))[1]
    assert np.abs(by_rank - fine).mean() > 1.0
    assert np.abs(by_height - by_rank).mean() > 1.0


def test_slider_sets_displayed_point_count_in_place(viewer, bunny_view):
    actors = dict(viewer.plotter.renderers[0].actors)
    mesh_id = id(viewer.level_mesh)
    for k in (1, 10, 123, 1000, len(bunny_view)):
        viewer.on_slider(math.log10(k))
        assert viewer.k == k
        assert viewer.n_displayed == k
        assert viewer.level_mesh.n_points == k
        np.testing.assert_array_equal(viewer.level_mesh.points, bunny_view.points[:k])
    assert dict(viewer.plotter.renderers[0].actors) == actors  # no actor added or removed
    assert id(viewer.level_mesh) == mesh_id
    k = viewer.set_rho(bunny_view.rho_for_size(300))
    assert k <= 300 and viewer.n_displayed == k
    assert bunny_view.radius[k] <= bunny_view.rho_for_size(300)


def test_point_size_follows_rho(viewer):
    viewer.set_level(10)
    coarse = viewer.level_actor.GetProperty().GetPointSize()
    viewer.set_level(1000)
    fine = viewer.level_actor.GetProperty().GetPointSize()
    assert coarse > fine >= 1.0


def test_box_refines_inside(viewer, bunny_view):
    viewer.set_level(50)
    lo = bunny_view.points.min(axis=0)
    hi = (bunny_view.points.min(axis=0) + bunny_view.points.max(axis=0)) / 2
    viewer.set_box(lo, hi)
    want = bunny_view.selective(50, lo, hi, viewer.refine_factor)
    assert viewer.n_displayed == want.size > 50
    viewer.set_box(None, None)
    assert viewer.n_displayed == 50


def test_voronoi_mode_colours_full_scan_by_cell(viewer, bunny_view):
    from lodbuilder.viewer.data import categorical

    viewer.set_colour("voronoi")
    viewer.set_level(8)
    img8 = viewer.image()
    viewer.set_level(200)
    img200 = viewer.image()
    # the full-scan panel shows the cells of the current level, so it changes with the level
    assert np.abs(img8[:, 200:].astype(int) - img200[:, 200:]).mean() > 1.0
    # every point has the colour of its nearest point of the level (brute force)
    pts = bunny_view.points
    d = np.linalg.norm(pts[:, None, :] - pts[None, :200, :], axis=2)
    full = np.asarray(viewer.full_mesh.point_data["colours"])
    np.testing.assert_array_equal(full, categorical(np.argmin(d, axis=1)))
    np.testing.assert_array_equal(
        np.asarray(viewer.level_mesh.point_data["colours"]), categorical(np.arange(200))
    )
    # in a box, the cells are those of the points shown
    lo, hi = pts.min(axis=0), (pts.min(axis=0) + pts.max(axis=0)) / 2
    viewer.set_box(lo, hi)
    shown = bunny_view.selective(200, lo, hi, viewer.refine_factor)
    d = np.linalg.norm(pts[:, None, :] - pts[None, shown, :], axis=2)
    full = np.asarray(viewer.full_mesh.point_data["colours"])
    np.testing.assert_array_equal(full, categorical(shown[np.argmin(d, axis=1)]))


def foreground(img: np.ndarray) -> np.ndarray:
    px = img.reshape(-1, 3).astype(float)
    return px[np.any(px < 245, axis=1)]


def test_shading_keeps_colours_on_both_panes(viewer):
    """Lighting by normals replaced eye-dome lighting, which took RGB to 40 % of its brightness
    and blanked the pane rendered before its own."""
    viewer.set_colour("rank")
    viewer.set_level(1500)
    plain = viewer.image()
    assert viewer.toggle_shading() is True
    shaded = viewer.image()
    for half in (slice(0, 200), slice(200, 400)):
        p, s = foreground(plain[40:, half]), foreground(shaded[40:, half])
        assert s.shape[0] > 0.8 * p.shape[0] > 400  # both panes still show their points
        assert s.mean() > 0.75 * p.mean()  # colours kept, not darkened
        assert np.abs(shaded[40:, half].astype(int) - plain[40:, half]).mean() > 0.5  # shaded
    viewer.set_level(1400)  # a level change keeps the shading (normals follow the level)
    assert viewer.level_mesh.GetPointData().GetNormals().GetNumberOfTuples() == 1400
    assert foreground(viewer.image()[40:, :200]).shape[0] > 400
    assert viewer.toggle_shading() is False
    viewer.set_level(1500)
    np.testing.assert_array_equal(viewer.image(), plain)  # off: exactly the plain picture


def test_scalar_bar_names_the_quantity_and_unit(bunny_view):
    from lodbuilder.viewer.app import LevelViewer

    bunny_view.units = "metre"
    try:
        vw = LevelViewer(bunny_view, off_screen=True, size=300, colour="radius", window_size=(400, 200))
    finally:
        bunny_view.units = None
    try:
        bar = vw.scalar_bar

        def title():
            assert "\n" not in bar.GetTitle()  # one line (it wrapped into 3-5 before)
            return bar.GetTitle()

        assert bar.GetVisibility() and title() == "radius (metre, log)"
        lut, legend = bar.GetLookupTable(), bunny_view.legend("radius", shown=vw.shown)
        assert lut.GetRange() == pytest.approx((legend.lo, legend.hi)) and lut.GetScale() == 1
        with_bar = vw.image()
        vw.set_colour("rank")
        assert title() == "rank (log)"
        vw.set_colour("importance")
        assert title() == "importance: height"
        assert bar.GetLookupTable().GetScale() == 0  # linear
        vw.set_colour("voronoi")
        assert not bar.GetVisibility()
        without = vw.image()
        # the bar is drawn at the right edge of the window
        right = slice(int(0.84 * 400), 400)
        assert foreground(with_bar[:, right]).shape[0] > foreground(without[:, right]).shape[0] + 200
        assert vw.crs_label == "CRS unknown, coordinates in metre"
    finally:
        vw.close()


def test_surface_preview_stays_near_the_points(viewer, bunny_view):
    viewer.set_level(1500)
    surf = viewer.reconstruct()
    assert surf.n_cells > 100
    assert viewer.toggle_surface() is True
    assert viewer._surface_actor is not None and not viewer.level_actor.GetVisibility()
    viewer.set_level(100)  # a level change drops the stale surface
    assert viewer._surface_actor is None and viewer.level_actor.GetVisibility()


def test_animation_gif(viewer, tmp_path):
    from PIL import Image

    out = viewer.animate(tmp_path / "a.gif", frames=6)
    with Image.open(out) as im:
        assert im.n_frames == 6
        im.seek(0)
        first = np.asarray(im.convert("RGB")).astype(int)
        im.seek(5)
        last = np.asarray(im.convert("RGB")).astype(int)
    assert np.abs(first - last).mean() > 1.0
    assert viewer.k == 1889


def test_bad_outputs(viewer, tmp_path):
    from lodbuilder.errors import InputError, MissingDependencyError

    with pytest.raises(InputError, match=r"screenshot .*x\.jpg must end in \.png"):
        viewer.screenshot(tmp_path / "x.jpg")
    with pytest.raises(InputError, match=r"animation .*x\.avi must end in \.gif or \.mp4"):
        viewer.animate(tmp_path / "x.avi")
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        with pytest.raises(MissingDependencyError, match="needs imageio and imageio-ffmpeg"):
            viewer.animate(tmp_path / "x.mp4")
    assert list(tmp_path.iterdir()) == []


def test_controls_drive_the_viewer(viewer, bunny_view):
    """The slider widget, the keys and the box widget of the window call into the viewer."""
    viewer.add_controls()
    widgets = getattr(viewer.plotter, "widgets", viewer.plotter)
    slider = widgets.slider_widgets[0]
    slider.GetRepresentation().SetValue(math.log10(321))
    slider.InvokeEvent("InteractionEvent")
    assert viewer.k == 321 and viewer.n_displayed == 321
    iren = viewer.plotter.iren.interactor

    def press(key):
        iren.SetKeySym(key)
        iren.InvokeEvent("KeyPressEvent")

    mode = viewer.mode
    press("c")
    assert viewer.mode != mode
    press("l")
    assert viewer.shade is True
    press("Right")
    assert viewer.k == 642 and viewer.n_displayed == 642
    assert slider.GetRepresentation().GetValue() == pytest.approx(math.log10(642))
    size = viewer.level_actor.GetProperty().GetPointSize()
    press("plus")
    assert viewer.level_actor.GetProperty().GetPointSize() > size or size == 40.0
    press("b")  # box widget on: refine inside it
    assert viewer.box is not None and viewer.n_displayed > 642
    box = widgets.box_widgets[0]
    lo, hi = bunny_view.points.min(axis=0), bunny_view.points.max(axis=0)
    box.PlaceWidget([lo[0], (lo[0] + hi[0]) / 2, lo[1], hi[1], lo[2], hi[2]])
    box.InvokeEvent("EndInteractionEvent")
    np.testing.assert_allclose(viewer.box[0], lo, atol=1e-9)
    assert viewer.n_displayed == bunny_view.selective(642, *viewer.box, viewer.refine_factor).size
    press("m")
    assert viewer._surface_actor is not None
    press("b")  # box widget off: back to the plain level
    assert viewer.box is None and viewer.n_displayed == 642
    img = viewer.image()
    assert non_background(img[40:, :200]) > 500


def test_animation_mp4_when_imageio_ffmpeg_is_there(viewer, tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v2 as iio

    out = viewer.animate(tmp_path / "a.mp4", frames=5)
    with iio.get_reader(str(out)) as reader:
        frames = [f for f in reader.iter_data()]
    assert len(frames) == 5 and frames[0].shape == (200, 400, 3)
    assert np.abs(frames[0].astype(int) - frames[-1]).mean() > 1.0
