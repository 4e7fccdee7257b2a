"""Entry point of the ``lodbuilder`` command.

Each command lives in its own module ``lodbuilder/cli/<name>.py`` that defines
``add_parser(subparsers)`` (returning its parser) and ``run(args) -> int``; to add a command, add
its name to ``COMMANDS``. Command modules keep their top-level imports light; heavy libraries are
imported inside ``run``. Every command gets ``-q/--quiet`` and ``-v/--verbose`` here; what they
share (``--json``, printing, the output-path rule) is in :mod:`lodbuilder.cli.output`.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from importlib import import_module
from typing import Any

from .. import __version__
from ..errors import LodbuilderError
from .output import Parser, add_common_options, check_options, print_error, setup_logging

COMMANDS = ("demo", "build", "slice", "info", "validate", "view", "evaluate", "export")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="lodbuilder",
        description="Build multiresolution point-set archives from 3D scans and slice levels from them.",
    )
    parser.add_argument("--version", action="version", version=f"lodbuilder {__version__}")
    # `lodbuilder -v CMD` as well as `lodbuilder CMD -v`: the two counts add up
    parser.add_argument("-v", "--verbose", dest="top_verbose", action="count", default=0,
                        help="print details and log progress (also after the command)")
    parser.add_argument("-q", "--quiet", dest="top_quiet", action="store_true",
                        help="print nothing but errors (also after the command)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        try:
            module = import_module(f"lodbuilder.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"lodbuilder.cli.{name}":
                continue  # command not shipped in this build
            raise
        p = module.add_parser(sub)
        add_common_options(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command of ``argv`` (default: the process's command line, as the ``lodbuilder``
    command does; the process then ends, see :func:`_before_exit`); returns the exit status."""
    command_line = argv is None
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    check_options(parser, argv)
    args, extras = parser.parse_known_args(argv)
    if extras:  # (from the command's parser, so that the message points to its help)
        command_parser(parser, args.command).error(f"unrecognized arguments: {' '.join(extras)}")
    args.verbose += args.top_verbose
    args.quiet = args.quiet or args.top_quiet
    log_level = setup_logging(args)
    try:
        with _remote_settings(args):
            return int(args._run(args) or 0)
    except LodbuilderError as exc:
        print_error(args.command, exc)
        return 2
    except ImportError as exc:  # an optional dependency missing deep inside a command
        from .._optional import extra_for, missing_message

        if extra_for(exc.name) is None:
            raise  # not an optional dependency: a bug, shown with its traceback
        print_error(args.command, missing_message(exc.name or "", f"lodbuilder {args.command}"))
        return 2
    except OSError as exc:  # a full disk where no writer of ours said so: still one line
        import errno

        if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        print_error(args.command, f"{where}no space left on the device; free some space or choose "
                    "another location")
        return 2
    except KeyboardInterrupt:
        print(f"lodbuilder {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `lodbuilder info --json A.h5 | head`: the reader went away
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    finally:  # main may be called from Python: leave the library's logging as it was
        import logging

        logging.getLogger("lodbuilder").setLevel(log_level)
        if command_line:
            _before_exit()


def _before_exit() -> None:
    """The command is done and the process ends next: every object goes to the garbage
    collector's permanent generation, so that the interpreter's shutdown does not walk them all
    once more (numba's compiler objects and the like: about 0.3 s of CPU after a build, 3 % of a
    million-point build). Nothing is left unfinished by it: files are closed and renamed by then,
    and the shutdown still runs the exit handlers and closes the modules."""
    import gc

    gc.freeze()


def command_parser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    """The parser of ``command`` (a subcommand of ``parser``)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices[command]
    return parser


def _remote_settings(args: argparse.Namespace) -> Any:
    """--timeout / --follow-redirects of a command that reads archives, for every URL it opens."""
    timeout, follow = getattr(args, "timeout", None), getattr(args, "follow_redirects", None)
    if timeout is None and not follow:
        return contextlib.nullcontext()
    from ..archive.remote import settings

    return settings(timeout=timeout, follow_redirects=follow)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
