"""``lodbuilder export ARCHIVE -o OUT.copc.laz | OUT.html``: a level for other tools."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from .level_options import add_level_options, add_up_option

FORMATS = {".copc.laz": "COPC", ".html": "web page", ".htm": "web page"}


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "export",
        help="write a level as a COPC file or a standalone web page",
        description=(
            "Write a level of a scan for other tools. OUT.copc.laz: a Cloud Optimized Point Cloud "
            "(QGIS, Potree, viewer.copc.io, CloudCompare, PDAL, laspy) whose octree depths are the "
            "farthest-point levels (the points of depths 0..D cover the scan within the rho "
            "written in the file), with every attribute, the CRS, the rank and the insertion "
            "radius. OUT.html: one self-contained page (no network) that draws the level with "
            "WebGL, coarse points first, with a slider over its coarser levels and colours by "
            "RGB, radius, importance or rank. Without --rho/--size/--fraction: the whole scan (a "
            "web page is capped at --max-points)."
        ),
    )
    add_level_options(p, required=False)
    p.add_argument(
        "--max-points",
        type=int,
        default=None,
        help="web page: most points it may hold (default 2,000,000: browsers slow down past it)",
    )
    add_up_option(
        p,
        default=None,
        help="web page: the scan's up axis for the first view (default z; y for many range scans)",
    )
    p.add_argument(
        "-o", "--output", required=True, metavar="OUT", help="OUT.copc.laz or OUT.html"
    )
    from .output import add_json_option

    add_json_option(p)
    return p


def output_format(out: Path) -> str:
    """The format named by ``out``'s suffix: ``COPC`` or ``web page``."""
    from ..errors import UnsupportedFormatError

    name = out.name.lower()
    for suffix, fmt in FORMATS.items():
        if name.endswith(suffix):
            return fmt
    raise UnsupportedFormatError(
        f"-o {out}: name it OUT.copc.laz (COPC) or OUT.html (web page); "
        "for .ply, .las, .laz, .csv, .npy... use lodbuilder slice"
    )


def run(args: argparse.Namespace) -> int:
    from ..archive.reader import open_archive
    from ..errors import InputError
    from .output import check_output, emit

    arc_path = args.archive  # (a path or an https:// / s3:// URL: open_archive reads both)
    out = check_output(args.output, "-o", inputs={"archive": arc_path})
    fmt = output_format(out)
    web = fmt == "web page"
    if not web:
        for opt, value in (("--max-points", args.max_points), ("--up", args.up)):
            if value is not None:
                raise InputError(f"{opt} applies to a web page (-o OUT.html) only")
    if args.max_points is not None and args.max_points < 1:
        raise InputError(f"--max-points must be at least 1, got {args.max_points}")
    if web:
        from ..export.web import MAX_POINTS, export_web
    else:
        from ..export.copc import _copclib, export_copc

        _copclib()  # a missing copclib: fail before reading anything
    from ..levels import LevelQuery

    query = LevelQuery(rho=args.rho, size=args.size, fraction=args.fraction)
    with open_archive(arc_path) as arc:
        view = arc.scan(args.scan)
        k = query.prefix_size(view.n_ordered, view.size_for_rho)
        doc: dict[str, Any] = {
            "archive": str(arc_path), "scan": view.name, "output": str(out), "format": fmt
        }
        if web:
            cap = args.max_points or MAX_POINTS
            note = ""
            if k > cap:
                if query.chosen:
                    raise InputError(
                        f"the level has {k:,} points, more than a web page holds ({cap:,}); "
                        "ask for a coarser level (--rho, --size) or raise --max-points"
                    )
                k, note = cap, f", capped at --max-points {cap:,}"
            page = export_web(view, out, k, up=args.up or "z")
            rho = f"rho = {page.rho:.4g}" if page.rho > 0 else "every point"
            doc.update(size=page.n_points, n_points=page.n_total, rho=page.rho,
                       bytes=page.n_bytes, chunks=page.chunks, capped=bool(note))
            text = (
                f"wrote {page.n_points:,} of {page.n_total:,} points of scan {view.name!r} to "
                f"{out} ({page.n_bytes / 1e6:.1f} MB, {rho}{note})"
            )
        else:
            from ..io.api import collect_notes

            with collect_notes() as changes:
                copc = export_copc(view, out, k)
            doc.update(size=copc.n_points, n_points=copc.n_total, rho=copc.rho,
                       bytes=copc.n_bytes, depths=copc.depths, nodes=copc.nodes,
                       spacing=copc.spacing, levels=copc.levels, changes=changes)
            points = " / ".join(f"{lv['points']:,}" for lv in copc.levels)
            rhos = " / ".join("inf" if lv["rho"] is None else f"{lv['rho']:.3g}" for lv in copc.levels)
            text = "\n".join(
                [
                    f"wrote {copc.n_points:,} of {copc.n_total:,} points of scan {view.name!r} "
                    f"to {out} ({copc.n_bytes / 1e6:.1f} MB, {copc.depths} depth(s), "
                    f"{copc.nodes:,} nodes)",
                    f"  depths 0..{copc.depths - 1} hold {points} points, covering radius {rhos}",
                ]
                + [f"  changed: {line}" for line in changes]
            )
    emit(args, doc, text)
    return 0
