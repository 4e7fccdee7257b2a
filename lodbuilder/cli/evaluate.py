"""``lodbuilder evaluate``: measure how well an archive's levels approximate the scan."""

from __future__ import annotations

import argparse
import sys

from ..errors import InputError
from .level_options import add_level_options, add_ordering_option


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "evaluate",
        help="quality of an archive's levels: covering radius vs rho, Hausdorff, Chamfer, ...",
        description=(
            "For each level: the covering radius (largest distance from a scan point to the level) "
            "and whether it meets the level's rho, the two-sided Hausdorff and Chamfer distances, "
            "the minimum spacing and uniformity (spacing / covering radius), and the distance of "
            "the scan points to the level's local surface (plane or MLS). Distances are Euclidean, "
            "in the unit of the scan's CRS (shown; 'scan units' when it is unknown)."
        ),
    )
    add_level_options(p, required=False, many=True, what="one level per value: ")
    add_ordering_option(p, "an extra ordering stored with the scan (default: uniform)")
    p.add_argument(
        "--surface", choices=("plane", "mls"), default="plane", help="local surface (default plane)"
    )
    p.add_argument("--k", type=int, help="neighbours per surface fit (default 8 plane, 16 mls)")
    p.add_argument("--plot", metavar="OUT.png", help="plot error vs size and radius vs rank")
    p.add_argument(
        "--gaps",
        nargs="?",
        type=float,
        const=12.0,
        metavar="MAX_HOLE",
        help="also list the gaps at each --rhos value: enclosed regions of the surface farther "
        "than rho from every input point, up to MAX_HOLE rho wide (default 12), with their area "
        "and bounding box (they are what 'slice --fill' fills)",
    )
    from .output import add_json_option

    add_json_option(p, to_file=True)
    return p


def _table(ev) -> str:
    from .level_facts import piece_counts

    uniform = ev.ordering in (None, "uniform")
    counts = {r.size: piece_counts(ev.build, r.size) for r in ev.reports} if uniform else {}
    known = any(c is not None and c[1] > 1 for c in counts.values())
    head = (
        f"{'size':>9} {'rho':>10} {'cover':>10} {'ok':>3} {'hausdorff':>10} {'chamfer':>10} "
        f"{'min sp.':>10} {'unif.':>6} {'surf rms':>10} {'surf max':>10}" + (f" {'pieces':>13}" if known else "")
    )
    unit = ev.units or "scan units (unit unknown)"
    lines = [
        f"scan {ev.scan!r}: {ev.n_points:,} points, ordering {ev.ordering}; distances in {unit}",
        head,
    ]

    def f(v):
        return "-" if v is None else f"{v:10.4g}"

    for r in ev.reports:
        ok = {True: "yes", False: "NO", None: "-"}[r.meets_rho]
        lines.append(
            f"{r.size:>9,} {f(r.rho)} {f(r.covering_radius)} {ok:>3} {f(r.hausdorff)} "
            f"{f(r.chamfer)} {f(r.min_spacing)} {r.uniformity:6.3f} "
            f"{f(r.surface_error['rms'])} {f(r.surface_error['max'])}" + (_pieces(counts.get(r.size)) if known else "")
        )
    lines += _first_point_notes(ev)
    return "\n".join(lines)


def _pieces(c) -> str:
    if c is None:
        return f" {'-':>13}"
    return f" {('>=' if not c[2] else '') + f'{c[0]:,}/{c[1]:,}':>13}"


def _first_point_notes(ev) -> list[str]:
    """A note for each level asked by a rho at or above the scan's largest finite radius."""
    import numpy as np

    radius = np.asarray(ev.radius)
    finite = radius[np.isfinite(radius)]
    if ev.ordering not in (None, "uniform") or not finite.size:
        return []
    top = float(finite[0])
    out = []
    for r in ev.reports:
        if r.label.startswith("rho=") and float(r.label[4:]) >= top > 0:
            out.append(f"level {r.label}: rho is at least the scan's largest finite radius {top:.4g}: the level "
                       "is the first point only; ask for a smaller rho for more")
    return out


def run(args: argparse.Namespace) -> int:
    from .output import check_output, emit, progress_enabled, say

    inputs = {"archive": args.archive}
    if args.json:
        check_output(args.json, "--json", inputs=inputs, stdout=True)
    if args.plot:
        check_output(args.plot, "--plot", inputs=inputs, suffixes=(".png",))
    if args.k is not None and args.k < 3:
        raise InputError(f"--k must be at least 3, got {args.k}")
    if args.gaps is not None and not args.rhos:
        raise InputError("--gaps needs --rhos R [R ...] (the densities whose gaps are listed)")
    if args.plot:
        from .._optional import require

        require("matplotlib", "evaluate --plot")
    from ..quality.archive import evaluate_archive
    from .progressbar import ProgressBars

    with ProgressBars(enabled=progress_enabled(args)) as bars:
        ev = evaluate_archive(
            args.archive,
            args.scan,
            sizes=args.sizes,
            rhos=args.rhos,
            fractions=args.fractions,
            ordering=args.ordering,
            surface=args.surface,
            k=args.k,
            progress=bars,
        )
    doc, gaps = ev.as_dict(), []
    if args.gaps is not None:
        from ..fill import archive_gaps

        gaps = archive_gaps(args.archive, args.scan, args.rhos, max_hole=args.gaps)
        doc["gaps"] = [g.as_dict() for g in gaps]
    emit(args, doc, lambda: "\n".join([_table(ev)] + [g.table() for g in gaps]))
    if args.plot:
        from ..quality.plots import plot_quality

        plot_quality(
            ev.reports, args.plot, radius=ev.radius, title=f"{ev.scan} ({ev.ordering})", units=ev.units
        )
        say(args, f"wrote {args.plot}")
    bad = [r for r in ev.reports if r.meets_rho is False]
    if bad:
        print(
            f"lodbuilder evaluate: {len(bad)} level(s) violate their rho "
            f"(sizes {', '.join(str(r.size) for r in bad)})",
            file=sys.stderr,
        )
        return 1
    return 0
