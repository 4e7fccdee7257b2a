"""Shared by the benchmark programs: the stamp every result carries (:func:`stamp`, :func:`finish`,
:func:`measured`), one JSON file per program in docs/bench (:func:`store`, :func:`load_run`) and one
block each in docs/benchmarks.md (:func:`write_section`).

docs/bench/<program>.json (e.g. bench_tiled.json) maps the kind of a run (``"survey"``,
``"quality"``; ``"run"`` where the program has one kind) to that run's JSON as the program printed
it, stamp included. It holds the current run of each kind only; earlier runs are in git history.
Store a run with::

    python tools/bench_tiled.py --survey S.laz --workers 2 > run.json
    python tools/benchdoc.py store docs/bench/bench_tiled.json survey run.json

and render a stored run into the page with the program's ``--from-json
docs/bench/bench_tiled.json:survey --markdown docs/benchmarks.md``."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BENCH_DIR = ROOT / "docs" / "bench"
PAGE = ROOT / "docs" / "benchmarks.md"


def commit() -> str:
    """Short git commit of the checkout the benchmark runs from ("?" outside git)."""
    try:
        out = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
        )
        return out.stdout.strip() or "?"
    except OSError:
        return "?"


def _load() -> str:
    return ", ".join(f"{x:.1f}" for x in os.getloadavg())


def stamp(
    tool: str, argv: Sequence[str] | None, *, inputs: str, synthetic: bool
) -> dict[str, Any]:
    """What every benchmark's JSON starts with: the benchmark (``tool``, e.g. ``"bench_fill"``),
    date, git commit, the command as run (``argv`` as given to ``main``; None: ``sys.argv``),
    load average at the start, core count, whether the inputs are synthetic
    (``inputs_synthetic``: true when any is) and what they are (``inputs``).
    Call :func:`finish` at the end for the load average then."""
    args = list(sys.argv[1:] if argv is None else argv)
    return {
        "benchmark": tool,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "commit": commit(),
        "command": " ".join(["python", f"tools/{tool}.py", *args]),
        "argv": " ".join(args),
        "loadavg": _load(),
        "cpu_count": os.cpu_count(),
        "inputs_synthetic": synthetic,
        "inputs": inputs,
    }


def finish(result: dict[str, Any]) -> dict[str, Any]:
    """Add the load average at the end of the run to ``result`` (returned)."""
    result["loadavg_end"] = _load()
    return result


def publish(
    result: dict[str, Any],
    *,
    section: str | None = None,
    render: Callable[[dict[str, Any]], str] | None = None,
    markdown: str | os.PathLike[str] | None = None,
) -> None:
    """End a run: :func:`finish` ``result``, write ``render(result)`` as the ``section`` of the
    ``markdown`` file when one is given, print ``result`` as JSON on stdout."""
    finish(result)
    if markdown and section and render:
        write_section(Path(markdown), section, render(result))
    print(json.dumps(result, indent=2, default=float))


def machine(**extra: Any) -> dict[str, Any]:
    """Python, platform, CPU, numpy and lodbuilder versions, plus ``extra``."""
    import numpy as np

    import lodbuilder

    info: dict[str, Any] = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "numpy": np.__version__,
        "lodbuilder": lodbuilder.__version__,
    }
    try:
        with open("/proc/cpuinfo") as f:
            info["cpu"] = next(
                (ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), "?"
            )
    except OSError:
        pass
    return {**info, **extra}


_LOAD_KEYS = ("loadavg", "load_average", "load_avg_at_start", "load_average_at_start")


def measured(result: dict[str, Any]) -> str:
    """The markdown sentence of a stamp: when, by which command, at which commit, under which
    load (also for JSON saved before :func:`stamp`, which had no ``command``)."""
    command = result.get("command") or (
        f"python tools/{result.get('benchmark', '?')}.py {result.get('argv', '')}".rstrip()
    )
    load = next((result[k] for k in _LOAD_KEYS if k in result), "?")
    if isinstance(load, list | tuple):
        load = ", ".join(f"{x:.1f}" for x in load)
    commit = result.get("commit") or result.get("git_commit") or "?"
    text = f"Measured {result.get('date', '?')} by `{command}` (commit {commit})"
    text += f"; load average at start {load}"
    if "loadavg_end" in result:
        text += f", at the end {result['loadavg_end']}"
    return text


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def store(path: str | os.PathLike[str], kind: str, run: dict[str, Any]) -> None:
    """Make ``run`` the current run of ``kind`` in the docs/bench file at ``path`` (other kinds
    are kept)."""
    if "benchmark" not in run:
        raise SystemExit("not one run as a benchmark program printed it (no 'benchmark' key)")
    path = Path(path)
    runs = json.loads(path.read_text()) if path.exists() else {}
    if not isinstance(runs, dict) or "benchmark" in runs:
        raise SystemExit(f"{path} is not a file of runs by kind; move it away or give a new path")
    runs[kind] = run
    _write_atomic(path, json.dumps(runs, indent=1, default=float) + "\n")


def load_run(spec: str | os.PathLike[str]) -> Any:
    """The run named by ``spec``: ``FILE`` (a run as a program printed it, or a docs/bench file
    with one kind) or ``FILE:KIND`` (that kind of a docs/bench file)."""
    text, kind = str(spec), None
    if not Path(text).exists() and ":" in text:
        text, kind = text.rsplit(":", 1)
    doc = json.loads(Path(text).read_text())
    if not isinstance(doc, dict) or "benchmark" in doc:
        if kind is not None:
            raise SystemExit(f"{text} holds one run, not runs by kind: give it without ':{kind}'")
        return doc
    if kind is None and len(doc) == 1:
        return next(iter(doc.values()))
    if kind not in doc:
        raise SystemExit(f"give FILE:KIND with KIND one of {', '.join(doc)} (got {kind!r})")
    return doc[kind]


def write_section(path: Path, name: str, text: str) -> None:
    """Put ``text`` between ``<!-- BEGIN name -->`` and ``<!-- END name -->`` in the markdown file
    at ``path`` (replacing that block, or appending it), leaving the rest of the page as it is:
    each section's heading and its text above the block are written by hand."""
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    block = f"{begin}\n{text.rstrip()}\n{end}\n"
    old = path.read_text() if path.exists() else "# Benchmarks\n\n"
    if begin in old and end in old:
        head, rest = old.split(begin, 1)
        tail = rest.split(end, 1)[1].lstrip("\n")
        new = head + block + ("\n" + tail if tail else "")
    else:
        new = old.rstrip("\n") + "\n\n" + block
    _write_atomic(path, new)


def main(argv: Sequence[str] | None = None) -> int:
    """``python tools/benchdoc.py store FILE KIND RUN.json``: see the module's docstring."""
    import argparse

    ap = argparse.ArgumentParser(description="store a benchmark run in its docs/bench file")
    sub = ap.add_subparsers(dest="command", required=True)
    st = sub.add_parser("store", help="make RUN the current run of KIND in FILE")
    st.add_argument("file", type=Path)
    st.add_argument("kind")
    st.add_argument("run", type=Path, help="the JSON the benchmark printed")
    args = ap.parse_args(argv)
    store(args.file, args.kind, json.loads(args.run.read_text()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
