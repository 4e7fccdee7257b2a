"""Running the command line in-process, shared by the CLI tests."""

from __future__ import annotations

from lodbuilder.cli.main import main


def run(capsys, *argv):
    """``lodbuilder ARGV`` in this process: (exit code, stdout, stderr)."""
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def one_line_error(capsys, cmd, *argv):
    """Run ``lodbuilder CMD ARGV``, check it failed with exit 2 and one line on stderr only, and
    return the message after ``lodbuilder CMD: error: ``."""
    rc, out, err = run(capsys, cmd, *argv)
    assert rc == 2, (rc, out, err)
    lines = err.splitlines()
    prefix = f"lodbuilder {cmd}: error: "
    assert out == "" and len(lines) == 1 and lines[0].startswith(prefix), err
    return lines[0][len(prefix):]


def in_child(*argv, cwd=None, timeout=600):
    """``python -m lodbuilder.cli.main ARGV`` in a child process with this repository first on
    its path: the CompletedProcess (text output captured)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    return subprocess.run([sys.executable, "-m", "lodbuilder.cli.main", *map(str, argv)],
                          capture_output=True, text=True, timeout=timeout, env=env, cwd=cwd)
