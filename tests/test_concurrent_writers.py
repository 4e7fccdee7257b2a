"""Several writers of one archive at once (real processes): every build either waits for the archive
or fails at once with one clear line; none removes another's files; no scan is lost.

Each race starts its builds together, so that they plan, clean and write the archive's hidden
work directory at the same moments (finding 1 of reliability-3: one build of two failed in every
round, and a small build removed a tiled build's work directory)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive import files as F
from lodbuilder.archive.validate import validate_archive
from lodbuilder.io import write_points

CLI = [sys.executable, "-c", "import sys; from lodbuilder.cli.main import main; sys.exit(main())"]

# a build started by the test; it waits for the file GO before it begins, so that every writer of
# a race starts at the same moment (their interpreters are already up)
RACER = textwrap.dedent("""
    import os, sys, time, json
    go = sys.argv[1]
    while not os.path.exists(go):
        time.sleep(0.002)
    from lodbuilder.cli.main import main
    sys.exit(main(json.loads(sys.argv[2])))
""")


# a build that stops at a chosen moment until the file GATE exists (it touches READY when it stops)
HOOKED = textwrap.dedent("""
    import json, os, sys, time
    from pathlib import Path

    def pause():
        Path(sys.argv[3]).touch()
        while not os.path.exists(sys.argv[2]):
            time.sleep(0.005)

    def hook(name):
        import lodbuilder.build.runner as R
        if name == "part":  # the scan's part is written in the work directory, not yet merged
            merge = R.merge_parts
            def merge_parts(*a, **k):
                pause()
                return merge(*a, **k)
            R.merge_parts = merge_parts
        elif name == "tiles":  # a tiled build has its work directory, about to order its tiles
            import lodbuilder.build.tiled.driver as D
            from lodbuilder.build.options import BuildOptions
            order = D._order_passes
            def order_passes(*a, **k):
                pause()
                return order(*a, **k)
            D._order_passes = order_passes
            make = BuildOptions.make.__func__
            def tiled(cls, **kw):
                return make(cls, **{**kw, "tile_points": 6000})  # tiles of 6,000 points
            BuildOptions.make = classmethod(tiled)

    if __name__ == "__main__":
        hook(sys.argv[1])
        from lodbuilder.cli.main import main
        sys.exit(main(json.loads(sys.argv[4])))
""")


def _hooked(tmp_path, hook, command):
    """Start a build that stops at ``hook``; returns (process, gate, ready)."""
    import json

    script = tmp_path / "hooked.py"
    script.write_text(HOOKED)
    gate, ready = tmp_path / f"gate-{hook}", tmp_path / f"ready-{hook}"
    proc = subprocess.Popen([sys.executable, str(script), hook, str(gate), str(ready), json.dumps(command)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not ready.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.time() < deadline
        time.sleep(0.01)
    return proc, gate


def _cli(command, timeout=120):
    return subprocess.run([*CLI, *command], capture_output=True, text=True, timeout=timeout)


def _cloud(n, seed):
    rng = np.random.default_rng(seed)
    uv = rng.random((n, 2))
    return np.c_[uv, 0.1 * np.sin(6 * uv[:, 0])]


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    d = tmp_path_factory.mktemp("scans")
    return [write_points(d / f"s{i}.npy", _cloud(1500, i)) for i in range(4)]


def _race(tmp_path, commands):
    """Run every command (CLI argument lists) at the same moment; return [(rc, stderr)]."""
    go = tmp_path / f"go-{time.monotonic_ns()}"
    script = tmp_path / "racer.py"
    script.write_text(RACER)
    import json

    procs = [subprocess.Popen([sys.executable, str(script), str(go), json.dumps(c)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True) for c in commands]
    time.sleep(1.0)  # the interpreters start and wait
    go.touch()
    out = []
    for p in procs:
        _, err = p.communicate(timeout=240)
        out.append((p.returncode, err))
    return out


def _parts(archive):
    return archive.with_name(f".{archive.name}.parts")


def test_writers_of_different_scans_all_land(tmp_path, scans):
    archive = tmp_path / "d.h5"
    res = _race(tmp_path, [["build", str(s), "-o", str(archive), "--no-progress"] for s in scans[:4]])
    assert [rc for rc, _ in res] == [0, 0, 0, 0], res
    with lodbuilder.open_archive(archive) as arc:
        assert arc.scans == ["s0", "s1", "s2", "s3"]
    assert validate_archive(archive) == []
    assert not _parts(archive).exists()
    assert not F.lock_name(archive).exists()


def test_two_builds_of_one_scan_both_succeed(tmp_path, scans):
    archive = tmp_path / "d.h5"
    res = _race(tmp_path, [["build", str(scans[0]), "-o", str(archive), "--no-progress"]] * 2)
    assert [rc for rc, _ in res] == [0, 0], res
    with lodbuilder.open_archive(archive) as arc:
        assert arc.scans == ["s0"]
    assert not _parts(archive).exists()


def test_a_build_waits_for_the_build_that_holds_the_archive(tmp_path, scans):
    """A stopped between writing its part and merging it; B (another scan) waits for A, says so,
    and both scans land (before: B deleted A's part or its directory, and one of them failed)."""
    archive = tmp_path / "d.h5"
    a, gate = _hooked(tmp_path, "part", ["build", str(scans[0]), "-o", str(archive), "--no-progress"])
    b = subprocess.Popen([*CLI, "build", str(scans[1]), "-o", str(archive), "--no-progress"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(2.0)
    assert b.poll() is None  # B waits
    gate.touch()
    _, err_a = a.communicate(timeout=120)
    _, err_b = b.communicate(timeout=120)
    assert (a.returncode, b.returncode) == (0, 0), (err_a, err_b)
    assert f"archive {archive} is being written by another process (pid {a.pid}, a build); waiting for it" \
        in err_b
    with lodbuilder.open_archive(archive) as arc:
        assert arc.scans == ["s0", "s1"]
    assert not _parts(archive).exists()


def test_a_small_build_during_a_tiled_build(tmp_path, scans):
    big = write_points(tmp_path / "big.npy", _cloud(20_000, 9))
    archive = tmp_path / "d.h5"
    script = ["build", str(big), "-o", str(archive), "--no-progress", "--workers", "1"]
    a, gate = _hooked(tmp_path, "tiles", script)
    b = subprocess.Popen([*CLI, "build", str(scans[2]), "-o", str(archive), "--no-progress"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(2.0)
    gate.touch()
    _, err_a = a.communicate(timeout=180)
    _, err_b = b.communicate(timeout=180)
    assert (a.returncode, b.returncode) == (0, 0), (err_a, err_b)
    with lodbuilder.open_archive(archive) as arc:
        assert arc.scans == ["big", "s2"]
        assert arc.scan("big").build["method"] == "tiled"


def test_wait_bounds_the_wait(tmp_path, scans):
    archive = tmp_path / "d.h5"
    a, gate = _hooked(tmp_path, "part", ["build", str(scans[0]), "-o", str(archive), "--no-progress"])
    try:
        now = _cli(["build", str(scans[1]), "-o", str(archive), "--no-progress", "--wait", "0"])
        t0 = time.monotonic()
        later = _cli(["build", str(scans[1]), "-o", str(archive), "--no-progress", "--wait", "0.5"])
        waited = time.monotonic() - t0
    finally:
        gate.touch()
        a.communicate(timeout=120)
    held = f"archive {archive} is being written by another process (pid {a.pid}, a build)"
    assert (now.returncode, now.stderr) == (2, f"lodbuilder build: error: {held}; run again when it has finished, "
                                               "or pass --wait SECONDS to wait for it\n")
    assert later.returncode == 2 and waited >= 0.5
    assert later.stderr.endswith(f"lodbuilder build: error: {held} and did not finish within --wait 0.5 s; run "
                                 "again later or wait longer\n")
    assert a.returncode == 0
    with lodbuilder.open_archive(archive) as arc:
        assert arc.scans == ["s0"]
