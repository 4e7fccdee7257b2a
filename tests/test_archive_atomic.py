"""kill -9 during an archive update leaves the previous archive intact (and readers never see a
half-written scan)."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive.demo_surface import demo_scan
from lodbuilder.archive.validate import validate_archive
from lodbuilder.archive.writer import ScanRecord, remove_stale_temps, update_archive

CHILD = r"""
import sys, numpy as np
from lodbuilder.io import Scan
from lodbuilder.sampling.ordering import Ordering
from lodbuilder.archive.writer import ScanRecord, update_archive
n = int(sys.argv[2])
rng = np.random.default_rng(1)
pts = rng.random((n, 3))
radius = np.sort(rng.random(n))[::-1].copy(); radius[0] = np.inf
parent = (np.arange(n) * rng.random(n)).astype(np.int64); parent[0] = -1
ordg = Ordering(rng.permutation(n).astype(np.int64), radius, parent, 0.0, 0.0, np.zeros(1, np.int64), n)
rec = ScanRecord(Scan(points=pts, attributes={"i": rng.random(n)}, name="big"), ordg)
print("ready", flush=True)
update_archive(sys.argv[1], [rec])
print("done", flush=True)
"""


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def base_archive(tmp_path):
    scan = demo_scan(1500, seed=5, name="base")
    path = tmp_path / "arch.h5"
    update_archive(path, [ScanRecord(scan, lodbuilder.fastfps(scan.points))])
    return path


def _temps(path):
    return [p for p in path.parent.iterdir() if p.name.startswith(f".{path.name}.tmp-")]


@pytest.mark.parametrize("when", ["early", "temp-appears", "temp-growing"])
def test_sigkill_during_add_leaves_old_archive(base_archive, when):
    path = base_archive
    before = sha(path)
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path), "1500000"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        hit_window = False
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            temps = _temps(path)
            if when == "early":
                time.sleep(0.01)
                hit_window = True  # killed before or right at the start of the write
                break
            if temps and (when == "temp-appears" or temps[0].stat().st_size > 4_000_000):
                hit_window = True
                break
            time.sleep(0.002)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL, "the writer finished before it could be killed"
    assert hit_window
    # the archive under its own name is the old one, byte for byte, and it is valid
    assert sha(path) == before
    assert validate_archive(path) == []
    with lodbuilder.open_archive(path) as arc:
        assert arc.scans == ["base"]
    # nothing else carries the archive's name; a left-over temporary is hidden and is removed by
    # the next writer because its process is gone
    names = [p.name for p in path.parent.iterdir()]
    assert names.count("arch.h5") == 1
    assert all(n in ("arch.h5", ".arch.h5.lock") or n.startswith(".arch.h5.tmp-") for n in names)
    removed = remove_stale_temps(path)
    assert _temps(path) == []
    assert len(removed) == len([n for n in names if n.startswith(".arch.h5.tmp-")])


def test_finished_add_is_complete(base_archive):
    path = base_archive
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), "20000"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert validate_archive(path) == []
    with lodbuilder.open_archive(path) as arc:
        assert arc.scans == ["base", "big"]
        assert arc.scan("big").n_points == 20000
    assert _temps(path) == []


def test_failed_write_leaves_no_temp_and_old_archive(base_archive, monkeypatch):
    from lodbuilder.archive import writer

    path = base_archive
    before = sha(path)

    def boom(root, rec):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(writer, "write_scan", boom)
    scan = demo_scan(100, seed=1, name="x")
    with pytest.raises(RuntimeError, match="disk on fire"):
        update_archive(path, [ScanRecord(scan, lodbuilder.fastfps(scan.points))])
    assert sha(path) == before
    assert _temps(path) == []


def test_open_reader_keeps_a_consistent_view_while_a_scan_is_added(base_archive):
    path = base_archive
    with lodbuilder.open_archive(path) as old:
        before = old.scan("base").level(size=300).points
        other = demo_scan(700, kind="torus", seed=2, name="ring")
        update_archive(path, [ScanRecord(other, lodbuilder.fastfps(other.points))])
        # the open handle still reads the file it opened, complete and unchanged
        assert old.scans == ["base"]
        np.testing.assert_array_equal(old.scan("base").level(size=300).points, before)
    with lodbuilder.open_archive(path) as new:
        assert new.scans == ["base", "ring"]
        np.testing.assert_array_equal(new.scan("base").level(size=300).points, before)
