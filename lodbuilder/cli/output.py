"""What every command shares: quiet/verbose levels, ``--json`` reports, one-line errors and the
one rule for output paths.

A command module uses it like this::

    from .output import add_json_option, check_output, emit

    def add_parser(subparsers):
        p = subparsers.add_parser("thing", ...)
        add_json_option(p)                      # --json: the report as JSON on stdout
        return p

    def run(args):
        out = check_output(args.output, "-o", inputs={"archive": args.archive})
        ...                                     # the work
        emit(args, {"wrote": str(out), "size": k}, f"wrote {k:,} points to {out}")
        return 0

``main`` adds ``-q/--quiet`` and ``-v/--verbose`` to every command (:func:`add_common_options`),
sets up logging from them (:func:`setup_logging`) and prints every error with :func:`error_line`.

Levels: ``-q`` prints errors only (and the JSON report when ``--json`` asks for it); the default
prints the command's result and warnings; ``-v`` adds details and INFO log lines; ``-vv`` DEBUG.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, NoReturn

from .. import _json
from .._json import jsonable  # noqa: F401 - the commands convert with it

QUIET, NORMAL, VERBOSE, DEBUG = -1, 0, 1, 2


# -- options ---------------------------------------------------------------------------------


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, like every other error of the command
    line: ``lodbuilder slice: error: argument --size: invalid int value: 'x' (see 'lodbuilder
    slice --help')``, exit 2 (argparse prints the whole usage first)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see '{self.prog} --help')\n")


_NEGATIVE = re.compile(r"^-\d+$|^-\d*\.\d+$")
#: a digit typed for the letter it looks like (``-0`` for ``-o``)
_LOOKALIKE = {"0": "o", "1": "l", "O": "o", "I": "l"}


def check_options(parser: argparse.ArgumentParser, argv: list[str]) -> None:
    """Before argparse parses ``argv``: an option the command does not have is an error that
    names the closest one (``unknown option --rhoo: did you mean --rho?``), from the command's
    parser, so that it points to the command's help. argparse would otherwise report a missing
    required option first, or the unknown one from the top parser."""
    sub_action = next(
        (a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None
    )
    i = 0
    while i < len(argv) and argv[i].startswith("-"):  # top-level options (no values)
        i += 1
    if sub_action is None or i >= len(argv) or argv[i] not in sub_action.choices:
        return
    sub = sub_action.choices[argv[i]]
    bad = _unknown_option(sub, argv[i + 1:])
    if bad is None:
        return
    name, hint = bad
    sub.error(f"unknown option {name}" + (f": did you mean {hint}?" if hint else ""))


def _unknown_option(p: argparse.ArgumentParser, tokens: list[str]) -> tuple[str, str | None] | None:
    """The first option of ``tokens`` that ``p`` does not know and the closest it knows (option
    values, abbreviations argparse accepts and anything after ``--`` are skipped)."""
    import difflib

    known = p._option_string_actions
    longs = sorted(s for s in known if s.startswith("--"))
    i = 0
    while i < len(tokens):
        t = tokens[i]
        i += 1
        if t == "--":
            return None
        if not t.startswith("-") or t == "-":
            continue
        name = t.split("=", 1)[0]
        if name.startswith("--"):
            hits = [name] if name in known else [s for s in longs if s.startswith(name)]
            action = known[hits[0]] if len(hits) == 1 else None
            if len(hits) > 1:
                return None  # argparse says "ambiguous option"
        elif _NEGATIVE.match(t):
            letter = _LOOKALIKE.get(t[1:])
            if letter is not None and f"-{letter}" in known:
                return t, f"-{letter}"
            continue  # a negative number
        else:
            action = known.get(t[:2])
            name = t[:2] if action is None and len(t) > 2 else name
        if action is None:
            if name.startswith("--"):
                close = difflib.get_close_matches(name, longs, n=1, cutoff=0.6)
            else:
                letter = _LOOKALIKE.get(name[1:], name[1:].lower())
                close = [f"-{letter}"] if f"-{letter}" in known else []
            return name, close[0] if close else None
        if "=" in t or (not t.startswith("--") and len(t) > 2):
            continue  # the value is in the token
        i = _skip_values(action, tokens, i)
    return None


def _skip_values(action: argparse.Action, tokens: list[str], i: int) -> int:
    """Index after the values of ``action`` that follow position ``i``."""
    nargs = action.nargs
    if nargs == 0:
        return i
    if nargs is None:
        return i + 1
    if isinstance(nargs, int):
        return i + nargs
    n = 0
    while i + n < len(tokens) and (
        not tokens[i + n].startswith("-") or _NEGATIVE.match(tokens[i + n])
    ):
        n += 1
        if nargs == "?":
            break
    return i + n


def add_common_options(p: argparse.ArgumentParser) -> None:
    """``-q/--quiet`` and ``-v/--verbose`` (repeatable); ``main`` calls this for every command."""
    g = p.add_argument_group("output levels")
    g.add_argument(
        "-q", "--quiet", action="store_true", help="print nothing but errors (and --json output)"
    )
    g.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="print details and log progress (-vv: debug log)",
    )


def add_json_option(p: argparse.ArgumentParser, *, to_file: bool = False) -> None:
    """``--json``: the command's report as JSON on stdout instead of text.

    With ``to_file`` the option takes a path (``--json OUT``, ``-`` for stdout), for reports
    large enough to keep."""
    if to_file:
        p.add_argument(
            "--json", metavar="OUT", help="write the report as JSON to OUT ('-' for stdout)"
        )
    else:
        p.add_argument(
            "--json", action="store_true", help="print the report as JSON on stdout instead of text"
        )


def verbosity(args: argparse.Namespace) -> int:
    """QUIET (-1), NORMAL (0), VERBOSE (1) or DEBUG (2) from the command's -q/-v options."""
    if getattr(args, "quiet", False):
        return QUIET
    return min(DEBUG, int(getattr(args, "verbose", 0) or 0))


def json_to_stdout(args: argparse.Namespace) -> bool:
    """True when the command's JSON report goes to stdout (then no text may go there)."""
    value = getattr(args, "json", None)
    return value is True or value == "-"


def setup_logging(args: argparse.Namespace) -> int:
    """Level of the ``lodbuilder`` loggers from the verbosity: ERROR when quiet, WARNING, INFO
    (-v), DEBUG (-vv); log lines go to stderr (a handler is added only when none is set up).
    Returns the level the logger had, for the caller to restore."""
    level = {QUIET: logging.ERROR, NORMAL: logging.WARNING, VERBOSE: logging.INFO}.get(
        verbosity(args), logging.DEBUG
    )
    if not logging.getLogger().handlers:
        logging.basicConfig(format="%(levelname)s %(name)s: %(message)s")
    logger = logging.getLogger("lodbuilder")
    before = logger.level
    logger.setLevel(level)
    return before


def progress_enabled(args: argparse.Namespace) -> bool | None:
    """For :class:`~lodbuilder.cli.progressbar.ProgressBars`: off when quiet or --no-progress,
    else None (on when stderr is a terminal)."""
    if verbosity(args) == QUIET or getattr(args, "no_progress", False):
        return False
    return None


# -- printing --------------------------------------------------------------------------------


def say(args: argparse.Namespace, text: str, level: int = NORMAL) -> None:
    """Print a line of the text report on stdout when the verbosity reaches ``level`` and stdout
    is not taken by a JSON report."""
    if verbosity(args) >= level and not json_to_stdout(args):
        print(text)


def emit(args: argparse.Namespace, doc: dict[str, Any], text: str | Callable[[], str]) -> None:
    """Report a command's result: ``doc`` as JSON with ``--json`` (stdout, or the file of
    ``--json OUT``), and ``text`` (a string or a function making it) unless quiet or JSON took
    stdout."""
    out = getattr(args, "json", None)
    if out:
        write_json(doc, "-" if out is True else out)
    if verbosity(args) >= NORMAL and not json_to_stdout(args):
        print(text() if callable(text) else text)


def dumps(doc: Any) -> str:
    return _json.dumps(doc, indent=2)


def write_json(doc: Any, out: str | os.PathLike[str] = "-") -> None:
    """``doc`` as JSON on stdout (``out`` is ``-``) or atomically into the file ``out`` (whose
    directory must exist: check it first with :func:`check_output`)."""
    text = dumps(doc) + "\n"
    if os.fspath(out) == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    from ..io._files import atomic_output

    with atomic_output(out) as tmp:
        tmp.write_text(text, encoding="utf-8")


def one_line(text: str) -> str:
    """``text`` with every control character (newline, carriage return, tab, ...) escaped as in a
    Python literal, so that a message stays on one line whatever names or paths it quotes."""
    if text.isprintable():
        return text
    return "".join(
        c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text
    )


def error_line(command: str | None, exc: BaseException | str) -> str:
    """The one line a failed command prints on stderr: ``lodbuilder CMD: error: MESSAGE``."""
    prefix = f"lodbuilder {command}" if command else "lodbuilder"
    return f"{prefix}: error: {one_line(str(exc))}"


def print_error(command: str | None, exc: BaseException | str) -> None:
    print(error_line(command, exc), file=sys.stderr)


# -- the output-path rule --------------------------------------------------------------------


def check_output(
    path: str | os.PathLike[str],
    option: str,
    *,
    inputs: dict[str, str | os.PathLike[str] | None] | None = None,
    suffixes: Iterable[str] | None = None,
    stdout: bool = False,
) -> Path:
    """The one rule every command applies to a file it will write, before any work:

    * ``-`` is stdout, accepted only where the command can stream (``stdout=True``);
    * the suffix must be one of ``suffixes`` (when given; compared case-insensitively);
    * the file must not be one of the command's ``inputs`` (``{"archive": path, ...}``);
    * its directory must exist and be writable (a missing directory is never created: make it
      first), and the path must not be a directory.

    Raises :class:`~lodbuilder.errors.InputError` or :class:`~lodbuilder.errors.ScanFileError`
    naming ``option``; returns the path."""
    from ..errors import InputError
    from ..io._files import check_output_path

    text = os.fspath(path)
    if text == "-":
        if stdout:
            return Path("-")
        raise InputError(f"{option} - (stdout) is not possible here; give a file name")
    p = Path(text)
    if suffixes is not None:
        allowed = tuple(s.lower() for s in suffixes)
        if not p.name.lower().endswith(allowed):
            raise InputError(f"{option} {p} must end in {' or '.join(allowed)}")
    for what, src in (inputs or {}).items():
        if src is not None and _same_file(p, Path(src)):
            raise InputError(f"{option} {p} is the input {what}; choose another output")
        if src is not None and what == "archive":
            own = archive_file(p, src)
            if own is not None:
                raise InputError(f"{option} {p} is {own} of the archive {src}; choose another output")
    inside = inside_archive_dir(p)
    if inside is not None:
        raise InputError(f"{option} {p} is {inside[1]} of the archive {inside[0]}; choose another output")
    try:
        check_output_path(p)
    except OSError as exc:
        raise type(exc)(f"{option} {exc}") from None
    return p


def inside_archive_dir(path: Path) -> tuple[Path, str] | None:
    """(archive, "in its parts directory" ...) when ``path`` lies in the parts directory of an
    archive (``NAME.h5.scans/`` beside ``NAME.h5``) or in a build work directory
    (``.NAME.h5.parts/``), whatever archive the command reads."""
    from ..archive.layout import PARTS_SUFFIX

    real = Path(os.path.realpath(path))
    for d in real.parents:
        if d.name.endswith(PARTS_SUFFIX) and d.with_name(d.name[: -len(PARTS_SUFFIX)]).is_file():
            return d.with_name(d.name[: -len(PARTS_SUFFIX)]), "in the parts directory"
        if d.name.startswith(".") and d.name.endswith(".parts") and len(d.name) > len("..parts"):
            return d.with_name(d.name[1 : -len(".parts")]), "in the build work directory"
    return None


def archive_file(path: Path, archive: str | os.PathLike[str]) -> str | None:
    """What ``path`` is of the local archive ``archive`` (its parts directory, its build work
    directory, its lock file, or a link to one of their files), or None: a command never writes
    its output there (the archive itself is an input, checked apart)."""
    from ..archive import files as F
    from ..archive.index import is_url
    from ..archive.layout import parts_dir_name

    if is_url(archive):
        return None
    a = Path(os.path.abspath(archive))
    dirs = {"in the parts directory": a.with_name(parts_dir_name(a.name)),
            "in the build work directory": a.with_name(f".{a.name}.parts")}
    real = Path(os.path.realpath(path))
    for what, d in dirs.items():
        rd = Path(os.path.realpath(d))
        if real == rd or rd in real.parents:
            return what
    if real == Path(os.path.realpath(F.lock_name(a))):
        return "the lock file"
    try:
        st = os.stat(path)
    except OSError:
        return None
    for d in dirs.values():
        for root, _, names in os.walk(d):  # never follows links to directories
            for name in names:
                try:
                    other = os.stat(os.path.join(root, name), follow_symlinks=False)
                except OSError:
                    continue
                if (other.st_dev, other.st_ino) == (st.st_dev, st.st_ino):
                    return f"a link to {name}, a file"
    return None


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
        return a.resolve() == b.resolve()
    except OSError:
        return False
