"""Entry point of the ``lodbuilder`` command.

Each command lives in its own module ``lodbuilder/cli/<name>.py`` that defines
``add_parser(subparsers)`` (returning its parser) and ``run(args) -> int``. Command modules keep
their top-level imports light; heavy libraries are imported inside ``run``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from importlib import import_module

from .. import __version__
from ..errors import LodbuilderError

COMMANDS = ("demo", "build", "slice", "info", "validate", "view", "evaluate", "export")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lodbuilder",
        description="Build multiresolution point-set archives from 3D scans and slice levels from them.",
    )
    parser.add_argument("--version", action="version", version=f"lodbuilder {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        try:
            module = import_module(f"lodbuilder.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"lodbuilder.cli.{name}":
                continue  # command not shipped in this build
            raise
        p = module.add_parser(sub)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args._run(args) or 0)
    except LodbuilderError as exc:
        print(f"lodbuilder {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"lodbuilder {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `lodbuilder info --json A.h5 | head`: the reader went away
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
