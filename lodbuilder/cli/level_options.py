"""Options that say which level of which scan a command reads: ARCHIVE, --scan, one of
--rho / --size / --fraction (or their lists), --box, --ordering and --up. slice, export, view and
evaluate add them from here, each with its own help where its meaning differs."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..filters import LevelFilter

SCAN_HELP = "scan name (may be left out when the archive holds one scan)"


def add_archive_options(p: argparse.ArgumentParser, *, scan_help: str = SCAN_HELP) -> None:
    """The ARCHIVE argument (a file or an ``https://`` / ``s3://`` URL) and --scan."""
    p.add_argument(
        "archive", metavar="ARCHIVE", help="archive written by lodbuilder build (file or URL)"
    )
    p.add_argument("--scan", help=scan_help)
    add_remote_options(p)


def seconds(text: str) -> float:
    """argparse type of --timeout: a number of seconds above 0."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number of seconds above 0, got {text!r}")
    return value


def add_remote_options(p: argparse.ArgumentParser) -> None:
    """--timeout and --follow-redirects: how an archive at a URL is read (every command that
    reads an archive; ``main`` applies them with :func:`lodbuilder.archive.remote.settings`)."""
    g = p.add_argument_group("archives at a URL")
    g.add_argument(
        "--timeout",
        type=seconds,
        metavar="SECONDS",
        help="give up when the server does not answer for SECONDS (default 30)",
    )
    g.add_argument(
        "--follow-redirects",
        action="store_true",
        help="follow an HTTP redirect to another host (refused by default)",
    )


def add_level_options(
    p: argparse.ArgumentParser,
    *,
    required: bool,
    many: bool = False,
    what: str = "",
    scan_help: str = SCAN_HELP,
) -> None:
    """ARCHIVE, --scan and one of --rho / --size / --fraction (``many``: --rhos / --sizes /
    --fractions, lists of levels); ``what`` starts each help text (e.g. "initial level: ")."""
    add_archive_options(p, scan_help=scan_help)
    g = p.add_mutually_exclusive_group(required=required)
    for name, kind, var, text in (
        ("rho", float, "R", "covering radius rho"),
        ("size", int, "N", "number of points"),
        ("fraction", float, "F", "fraction of the points, in (0, 1]"),
    ):
        if many:
            g.add_argument(f"--{name}s", type=kind, nargs="+", metavar=var, help=f"{what}{text}")
        else:
            g.add_argument(f"--{name}", type=kind, help=f"{what}{text}")


def add_box_option(p: argparse.ArgumentParser, help: str) -> None:
    """--box XMIN YMIN ZMIN XMAX YMAX ZMAX."""
    p.add_argument(
        "--box",
        type=float,
        nargs=6,
        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
        help=help,
    )


def add_ordering_option(p: argparse.ArgumentParser, help: str) -> None:
    """--ordering NAME: an extra ordering stored with the scan."""
    p.add_argument("--ordering", help=help)


def add_up_option(p: argparse.ArgumentParser, *, default: str | None, help: str) -> None:
    """--up AXIS: the scan's up axis for the first view."""
    p.add_argument("--up", default=default, choices=("z", "y", "x", "-z", "-y", "-x"), help=help)


def add_filter_options(p: argparse.ArgumentParser) -> None:
    """--class, --return, --where, --clip-box, --polygon: keep the points of the level that pass
    (one :class:`lodbuilder.filters.LevelFilter`, built by :func:`filter_from_args`)."""
    g = p.add_argument_group(
        "survey filters (keep the level's points that pass all of them; coordinates in the "
        "archive's CRS)"
    )
    g.add_argument("--class", dest="filter_class", metavar="CODES",
                   help="classification codes or ASPRS names, e.g. 2,6 or ground,building")
    g.add_argument("--return", dest="filter_return", metavar="R",
                   help="return numbers and/or first, last, only (e.g. first or 1,2)")
    g.add_argument("--where", dest="filter_where", action="append", metavar="NAME=LO:HI",
                   help="attribute range, bounds included, either may be left out "
                   "(repeatable): intensity=100:2000")
    g.add_argument("--clip-box", dest="filter_box", type=float, nargs="+", metavar="V",
                   help="XMIN YMIN XMAX YMAX, or XMIN YMIN ZMIN XMAX YMAX ZMAX")
    g.add_argument("--polygon", dest="filter_polygon", metavar="WKT|GEOJSON|FILE",
                   help="keep the points inside a polygon (x, y): WKT POLYGON/MULTIPOLYGON, "
                   "GeoJSON, or a file holding either")


def filter_from_args(args: argparse.Namespace) -> LevelFilter | None:
    """The :class:`lodbuilder.filters.LevelFilter` of the filter options, None when none given."""
    from ..filters import LevelFilter, parse_classes, parse_polygon, parse_range, parse_returns

    box = getattr(args, "filter_box", None)
    if box is not None and len(box) not in (4, 6):
        from ..errors import InputError

        raise InputError(f"--clip-box takes 4 numbers (XMIN YMIN XMAX YMAX) or 6, got {len(box)}")
    flt = LevelFilter(
        classes=parse_classes(args.filter_class) if getattr(args, "filter_class", None) else None,
        returns=parse_returns(args.filter_return) if getattr(args, "filter_return", None) else None,
        ranges=tuple(parse_range(w) for w in getattr(args, "filter_where", None) or ()),
        box=tuple(box) if box is not None else None,
        polygons=parse_polygon(args.filter_polygon) if getattr(args, "filter_polygon", None) else None,
    )
    return None if flt.empty else flt


def level_query(args: argparse.Namespace) -> Any:
    """The :class:`~lodbuilder.levels.LevelQuery` of a command's level options (checked)."""
    from ..levels import LevelQuery

    def tup(v: Any) -> Any:
        return None if v is None else tuple(float(x) for x in v)

    return LevelQuery(
        rho=getattr(args, "rho", None), size=getattr(args, "size", None), fraction=getattr(args, "fraction", None),
        ordering=getattr(args, "ordering", None), box=tup(getattr(args, "box", None)),
        box_rho=getattr(args, "box_rho", None), viewpoint=tup(getattr(args, "viewpoint", None)),
        slope=getattr(args, "slope", None), rho_max=getattr(args, "rho_max", None),
        floor_rho=getattr(args, "floor_rho", None), fill=getattr(args, "fill", None),
    )
