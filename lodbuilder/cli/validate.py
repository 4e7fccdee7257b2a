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
            "listing every fault otherwise."
        ),
    )
    p.add_argument("archive", metavar="ARCHIVE")
    return p


def run(args: argparse.Namespace) -> int:
    from ..archive.reader import open_archive
    from ..archive.validate import validate_archive

    faults = validate_archive(args.archive)
    if faults:
        for fault in faults:
            print(f"lodbuilder validate: {args.archive}: {fault}", file=sys.stderr)
        print(f"{args.archive}: INVALID ({len(faults)} fault(s))")
        return 1
    with open_archive(args.archive) as arc:
        total = sum(r["n_points"] for r in arc.index())
        print(
            f"{args.archive}: valid ({len(arc)} scan(s), {total} points, schema version {arc.schema_version})"
        )
    return 0
