"""The README stays true: every command it shows runs as shown and prints what it shows.

The ``console`` blocks are run in order as one shell script in a fresh directory beside a link to
``../shared/data`` (as the README says: from the repository's root, with the real scans beside it);
each command must exit 0, and every output line the README shows must be among the lines the
command printed, once times are masked (they vary from run to run). The ``python`` block runs as a
doctest in the same directory, its outputs compared exactly.
"""

from __future__ import annotations

import doctest
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.M | re.S)
TIME = re.compile(r"\b\d+(\.\d+)? s\b")
DEMO_ROW = re.compile(r"^(\s+[\d,]+\s+[\d.]+)\s+[\d.]+(\s+demo_out/)")
MARK = "@@README-COMMAND@@"

pytestmark = [pytest.mark.slow, pytest.mark.data]


def blocks(kind: str) -> list[str]:
    return [body for info, body in FENCE.findall(README.read_text()) if info == kind]


def commands() -> list[tuple[str, list[str]]]:
    """(command, the output lines the README shows for it), in README order."""
    out: list[tuple[str, list[str]]] = []
    for body in blocks("console"):
        for line in body.splitlines():
            if line.startswith("$ "):
                out.append((line[2:], []))
            elif out and line.strip() and line.strip() != "...":
                out[-1][1].append(line)
    return out


def normal(line: str) -> str:
    """A line with its times masked."""
    line = DEMO_ROW.sub(r"\1 <ms>\2", line.rstrip())
    return TIME.sub("<t> s", line)


def test_readme_has_commands_and_a_python_example():
    cmds = [c for c, _ in commands()]
    assert len(cmds) >= 20
    assert any(c.startswith("lodbuilder build") for c in cmds)
    assert len(blocks("python")) == 1


@pytest.fixture(scope="module")
def workdir(tmp_path_factory, shared_data):
    root = tmp_path_factory.mktemp("readme")
    (root / "shared").symlink_to(shared_data.parent)
    (root / "lodbuilder").mkdir()
    (root / "lodbuilder" / "tools").symlink_to(README.parent / "tools")  # the README runs tools/ scripts
    return root / "lodbuilder"


def test_every_readme_command_runs_and_prints_what_the_readme_shows(workdir):
    cmds = commands()
    script = ["set -eu", "trap 'kill $(jobs -p) 2>/dev/null || true' EXIT"]
    for i, (cmd, _) in enumerate(cmds):
        script += [f"echo '{MARK} {i}'", cmd]
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
               VTK_DEFAULT_OPENGL_WINDOW="vtkEGLRenderWindow")
    proc = subprocess.run(["bash", "-c", "\n".join(script)], cwd=workdir, env=env,
                          capture_output=True, text=True, timeout=1800)
    printed: dict[int, list[str]] = {}
    current = -1
    for line in proc.stdout.splitlines():
        if line.startswith(MARK):
            current = int(line.split()[1])
            printed[current] = []
        elif current >= 0:
            printed[current].append(normal(line))
    ran = max(printed, default=-1)
    assert proc.returncode == 0, (f"README command failed: {cmds[ran][0]!r}\n"
                                  f"stdout: {proc.stdout[-2000:]}\nstderr: {proc.stderr[-2000:]}")
    assert ran == len(cmds) - 1
    for i, (cmd, shown) in enumerate(cmds):
        for line in shown:
            if line.startswith("[") and "/" in line.split()[0]:
                continue  # per-scan progress lines of a pool come in the order the scans finish
            assert normal(line) in printed[i], (
                f"README shows {line!r} for {cmd!r}; it printed:\n" + "\n".join(printed[i]))


def test_the_readme_python_example(workdir):
    (body,) = blocks("python")
    test = doctest.DocTestParser().get_doctest(body, {}, "README", str(README), 0)
    runner = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE)
    cwd = os.getcwd()
    os.chdir(workdir)
    try:
        result = runner.run(test)
    finally:
        os.chdir(cwd)
    assert result.failed == 0 and result.attempted >= 6
