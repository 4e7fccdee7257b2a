"""``lodbuilder view``: look at the levels of an archive (window, screenshot or animation)."""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

from ..errors import InputError
from .level_options import (
    add_box_option,
    add_filter_options,
    add_level_options,
    add_ordering_option,
    add_up_option,
    filter_from_args,
)

MODES_HELP = (
    "rgb, radius, rank, importance[:NAME], scan, voronoi, gaps (red: near a hole the level "
    "cannot cover at its rho, filled by 'slice --fill'; orange: near a rough one, not filled)"
)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "view",
        help="show an archive's levels in a PyVista window, or render a screenshot/animation",
        description=(
            "Open a window with the current level on the left (slider over the point count on a "
            "log scale) and the full scan on the right. Keys: c colour mode, l shading by normals, "
            "b refine inside a box, m surface of the level, +/- point size, Left/Right halve or "
            "double the level. With --screenshot or --animate nothing is shown on screen (works "
            "without X through EGL)."
        ),
    )
    add_level_options(
        p,
        required=False,
        what="initial level: ",
        scan_help="scan to show (default: the only scan, or every scan merged)",
    )
    add_ordering_option(p, "show the levels of an extra ordering (e.g. weighted; default uniform)")
    p.add_argument("--colour", "--color", dest="colour", help=f"colour mode: {MODES_HELP}")
    p.add_argument("--screenshot", metavar="OUT.png", help="render the level off screen to a PNG")
    p.add_argument(
        "--animate", metavar="OUT.gif", help="render coarse-to-fine off screen (.gif, or .mp4)"
    )
    p.add_argument("--frames", type=int, default=40, help="animation frames (default 40)")
    p.add_argument("--fps", type=float, default=10.0, help="animation frames per second")
    p.add_argument(
        "--window-size", type=int, nargs=2, metavar=("W", "H"), help="pixels, 32 to 8192 a side (default 1600 800)"
    )
    p.add_argument("--no-full", action="store_true", help="do not show the full scan beside")
    p.add_argument(
        "--shade",
        "--edl",
        dest="shade",
        action="store_true",
        help="start with the points lit by their normals (key l; replaces eye-dome lighting, "
        "which darkened colours)",
    )
    add_box_option(p, "refine inside this box (rho / --refine-factor there)")
    p.add_argument("--refine-factor", type=float, default=4.0, help="box refinement (default 4)")
    p.add_argument("--surface", action="store_true", help="show a surface of the level")
    p.add_argument(
        "--view",
        default="iso",
        choices=("iso", "xy", "xz", "yz", "yx", "zx", "zy"),
        help="camera direction (default iso)",
    )
    add_up_option(
        p,
        default="z",
        help="the scan's up axis for the default view (z for survey data; y for many range scans, "
        "e.g. the Stanford bunny)",
    )
    p.add_argument("--point-scale", type=float, default=1.0, help="scale the rho point size (> 0; default 1)")
    add_filter_options(p)
    return p


def _has_display() -> bool:
    if sys.platform != "linux":
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def run(args: argparse.Namespace) -> int:
    from .output import say

    off_screen = bool(args.screenshot or args.animate)
    _check_options(args, off_screen)
    if off_screen:
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    from .._optional import require

    require("pyvista", "lodbuilder view")

    from ..viewer.source import load_view_data

    flt = filter_from_args(args)
    data = load_view_data(args.archive, args.scan, args.ordering, flt)
    if flt is not None:
        say(args, f"filter {flt.describe()}: {len(data):,} points kept; {flt.guarantee(None)}")
    from ..levels import LevelQuery

    query = LevelQuery(rho=args.rho, size=args.size, fraction=args.fraction)
    size = query.prefix_size(len(data), data.size_for_rho) if query.chosen else None
    if args.colour:
        data.check_mode(args.colour)

    from ..viewer.app import LevelViewer

    viewer = LevelViewer(
        data,
        size=size,
        colour=args.colour,
        off_screen=off_screen,
        full_scan=not args.no_full,
        window_size=args.window_size,
        point_scale=args.point_scale,
        shade=args.shade,
        view=args.view,
        up=args.up,
        refine_factor=args.refine_factor,
    )
    try:
        _show(args, viewer, off_screen)
    finally:
        viewer.close()
    return 0


def _check_options(args: argparse.Namespace, off_screen: bool) -> None:
    """Refuse bad outputs and numbers, and a window without a display, before reading anything."""
    from ..viewer.options import check_point_scale, check_window_size
    from .output import check_output

    for opt, out, suffixes in (
        ("--screenshot", args.screenshot, (".png",)),
        ("--animate", args.animate, (".gif", ".mp4")),
    ):
        if out:
            check_output(out, opt, inputs={"archive": args.archive}, suffixes=suffixes)
    if args.animate:
        from ..viewer.movie import check_movie_path

        check_movie_path(args.animate)
    if args.frames < 2:
        raise InputError(f"--frames must be at least 2, got {args.frames}")
    if args.fps <= 0:
        raise InputError(f"--fps must be > 0, got {args.fps}")
    if args.window_size is not None:
        check_window_size(args.window_size)
    check_point_scale(args.point_scale)
    if args.refine_factor <= 1:
        raise InputError(f"--refine-factor must be > 1, got {args.refine_factor}")
    if not off_screen and not _has_display():
        raise InputError(
            "no display to open a window on (DISPLAY is not set); render off screen with "
            "--screenshot OUT.png or --animate OUT.gif"
        )


def _show(args: argparse.Namespace, viewer: Any, off_screen: bool) -> None:
    """The box and surface asked for, then the window, or the screenshot and the animation."""
    from .output import say

    if args.box:
        viewer.set_box(args.box[:3], args.box[3:], render=False)
    if args.surface:
        viewer.toggle_surface()
    if not off_screen:
        viewer.show()
        return
    if args.screenshot:
        out = viewer.screenshot(args.screenshot)
        say(args, f"wrote {out} ({viewer.n_displayed:,} points, colour {viewer.mode})")
    if args.animate:
        out = viewer.animate(args.animate, frames=args.frames, fps=args.fps)
        say(args, f"wrote {out} ({args.frames} frames, coarse to fine)")
