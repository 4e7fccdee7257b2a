"""``lodbuilder slice ARCHIVE (--rho R | --size N | --fraction F) -o OUT``: write one level."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from .level_options import (
    add_box_option,
    add_filter_options,
    add_level_options,
    add_ordering_option,
    filter_from_args,
)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "slice",
        help="write one level of detail of a scan",
        description=(
            "Write the level of a scan given by a density RHO (every input point within RHO of a "
            "kept point), a SIZE or a FRACTION, with its attributes, to OUT (.ply, .npy, .csv, ...). "
            "--box with --box-rho makes it finer inside a box; --viewpoint with --slope makes rho "
            "grow with the distance from a point (rho = RHO + SLOPE * distance)."
        ),
    )
    add_level_options(p, required=True)
    add_box_option(p, "refine inside this box (needs --rho outside and --box-rho inside)")
    p.add_argument("--box-rho", type=float, metavar="R", help="finer rho inside --box")
    p.add_argument(
        "--viewpoint", type=float, nargs=3, metavar=("X", "Y", "Z"), help="refine near this point"
    )
    p.add_argument(
        "--slope", type=float, default=None, help="growth of rho per unit distance from --viewpoint"
    )
    p.add_argument("--rho-max", type=float, default=None, help="cap of rho far from --viewpoint")
    add_ordering_option(
        p, "take the prefix of a stored extra ordering instead of the uniform one"
    )
    p.add_argument(
        "--extra", action="store_true", help="also write source_index, radius and rank per point"
    )
    p.add_argument(
        "--all-scans",
        action="store_true",
        help="write the --rho level of every scan of the archive, merged, with a scan_id attribute (a joint "
        "scan counts as its member scans; with --scan NAME only that scan or joint member)",
    )
    p.add_argument(
        "--fill",
        nargs="?",
        type=float,
        const=12.0,
        metavar="MAX_HOLE",
        help="add synthetic points (attribute synthetic = 1) in the enclosed holes of the scan "
        "up to MAX_HOLE rho wide (default 12), so that the level meets --rho there too",
    )
    p.add_argument(
        "-o", "--output", required=True, metavar="OUT", help="output file (.ply, .npy, .csv, ...)"
    )
    p.add_argument(
        "--colour-depth",
        type=int,
        choices=(8, 16),
        default=None,
        help="PLY colour: 8 (uchar, the default: every viewer reads it) or 16 (ushort; "
        "CloudCompare 2.11 shows 16-bit PLY colour as black)",
    )
    from .feature_options import add_slice_options
    from .output import add_json_option

    add_slice_options(p)
    add_filter_options(p)
    add_json_option(p)
    return p


def run(args: argparse.Namespace) -> int:
    from ..archive.reader import open_archive
    from ..io import write_points
    from ..io.api import collect_notes
    from ..io.registry import writer_for
    from .level_options import level_query
    from .output import VERBOSE, check_output, emit, say

    arc_path = Path(args.archive)
    out = check_output(args.output, "-o", inputs={"archive": arc_path})
    writer_for(out)  # unknown output suffix (or .copc.laz): fail before reading anything
    query = level_query(args)  # one check of the level options, before anything is read
    flt = _check_scans(args)
    if getattr(args, "all_scans", False):
        from .collection_options import slice_all

        return slice_all(args)

    t0 = time.perf_counter()
    with open_archive(arc_path) as arc:
        view = arc.scan(args.scan)
        level, filled, note, facts = _read(view, query)
        metadata = view.format_metadata
        say(args, f"read the level in {(time.perf_counter() - t0) * 1e3:.1f} ms", VERBOSE)
    guarantee = None
    if flt is not None:
        before = level.size
        level = flt.apply(level)
        guarantee = flt.guarantee(level.rho)
        note = f"filter {flt.describe()}: {level.size:,} of the level's {before:,} points; {note} before the filter"
    attrs = dict(level.attributes)
    if args.extra:
        attrs.update(source_index=level.source_index, radius=level.radius, rank=level.rank)
    with collect_notes() as changes:
        write_points(out, level, attrs, metadata=metadata, colour_depth=args.colour_depth)
    doc = _document(arc_path, view, out, level, note, facts, attrs, changes)
    if flt is not None:
        doc.update(filter=flt.describe(), level_size=level.region["level_size"], guarantee=guarantee)
    what = f"{level.size:,} of {view.n_points:,} points"
    if filled is not None:
        doc["synthetic"] = filled.n_synthetic
        what = filled.summary(view.n_points)
    emit(
        args,
        doc,
        "\n".join(
            [f"wrote {what} of scan {view.name!r} to {out} ({note})"]
            + ([f"  guarantee: {guarantee}"] if guarantee else [])
            + [f"  changed: {line}" for line in changes]
        ),
    )
    return 0


def _check_scans(args: argparse.Namespace) -> Any:
    """The survey filter of the options (or None), after refusing what --all-scans cannot do."""
    from ..errors import InputError

    if args.fill is not None and getattr(args, "all_scans", False):
        raise InputError("--fill fills one scan's --rho level; leave out --all-scans and --floor-rho")
    flt = filter_from_args(args)
    if flt is not None and getattr(args, "all_scans", False):
        raise InputError("survey filters apply to one scan's level; leave out --all-scans")
    return flt


def _read(view: Any, query: Any) -> tuple[Any, Any, str, dict[str, Any]]:
    """(level, filled level or None, its bound sentence with the level's facts, the facts)."""
    from ..query import read_level
    from .level_facts import facts_text, level_facts

    answer = read_level(view, query)
    plain = query.box is None and query.viewpoint is None and query.fill is None and query.floor_rho is None
    rho_asked = query.rho if plain else None
    facts = level_facts(view, answer.level, rho_asked)
    note = "; ".join([answer.guarantee, *facts_text(facts, rho_asked)])
    return answer.level, answer.filled, note, facts


def _document(arc_path: Path, view: Any, out: Path, level: Any, note: str, facts: dict[str, Any],
              attrs: dict[str, Any], changes: list[str]) -> dict[str, Any]:
    """The --json document of the level written."""
    return {
        "archive": str(arc_path),
        "scan": view.name,
        "output": str(out),
        "size": level.size,
        "n_points": view.n_points,
        "rho": level.rho,
        "ordering": level.ordering or "uniform",
        "bound": note,
        "pieces_reached": facts["pieces_reached"],
        "pieces": facts["pieces"],
        "first_point_only": facts["first_point_only"],
        "region": level.region,
        "attributes": sorted(attrs),
        "crs": level.crs,
        "units": level.units,
        "changes": changes,
    }
