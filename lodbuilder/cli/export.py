"""``lodbuilder export ARCHIVE -o OUT.copc.laz | OUT.html``: a level for other tools."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from .level_options import add_filter_options, add_level_options, add_up_option, filter_from_args

FORMATS = {".copc.laz": "COPC", ".html": "web page", ".htm": "web page", ".json": "3D Tiles"}


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "export",
        help="write a level as a COPC file or a standalone web page",
        description=(
            "Write a level of a scan for other tools. OUT.copc.laz: a Cloud Optimized Point Cloud "
            "(QGIS, Potree, viewer.copc.io, CloudCompare, PDAL, laspy) whose octree depths are the "
            "farthest-point levels (the points of depths 0..D cover the scan within the rho "
            "written in the file), with every attribute and the CRS; --rank-radius adds 256 "
            "sub-levels a depth with their covering radius (--rank-radius exact: the rank and "
            "the insertion radius of every point). OUT.html: one self-contained page (no network) that draws the level with "
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
    p.add_argument(
        "--all-scans",
        action="store_true",
        help="COPC or web page of every scan of the archive (a joint scan counts as its member "
        "scans), merged at --rho (default: every point), with each point's scan as attribute "
        "scan_id and the scans' names in the file",
    )
    p.add_argument(
        "--rank-radius",
        nargs="?",
        const="level",
        default=None,
        metavar="MODE",
        help="COPC: also store where each point is in the farthest-point order. level (the "
        "default): a one-byte extra dimension 'sublevel' (up to 256 equal-count sub-levels a "
        "depth) and, per depth and sub-level, the prefix and its exact covering radius (an "
        "EVLR): the points of depths < D and those of depth D with sublevel <= s are that "
        "prefix; about 1 byte a point (1.28-1.31 x the source LAZ on airborne data). exact: each "
        "point's rank (uint32 extra bytes) and the insertion radius by rank (an EVLR), 2.9-3.8 "
        "bytes a point (1.6-1.7 x)",
    )
    add_up_option(
        p,
        default=None,
        help="web page: the scan's up axis for the first view (default z; y for many range scans)",
    )
    p.add_argument(
        "-o", "--output", required=True, metavar="OUT",
        help="OUT.copc.laz, OUT.html or DIR/tileset.json (3D Tiles 1.1: the tiles go to "
        "DIR/tileset_tiles/)"
    )
    from .output import add_json_option

    add_filter_options(p)
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
        f"-o {out}: name it OUT.copc.laz (COPC), OUT.html (web page) or DIR/tileset.json (3D Tiles); "
        "for .ply, .las, .laz, .csv, .npy... use lodbuilder slice"
    )


def run(args: argparse.Namespace) -> int:
    from ..archive.reader import open_archive
    from ..levels import LevelQuery
    from .output import check_output, emit

    arc_path = args.archive  # (a path or an https:// / s3:// URL: open_archive reads both)
    out = check_output(args.output, "-o", inputs={"archive": arc_path})
    fmt = output_format(out)
    _check_format_options(args, fmt)
    flt = filter_from_args(args)
    if args.all_scans:
        return _run_all_scans(args, out, fmt, flt)
    _check_max_points(args)
    if fmt == "COPC":
        from ..export.copc import check_copc_dependencies

        check_copc_dependencies()  # a missing laspy or lazrs: fail before reading anything
    query = LevelQuery(rho=args.rho, size=args.size, fraction=args.fraction)
    with open_archive(arc_path) as arc:
        view = arc.scan(args.scan)
        k = query.prefix_size(view.n_ordered, view.size_for_rho)
        doc: dict[str, Any] = {
            "archive": str(arc_path), "scan": view.name, "output": str(out), "format": fmt
        }
        write = {"web page": _write_web, "3D Tiles": _write_tiles, "COPC": _write_copc}[fmt]
        text = write(args, view, out, k, query.chosen, flt, doc)
    if flt is not None:
        text = _with_filter(flt, doc, text, k)
    emit(args, doc, text)
    return 0


def _check_format_options(args: argparse.Namespace, fmt: str) -> None:
    """Refuse the options that do not apply to the output's format."""
    from ..errors import InputError

    if fmt != "web page":
        for opt, value in (("--max-points", args.max_points), ("--up", args.up)):
            if value is not None:
                raise InputError(f"{opt} applies to a web page (-o OUT.html) only")
    if args.rank_radius is not None and args.rank_radius not in ("level", "exact"):
        raise InputError(f"--rank-radius takes level (the default: 256 sub-levels a depth, one byte "
                         f"a point) or exact (each point's rank), got {args.rank_radius!r}")
    if args.rank_radius and fmt != "COPC":
        raise InputError("--rank-radius applies to a COPC file (-o OUT.copc.laz) only")


def _check_max_points(args: argparse.Namespace) -> None:
    from ..errors import InputError

    if args.max_points is not None and args.max_points < 1:
        raise InputError(f"--max-points must be at least 1, got {args.max_points}")


def _write_web(args: argparse.Namespace, view: Any, out: Path, k: int, chosen: bool, flt: Any,
               doc: dict[str, Any]) -> str:
    """The web page of the level's first ``k`` points (capped at --max-points unless the level was
    asked for); its figures go to ``doc``; returns the report."""
    from ..errors import InputError
    from ..export.web import MAX_POINTS, export_web

    cap = args.max_points or MAX_POINTS
    note = ""
    if k > cap:
        if chosen:
            raise InputError(
                f"the level has {k:,} points, more than a web page holds ({cap:,}); "
                "ask for a coarser level (--rho, --size) or raise --max-points"
            )
        k, note = cap, f", capped at --max-points {cap:,}"
    page = export_web(view, out, k, up=args.up or "z", flt=flt)
    rho = f"rho = {page.rho:.4g}" if page.rho > 0 else "every point"
    doc.update(size=page.n_points, n_points=page.n_total, rho=page.rho,
               bytes=page.n_bytes, chunks=page.chunks, capped=bool(note))
    return (
        f"wrote {page.n_points:,} of {page.n_total:,} points of scan {view.name!r} to "
        f"{out} ({page.n_bytes / 1e6:.1f} MB, {rho}{note})"
    )


def _write_tiles(args: argparse.Namespace, view: Any, out: Path, k: int, chosen: bool, flt: Any,
                 doc: dict[str, Any]) -> str:
    """The 3D Tiles of the level's first ``k`` points; its figures go to ``doc``; returns the report."""
    from ..export.tiles import export_tiles

    ts = export_tiles(view, out, k, flt=flt)
    doc.update(size=ts.n_points, n_points=ts.n_total, rho=ts.rho, bytes=ts.n_bytes,
               tiles=ts.tiles, depths=ts.depths, geometric_errors=ts.geometric_errors,
               placement=ts.placed)
    errs = " / ".join(f"{e:.3g}" for e in ts.geometric_errors)
    return (
        f"wrote {ts.n_points:,} of {ts.n_total:,} points of scan {view.name!r} to {out} "
        f"({ts.n_bytes / 1e6:.1f} MB, {ts.tiles:,} tiles, {ts.depths} depth(s))\n"
        f"  geometricError by depth (covering radius, metres): {errs}\n  {ts.placed}"
    )


def _write_copc(args: argparse.Namespace, view: Any, out: Path, k: int, chosen: bool, flt: Any,
                doc: dict[str, Any]) -> str:
    """The COPC file of the level's first ``k`` points; its figures go to ``doc``; returns the report."""
    from ..export.copc import export_copc
    from ..io.api import collect_notes

    with collect_notes() as changes:
        copc = export_copc(view, out, k, rank_radius=args.rank_radius, flt=flt)
    doc.update(size=copc.n_points, n_points=copc.n_total, rho=copc.rho,
               bytes=copc.n_bytes, depths=copc.depths, nodes=copc.nodes,
               spacing=copc.spacing, levels=copc.levels, changes=changes)
    points = " / ".join(f"{lv['points']:,}" for lv in copc.levels)
    rhos = " / ".join("inf" if lv["rho"] is None else f"{lv['rho']:.3g}" for lv in copc.levels)
    return "\n".join(
        [
            f"wrote {copc.n_points:,} of {copc.n_total:,} points of scan {view.name!r} "
            f"to {out} ({copc.n_bytes / 1e6:.1f} MB, {copc.depths} depth(s), "
            f"{copc.nodes:,} nodes)",
            f"  depths 0..{copc.depths - 1} hold {points} points, covering radius {rhos}",
        ]
        + [f"  changed: {line}" for line in changes]
    )


def _with_filter(flt: Any, doc: dict[str, Any], text: str, k: int) -> str:
    """The report with the survey filter's count and guarantee under its first line (also in ``doc``)."""
    kept = doc["size"]
    doc.update(filter=flt.describe(), level_size=k, guarantee=flt.guarantee(doc["rho"]))
    first, _, rest = text.partition("\n")
    return "\n".join(
        [first, f"  filter {flt.describe()}: {kept:,} of the level's {k:,} points",
         f"  guarantee: {doc['guarantee']}"] + ([rest] if rest else [])
    )


def _run_all_scans(args: argparse.Namespace, out: Any, fmt: str, flt: Any) -> int:
    """``export --all-scans``: one COPC file or web page of the whole collection."""
    from ..archive.reader import open_archive
    from ..errors import InputError
    from ..export.collection import export_collection
    from .output import emit

    for opt, bad in (("--scan", args.scan is not None), ("--size", args.size is not None),
                     ("--fraction", args.fraction is not None), ("a survey filter", flt is not None),
                     ("--rank-radius", args.rank_radius)):
        if bad:
            raise InputError(f"--all-scans merges every scan at one --rho; leave out {opt}")
    if fmt == "3D Tiles":
        raise InputError("--all-scans writes a COPC file or a web page; 3D Tiles take one scan (--scan NAME)")
    if fmt == "COPC":
        from ..export.copc import check_copc_dependencies

        check_copc_dependencies()
    from ..export.web import MAX_POINTS
    from ..io.api import collect_notes

    with open_archive(args.archive) as arc, collect_notes() as changes:
        written, merged = export_collection(arc, out, args.rho, fmt=fmt,
                                            max_points=args.max_points or MAX_POINTS, up=args.up or "z")
    doc: dict[str, Any] = {"archive": str(args.archive), "scans": merged.names, "output": str(out),
                           "format": fmt, "size": written.n_points, "n_points": merged.n_total,
                           "rho": merged.rho, "bytes": written.n_bytes, "changes": changes}
    rho = f"rho = {merged.rho:.4g}" if merged.rho > 0 else "every point"
    text = (f"wrote {written.n_points:,} of {merged.n_total:,} points of {len(merged.names)} scans "
            f"to {out} ({written.n_bytes / 1e6:.1f} MB, {rho}; attribute scan_id: "
            + ", ".join(f"{i} {n}" for i, n in enumerate(merged.names[:8]))
            + (", ..." if len(merged.names) > 8 else "") + ")")
    emit(args, doc, "\n".join([text] + [f"  changed: {line}" for line in changes]))
    return 0
