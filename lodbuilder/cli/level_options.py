"""Options that say which level of which scan a command reads: ARCHIVE, --scan, one of
--rho / --size / --fraction (or their lists), --box, --ordering and --up. slice, export, view and
evaluate add them from here, each with its own help where its meaning differs."""

from __future__ import annotations

import argparse
from typing import Any

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
