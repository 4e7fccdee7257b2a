"""Shared by the benchmark programs: the stamp every result carries (:func:`stamp`, :func:`finish`,
:func:`measured`) and one section each in docs/benchmarks.md (:func:`write_section`)."""

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


def write_section(path: Path, name: str, text: str) -> None:
    """Put ``text`` between ``<!-- BEGIN name -->`` and ``<!-- END name -->`` in the markdown file
    at ``path`` (replacing that section, or appending it), leaving other sections as they are."""
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    block = f"{begin}\n{text.rstrip()}\n{end}\n"
    old = path.read_text() if path.exists() else "# Benchmarks\n\n"
    if begin in old and end in old:
        head, rest = old.split(begin, 1)
        new = head + block + rest.split(end, 1)[1].lstrip("\n")
    else:
        new = old.rstrip("\n") + "\n\n" + block
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(new)
    os.replace(tmp, path)
