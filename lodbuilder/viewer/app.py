"""The PyVista level viewer. Importing this module imports PyVista: only the viewer does.

One :class:`LevelViewer` owns one ``pyvista.Plotter`` with the current level on the left and the
full scan on the right (cameras linked). A level change swaps the level mesh's point, vertex and
colour arrays in place (zero-copy views of the stored prefix); no actor is added or removed.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyvista as pv
from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray

from .._validate import strict_methods
from ..errors import InputError
from . import overlays
from .data import LEVEL_MODES, ViewData, crs_label
from .options import check_point_scale, check_window_size

log = logging.getLogger(__name__)

UPS = ("x", "y", "z", "-x", "-y", "-z")
VIEWS = ("iso", "xy", "xz", "yz", "yx", "zx", "zy")
HELP = (
    "slider: level (log10 points)   c: colour mode   l: shading   b: refine in a box\n"
    "m: surface of the level   +/-: point size   Left/Right: level /2, x2   q: quit"
)


def _vtk_array(arr: np.ndarray, name: str):
    a = numpy_to_vtk(arr, deep=False)
    a.SetName(name)
    return a


@strict_methods
class LevelViewer:
    """An interactive (or off-screen) window over the levels of :class:`ViewData`.

    Args:
        data: the scan(s) to show.
        size: initial level size (default: 5 % of the points, at least 1000 and at most N).
        colour: initial colour mode (default: ``rgb`` when the scan has colours, else ``radius``).
        off_screen: render without a window (screenshots, animations, tests).
        full_scan: show the full scan side by side, cameras linked.
        window_size: pixels (width, height).
        point_scale: multiplies the point size that follows rho.
        shade: start with the points lit by their normals (see :mod:`.overlays`; it replaces
            eye-dome lighting, which darkened colours and worked on one pane only).
        view: initial camera direction (``iso``, ``xy``, ``xz``, ``yz``, ...).
        refine_factor: inside the refinement box, rho is divided by this.
    """

    def __init__(
        self,
        data: ViewData,
        *,
        size: int | None = None,
        colour: str | None = None,
        off_screen: bool = False,
        full_scan: bool = True,
        window_size: Sequence[int] | None = None,
        point_scale: float = 1.0,
        shade: bool = False,
        view: str = "iso",
        refine_factor: float = 4.0,
        show_help: bool = True,
        up: str = "z",
    ) -> None:
        if view not in VIEWS:
            raise InputError(f"view must be one of {', '.join(VIEWS)}, got {view!r}")
        if up not in UPS:
            raise InputError(f"up must be one of {', '.join(UPS)}, got {up!r}")
        self.up = up
        data.up = up  # (what colour mode ``elevation`` reads)
        self.data = data
        n = len(data)
        self.k = data.clamp_size(size if size is not None else min(n, max(1000, n // 20)))
        modes = data.colour_modes()
        self.mode = data.check_mode(colour) if colour else modes[0]
        self.point_scale = check_point_scale(point_scale, "point_scale")
        self.refine_factor = float(refine_factor)
        self.box: tuple[np.ndarray, np.ndarray] | None = None
        self.shade = False
        self.full_scan = bool(full_scan)
        self._ids = np.arange(n + 1, dtype=np.int64)
        self._refs: dict[int, tuple[np.ndarray, ...]] = {}  # arrays VTK views, per mesh
        self._pos: np.ndarray | None = None  # stored positions shown, None for the prefix
        self._colours = data.colours(self.mode, self.k)
        self._surface_actor: Any = None
        self._slider: Any = None
        self.full_mesh: pv.PolyData | None = None
        # the full scan's spacing, from the level of half the points (rho ~ 1/sqrt(k) on a surface)
        self._full_rho = data.rho_for_size(max(1, len(data) // 2)) / math.sqrt(2.0)
        self.plotter: Any = self._make_plotter(off_screen, full_scan, window_size)
        self.level_mesh = pv.PolyData()
        self._update_level_arrays()
        self._add_level_pane(show_help and not off_screen)
        if full_scan:
            self._add_full_pane()
        self._add_overlays()
        self._set_view(view)
        self._update_point_size()
        self._update_text()
        if shade:
            self.toggle_shading()

    @staticmethod
    def _make_plotter(off_screen: bool, full_scan: bool, window_size: Sequence[int] | None) -> Any:
        """A white plotter of one pane, or two side by side for the full scan."""
        if window_size is None:
            window_size = (1600, 800) if full_scan else (1000, 800)
        window_size = check_window_size(window_size, "window_size")
        shape = (1, 2) if full_scan else (1, 1)
        plotter_cls: Any = pv.Plotter  # (pyvista's decorated __init__ confuses type checkers)
        # No multisampling: points do not need it, and 8x MSAA (PyVista's default) costs ~70 ms a
        # frame at 1600x800 under software OpenGL (llvmpipe), more than drawing 100k points.
        plotter = plotter_cls(off_screen=off_screen, shape=shape, window_size=list(window_size))
        plotter.ren_win.SetMultiSamples(0)
        plotter.set_background("white")
        return plotter

    def _add_level_pane(self, show_help: bool) -> None:
        """The level's points and its text (and the key help) in the left pane."""
        self.plotter.subplot(0, 0)
        self.level_actor = self.plotter.add_mesh(
            self.level_mesh, scalars="colours", rgb=True, style="points", point_size=3.0
        )
        self._text = self.plotter.add_text("", position="upper_left", font_size=10, color="black")
        if show_help:
            self.plotter.add_text(HELP, position="lower_left", font_size=9, color="gray")

    def _add_full_pane(self) -> None:
        """Every point of the scan in the right pane, its camera linked to the level's."""
        n = len(self.data)
        self.plotter.subplot(0, 1)
        self.full_mesh = pv.PolyData()
        self._set_arrays(self.full_mesh, self.data.points, n, self._colours)
        self.full_actor = self.plotter.add_mesh(
            self.full_mesh, scalars="colours", rgb=True, style="points", point_size=2.0
        )
        names = ", ".join(self.data.scan_names)
        self.plotter.add_text(
            f"full scan: {n:,} points ({names})",
            position="upper_left",
            font_size=10,
            color="black",
        )
        self.plotter.link_views()

    def _add_overlays(self) -> None:
        """The scale of the colour mode in the rightmost pane; the CRS in the level pane's corner."""
        self.scalar_bar = overlays.scalar_bar()
        self.plotter.renderers[-1].AddViewProp(self.scalar_bar)
        self.legend_box = overlays.legend_box()
        self.plotter.renderers[-1].AddViewProp(self.legend_box)
        overlays.set_scalar_bar(self.scalar_bar, self.data.legend(self.mode, self.shown), self.legend_box)
        self.plotter.subplot(0, 0)
        self.crs_label = crs_label(self.data.crs, self.data.units)
        self._crs_text = self.plotter.add_text(
            self.crs_label, position="lower_right", font_size=9, color="black"
        )

    # ---- arrays -------------------------------------------------------------------------------

    def _set_arrays(
        self,
        mesh: pv.PolyData,
        pts: np.ndarray,
        m: int,
        colours: np.ndarray,
        normals: np.ndarray | None = None,
    ) -> None:
        """Point ``mesh`` at ``pts``/``colours``/``normals`` (no copy when they are contiguous)
        with m vertices."""
        pts = np.ascontiguousarray(pts)
        colours = np.ascontiguousarray(colours)
        self._refs[id(mesh)] = (pts, colours) if normals is None else (pts, colours, normals)
        vp = vtkPoints()
        vp.SetData(numpy_to_vtk(pts, deep=False))
        mesh.SetPoints(vp)
        cells = vtkCellArray()
        cells.SetData(
            numpy_to_vtkIdTypeArray(self._ids[: m + 1], deep=False),
            numpy_to_vtkIdTypeArray(self._ids[:m], deep=False),
        )
        mesh.SetVerts(cells)
        pd = mesh.GetPointData()
        pd.AddArray(_vtk_array(colours, "colours"))
        pd.SetActiveScalars("colours")
        if normals is not None:
            normals = np.ascontiguousarray(normals)
            pd.SetNormals(_vtk_array(normals, "Normals"))
        mesh.Modified()

    @property
    def shown(self) -> int | np.ndarray:
        """What the level pane shows: the prefix size k, or the stored positions (in a box)."""
        return self.k if self._pos is None else self._pos

    def _update_level_arrays(self) -> None:
        """Recompute what the level pane shows (and the Voronoi colours, which follow it)."""
        k = self.k
        self._pos = (
            None
            if self.box is None
            else self.data.selective(k, self.box[0], self.box[1], self.refine_factor)
        )
        if self.mode in LEVEL_MODES:
            self._colours = self.data.colours(self.mode, self.shown)
            self._update_full_colours()
            if self.mode == "radius" and getattr(self, "scalar_bar", None) is not None:
                # (its scale follows the level: ViewData.legend)
                overlays.set_scalar_bar(self.scalar_bar, self.data.legend(self.mode, self.shown),
                                        self.legend_box)
        sel = slice(0, k) if self._pos is None else self._pos
        normals = self.data.normals()[sel] if self.shade else None
        pts, col = self.data.points[sel], self._colours[sel]
        self._set_arrays(self.level_mesh, pts, pts.shape[0], col, normals)

    def _update_full_colours(self) -> None:
        if self.full_mesh is not None:
            refs = self._refs.get(id(self.full_mesh), ())
            self._refs[id(self.full_mesh)] = (self.data.points, self._colours, *refs[2:])
            pd = self.full_mesh.GetPointData()
            pd.AddArray(_vtk_array(self._colours, "colours"))
            pd.SetActiveScalars("colours")
            self.full_mesh.Modified()

    @property
    def n_displayed(self) -> int:
        """Number of points the level mesh currently draws."""
        return int(self.level_mesh.GetNumberOfVerts())

    @property
    def rho(self) -> float:
        return self.data.rho_for_size(self.k)

    # ---- level, colour, size ------------------------------------------------------------------

    def set_level(self, k: float, render: bool = True) -> int:
        """Show the level of ``k`` points (the prefix, refined inside the box if one is set)."""
        self.k = self.data.clamp_size(k)
        self._update_level_arrays()
        if self._surface_actor is not None:
            self._remove_surface()
        self._update_point_size()
        self._update_text()
        if self._slider is not None:  # keys move the level too: keep the slider in step
            self._slider.GetRepresentation().SetValue(math.log10(self.k))
        if render:
            self._render_level()
        return self.k

    def _render_level(self) -> None:
        """Render after a change of the level panel only: the full-scan panel is left as drawn
        (it is not redrawn unless its colours change), which halves the cost of a slider move."""
        if self.full_mesh is None or self.mode in LEVEL_MODES:
            self.plotter.render()
            return
        full = self.plotter.renderers[1]
        full.SetDraw(False)
        try:
            self.plotter.render()
        finally:
            full.SetDraw(True)

    def set_rho(self, rho: float, render: bool = True) -> int:
        """Show the smallest level that covers the scan within ``rho``."""
        return self.set_level(self.data.size_for_rho(rho), render)

    def on_slider(self, value: float) -> None:
        """Slider callback: ``value`` is log10 of the point count."""
        self.set_level(10.0 ** float(value))

    def set_colour(self, mode: str, render: bool = True) -> str:
        self.mode = self.data.check_mode(mode)
        self._colours = self.data.colours(self.mode, self.shown)
        self._update_level_arrays()
        self._update_full_colours()
        overlays.set_scalar_bar(self.scalar_bar, self.data.legend(self.mode, self.shown), self.legend_box)
        self._update_text()
        if render:
            self.plotter.render()
        return self.mode

    def next_colour(self) -> str:
        modes = self.data.colour_modes()
        i = modes.index(self.mode) if self.mode in modes else -1
        return self.set_colour(modes[(i + 1) % len(modes)])

    def _pixels_per_unit(self) -> float:
        ren = self.plotter.renderers[0]
        cam = ren.GetActiveCamera()
        h_px = max(1, ren.GetSize()[1])
        if cam.GetParallelProjection():
            visible = 2.0 * cam.GetParallelScale()
        else:
            visible = 2.0 * cam.GetDistance() * math.tan(math.radians(cam.GetViewAngle()) / 2.0)
        return h_px / max(visible, 1e-300)

    def point_size_for(self, rho: float) -> float:
        """Screen size (pixels) of a point at density ``rho``: a square about 1.5 rho wide."""
        if self.box is not None:
            rho = rho / self.refine_factor
        # never smaller than the full scan's own spacing (the last radii of an ordering are tiny)
        rho = max(rho, self._full_rho) if self._full_rho > 0 else rho
        if rho <= 0:
            rho = self.data.diagonal * 1e-3
        # squares 1.5 rho wide: the level's points are about rho apart, so this closes the gaps
        px = 1.5 * rho * self._pixels_per_unit() * self.point_scale
        return float(min(40.0, max(1.0, px)))

    def _update_point_size(self) -> None:
        self.level_actor.GetProperty().SetPointSize(self.point_size_for(self.rho))
        if self.full_mesh is not None:
            self.full_actor.GetProperty().SetPointSize(
                max(2.0, self.point_size_for(self._full_rho))
            )

    def scale_points(self, factor: float) -> None:
        self.point_scale *= factor
        self._update_point_size()
        self.plotter.render()

    def _update_text(self) -> None:
        n = len(self.data)
        box = (
            f", x{self.refine_factor:g} finer in box ({self.n_displayed:,} shown)"
            if self.box
            else ""
        )
        self._text.SetText(
            2,
            f"level: {self.k:,} of {n:,} points ({100.0 * self.k / n:.3g} %), rho = {self.rho:.4g}{box}\n"
            f"colour: {self.mode}",
        )

    # ---- view ---------------------------------------------------------------------------------

    def _set_view(self, view: str) -> None:
        self.plotter.subplot(0, 0)
        bounds = np.column_stack(
            [self.data.points.min(axis=0), self.data.points.max(axis=0)]
        ).ravel()
        if view == "iso":
            # facing the scan: see lodbuilder.viewer.data.facing_camera
            from .data import facing_camera

            direction, up = facing_camera(self.data.points, self.up)
            lo, hi = bounds[0::2], bounds[1::2]
            centre = (lo + hi) / 2
            far = float(np.linalg.norm(hi - lo)) or 1.0
            self.plotter.camera_position = [
                tuple(centre + direction * far), tuple(centre), tuple(up)
            ]
        else:
            getattr(self.plotter, f"view_{view}")(bounds=bounds)
        self.plotter.reset_camera(bounds=bounds)

    def toggle_shading(self) -> bool:
        """Light the points of both panes by their normals, or draw them flat (key ``l``).

        The normals are the scan's PCA normals (computed once, on first use); see
        :mod:`lodbuilder.viewer.overlays` for why this replaces eye-dome lighting."""
        self.shade = not self.shade
        self._update_level_arrays()
        actors = [self.level_actor]
        if self.full_mesh is not None:
            normals = self.data.normals() if self.shade else None
            self._set_arrays(self.full_mesh, self.data.points, len(self.data), self._colours, normals)
            actors.append(self.full_actor)
        for actor in actors:
            overlays.set_shading(actor, self.shade)
        self.plotter.render()
        return self.shade

    # ---- selective refinement -----------------------------------------------------------------

    def set_box(self, lo, hi, render: bool = True) -> None:
        """Refine inside the axis-aligned box [lo, hi] (``None`` to clear)."""
        if lo is None:
            self.box = None
        else:
            lo_a, hi_a = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
            if lo_a.shape != (3,) or hi_a.shape != (3,) or np.any(hi_a < lo_a):
                raise InputError(f"box must be xmin ymin zmin <= xmax ymax zmax, got {lo} and {hi}")
            self.box = (lo_a, hi_a)
        self.set_level(self.k, render)

    def _on_box_widget(self, box) -> None:
        b = np.asarray(box.GetBounds() if hasattr(box, "GetBounds") else box.bounds)
        self.set_box(b[0::2], b[1::2])

    def toggle_box_widget(self) -> None:
        """Show a box widget on the level (refining inside it), or remove it and the refinement."""
        self.plotter.subplot(0, 0)
        widgets = getattr(self.plotter, "widgets", self.plotter)  # pyvista >= 0.47 groups them
        if widgets.box_widgets:
            widgets.clear_box_widgets()
            self.set_box(None, None)
            return
        lo, hi = self.data.points.min(axis=0), self.data.points.max(axis=0)
        c, half = (lo + hi) / 2, (hi - lo) / 4
        bounds = np.column_stack([c - half, c + half]).ravel()
        self.plotter.add_box_widget(
            self._on_box_widget, bounds=bounds, factor=1.0, rotation_enabled=False
        )
        self.set_box(c - half, c + half)

    # ---- surface ------------------------------------------------------------------------------

    def reconstruct(self) -> pv.PolyData:
        """A surface of the shown points, trimmed to within 2 rho of them (:mod:`.surface`)."""
        from .surface import level_surface

        rho = max(self.rho, self._full_rho)  # (in a box the points are closer: rho still bounds)
        return level_surface(np.asarray(self.level_mesh.points, dtype=np.float64), rho)

    def toggle_surface(self) -> bool:
        if self._surface_actor is not None:
            self._remove_surface()
            self.plotter.render()
            return False
        self.plotter.subplot(0, 0)
        self._surface_actor = self.plotter.add_mesh(
            self.reconstruct(), color="lightgray", smooth_shading=True, name="level-surface"
        )
        self.level_actor.SetVisibility(False)
        self.plotter.render()
        return True

    def _remove_surface(self) -> None:
        self.plotter.subplot(0, 0)
        self.plotter.remove_actor(self._surface_actor, render=False)
        self._surface_actor = None
        self.level_actor.SetVisibility(True)

    # ---- interaction --------------------------------------------------------------------------

    def add_controls(self) -> None:
        """Slider and key bindings of the interactive window."""
        n = len(self.data)
        self.plotter.subplot(0, 0)
        self._slider = self.plotter.add_slider_widget(
            self.on_slider,
            rng=[0.0, math.log10(n) if n > 1 else 1.0],
            value=math.log10(self.k),
            title="log10(points)",
            pointa=(0.05, 0.1),
            pointb=(0.95, 0.1),
            style="modern",
            interaction_event="always",
        )
        self.plotter.add_key_event("c", self.next_colour)
        self.plotter.add_key_event("l", self.toggle_shading)
        self.plotter.add_key_event("b", self.toggle_box_widget)
        self.plotter.add_key_event("m", self.toggle_surface)
        self.plotter.add_key_event("plus", lambda: self.scale_points(1.25))
        self.plotter.add_key_event("minus", lambda: self.scale_points(0.8))
        self.plotter.add_key_event("Right", lambda: self.set_level(self.k * 2))
        self.plotter.add_key_event("Left", lambda: self.set_level(self.k / 2))

    def show(self) -> None:
        self.add_controls()
        self.plotter.show(title=f"lodbuilder view: {', '.join(self.data.scan_names)} ({self.crs_label})")

    # ---- off screen ---------------------------------------------------------------------------

    def image(self) -> np.ndarray:
        """(H, W, 3) uint8 of the current frame."""
        self.plotter.render()
        return np.asarray(self.plotter.screenshot(None, return_img=True))

    def screenshot(self, out: str | os.PathLike) -> Path:
        """Write the current frame as PNG (atomically: temp file, then rename)."""
        out = Path(out)
        if out.suffix.lower() != ".png":
            raise InputError(f"screenshot {out} must end in .png")
        img = self.image()
        from PIL import Image

        _atomic_write(out, lambda tmp: Image.fromarray(img).save(tmp, format="PNG"))
        return out

    def animate(
        self,
        out: str | os.PathLike,
        *,
        frames: int = 40,
        fps: float = 10.0,
        start: int | None = None,
    ) -> Path:
        """Write an animation from coarse (``start`` points) to the full scan: GIF, or MP4 when
        imageio-ffmpeg is installed."""
        from .movie import write_movie

        out = Path(out)
        n = len(self.data)
        lo = start if start is not None else max(1, min(n, 10))
        from ..levels import log_sizes

        sizes = log_sizes(lo, n, max(2, int(frames)))
        images = []
        for s in sizes:
            self.set_level(int(s), render=False)
            images.append(self.image())
        return write_movie(out, images, fps)

    def close(self) -> None:
        self.plotter.close()


def _atomic_write(out: Path, write) -> None:
    from ..io._files import atomic_output

    with atomic_output(out) as tmp:
        write(str(tmp))
