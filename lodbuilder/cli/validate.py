"""``lodbuilder validate ARCHIVE``: check schema, checksums and ordering invariants."""

from __future__ import annotations

import argparse
import sys


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "validate",
        help="check an archive (schema, checksums, invariants)",
        description=(
            "Check ARCHIVE against the JSON Schema, read every dataset (verifying its fletcher32 "
            "checksums) and check the invariants: stored points are a permutation of the input, "
            "radii never increase, parents come before their children. Exit 0 when valid, 1 "
            "listing every fault otherwise (on stderr, or in the --json report)."
        ),
    )
    p.add_argument("archive", metavar="ARCHIVE")
    from .level_options import add_remote_options

    add_remote_options(p)
    from .output import add_json_option

    add_json_option(p)
    return p


def run(args: argparse.Namespace) -> int:
    from ..archive.reader import open_archive
    from ..archive.validate import validate_archive
    from .output import emit, one_line

    faults = validate_archive(args.archive)
    doc: dict = {"archive": str(args.archive), "valid": not faults, "faults": faults}
    if faults:
        if not args.json:
            for fault in faults:
                print(one_line(f"lodbuilder validate: {args.archive}: {fault}"), file=sys.stderr)
        emit(args, doc, one_line(f"{args.archive}: INVALID ({len(faults)} fault(s))"))
        return 1
    with open_archive(args.archive) as arc:
        total = sum(r["n_points"] for r in arc.index())
        doc.update(scans=len(arc), points=total, schema_version=arc.schema_version)
    emit(
        args,
        doc,
        one_line(
            f"{args.archive}: valid ({doc['scans']} scan(s), {total:,} points, schema version "
            f"{doc['schema_version']})"
        ),
    )
    return 0
