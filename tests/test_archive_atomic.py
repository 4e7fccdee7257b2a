"""kill -9 at every moment of an archive write leaves the previous archive complete (and readers
never see a half-written scan); the next write collects what the killed one left."""

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
from lodbuilder.archive import layout as L
from lodbuilder.archive.validate import validate_archive
from lodbuilder.archive.writer import (
    ScanRecord,
    remove_stale_temps,
    update_archive,
    write_record,
)
from lodbuilder.datasets import demo_scan

CHILD = r"""
import sys, numpy as np
from lodbuilder.io import Scan
from lodbuilder.sampling.ordering import Ordering
from lodbuilder.archive.writer import ScanRecord, update_archive
n = int(sys.argv[2])
rng = np.random.default_rng(1)
pts = rng.random((n, 3))
if n <= 100_000:  # true radii: validate checks them against the points
    import lodbuilder
    ordg = lodbuilder.euclidean_fps(pts)
else:  # a big write to kill part-way (the archive is never validated): any valid-looking order
    radius = np.sort(rng.random(n))[::-1].copy(); radius[0] = np.inf
    parent = (np.arange(n) * rng.random(n)).astype(np.int64); parent[0] = -1
    ordg = Ordering(rng.permutation(n).astype(np.int64), radius, parent, 0.0, 0.0, np.zeros(1, np.int64), n)
rec = ScanRecord(Scan(points=pts, attributes={"i": rng.random(n)}, name="big"), ordg)
print("ready", flush=True)
update_archive(sys.argv[1], [rec])
print("done", flush=True)
"""

# A child that performs one write and kills itself with SIGKILL at a chosen moment.
MOMENT_CHILD = r"""
import os, signal, sys
from pathlib import Path
import numpy as np
import lodbuilder
from lodbuilder.archive import files as F, writer as W, scanwriter as SW
from lodbuilder.datasets import demo_scan

archive, op, moment = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
pdir = W.parts_dir(archive)

def die():
    os.kill(os.getpid(), signal.SIGKILL)

if moment == "part-write":  # inside the writing of the new part, after its first row group
    orig_flush = SW.ScanWriter._flush_group
    count = [0]
    def flush(self, k):
        orig_flush(self, k)
        count[0] += 1
        if count[0] == 1:
            die()
    SW.ScanWriter._flush_group = flush
elif moment == "moved-out":  # the archive file was linked into the parts directory
    orig_link = W._link_or_copy
    def link(src, dst):
        orig_link(src, dst)
        if Path(src) == archive:
            die()
    W._link_or_copy = link
orig_publish = F.publish
def publish(tmp, path):
    if moment == "index-temp" and Path(path) == archive:
        die()  # the new index is complete in its temporary, not yet renamed
    orig_publish(tmp, path)
    if moment == "part-renamed" and Path(path).parent == pdir:
        die()  # the new part is in place, the index does not list it yet
    if moment == "index-replaced" and Path(path) == archive:
        die()  # the new index is in place, nothing collected yet
F.publish = publish
if moment == "linked":  # register: the part is linked into the directory
    orig_link2 = W._link_or_copy
    def link2(src, dst):
        orig_link2(src, dst)
        if Path(dst).parent == pdir and Path(src) != archive:
            die()
    W._link_or_copy = link2

new = demo_scan(9000, kind="torus", seed=7, name="new")
order = lodbuilder.euclidean_fps(new.points)
rec = W.ScanRecord(new, order)
if op == "add":
    W.update_archive(archive, [rec])
elif op == "overwrite":
    new.name = "one"
    W.update_archive(archive, [rec], overwrite=True)
elif op == "register":
    W.register_parts(archive, [sys.argv[4]])
elif op == "importance":
    W.add_importance(archive, "one", "z", np.arange(3000, dtype=float))
print("finished", flush=True)
"""


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _scan(n, name, seed=5):
    scan = demo_scan(n, seed=seed, name=name)
    return ScanRecord(scan, lodbuilder.euclidean_fps(scan.points))


@pytest.fixture
def base_archive(tmp_path):
    path = tmp_path / "arch.h5"
    update_archive(path, [_scan(1500, "base")])
    return path


def _temps(path):
    dirs = [path.parent, path.parent / (path.name + L.PARTS_SUFFIX)]
    return [p for d in dirs if d.is_dir() for p in d.iterdir() if ".tmp-" in p.name]


def _files(path):
    """Every file of the archive's directory, relative names (the parts directory expanded)."""
    out = []
    for p in sorted(path.parent.rglob("*")):
        if p.is_file():
            out.append(str(p.relative_to(path.parent)))
    return out


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
    # nothing else carries the archive's name; left-overs are hidden temporaries or unlisted parts,
    # removed by the next writer because their process is gone
    names = _files(path)
    assert names.count("arch.h5") == 1
    update_archive(path, [_scan(700, "after", seed=2)])
    assert _temps(path) == []
    with lodbuilder.open_archive(path) as arc:
        assert arc.scans == ["after", "base"]
        listed = {r.part for r in arc.rows}
    assert sorted(_files(path)) == sorted(["arch.h5"] + [f"arch.h5.scans/{p}" for p in listed])
    assert remove_stale_temps(path) == []


def _two_scan_archive(tmp_path):
    path = tmp_path / "two.h5"
    update_archive(path, [_scan(3000, "one", seed=1)])
    update_archive(path, [_scan(2000, "two", seed=2)])
    return path


# (operation, moment, whether the new state is visible after the kill)
MOMENTS = [
    ("add", "moved-out", False),  # first addition: the archive file linked out as a part
    ("add", "part-write", False),
    ("add", "part-renamed", False),
    ("add", "index-temp", False),
    ("add", "index-replaced", True),
    ("overwrite", "part-write", False),
    ("overwrite", "part-renamed", False),
    ("overwrite", "index-replaced", True),
    ("register", "linked", False),
    ("register", "index-replaced", True),
    ("importance", "part-write", False),
    ("importance", "index-replaced", True),
]


@pytest.mark.parametrize("op,moment,visible", MOMENTS)
def test_sigkill_at_every_moment(tmp_path, op, moment, visible):
    if op == "add" and moment == "moved-out":
        path = tmp_path / "one.h5"
        update_archive(path, [_scan(3000, "one", seed=1)])
        old_scans = ["one"]
    else:
        path = _two_scan_archive(tmp_path)
        old_scans = ["one", "two"]
    staged = tmp_path / "staged" / "new.h5"
    if op == "register":
        staged.parent.mkdir()
        new = demo_scan(9000, kind="torus", seed=7, name="new")
        write_record(staged, ScanRecord(new, lodbuilder.euclidean_fps(new.points)))
    with lodbuilder.open_archive(path) as arc:
        old_points = {n: arc.scan(n).points() for n in old_scans}
    before = sha(path)
    proc = subprocess.run(
        [sys.executable, "-c", MOMENT_CHILD, str(path), op, moment, str(staged)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    # the archive is complete and valid: the old one, or (after the index replace) the new one
    assert validate_archive(path) == []
    with lodbuilder.open_archive(path) as arc:
        scans = arc.scans
        for n in old_scans:  # every finished scan is there, its data unchanged
            if not (visible and op == "overwrite" and n == "one"):
                np.testing.assert_array_equal(arc.scan(n).points(), old_points[n])
        if visible and op == "importance":
            assert arc.scan("one").importance_names == ["z"]
    if visible:
        assert sha(path) != before
        expected = old_scans + (["new"] if op in ("add", "register") else [])
        assert scans == sorted(expected)
    else:
        assert sha(path) == before
        assert scans == old_scans
    if op == "register":
        assert staged.is_file()  # the caller's part survives: a re-run registers it, no rebuild
    # the next write collects every left-over; re-running the operation completes it
    if op == "register":
        lodbuilder.archive.writer.register_parts(path, [staged], overwrite=True)
    elif op == "importance":
        lodbuilder.archive.writer.add_importance(path, "one", "z", np.arange(3000, dtype=float))
    else:
        new = demo_scan(9000, kind="torus", seed=7, name="new" if op == "add" else "one")
        update_archive(path, [ScanRecord(new, lodbuilder.euclidean_fps(new.points))], overwrite=True)
    assert _temps(path) == []
    assert validate_archive(path) == []
    with lodbuilder.open_archive(path) as arc:
        listed = {r.part for r in arc.rows}
        assert "" not in listed
    assert sorted(_files(path)) == sorted(["two.h5" if path.name == "two.h5" else "one.h5"]
                                          + [f"{path.name}.scans/{p}" for p in listed]
                                          + (["staged/new.h5"] if op == "register" else []))


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
    from lodbuilder.archive import scanwriter

    path = base_archive
    before = sha(path)
    files = _files(path)

    def boom(self, k):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(scanwriter.ScanWriter, "_flush_group", boom)
    scan = demo_scan(100, seed=1, name="x")
    with pytest.raises(RuntimeError, match="disk on fire"):
        update_archive(path, [ScanRecord(scan, lodbuilder.fastfps(scan.points))])
    assert sha(path) == before
    assert _temps(path) == []
    assert _files(path) == files  # nothing left beside it, not even a parts directory


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


CONCURRENT_CHILD = r"""
import sys
import lodbuilder
from lodbuilder.datasets import demo_scan
from lodbuilder.archive.writer import ScanRecord, update_archive
for j in range(4):
    scan = demo_scan(800 + 100 * j, seed=j, name=f"{sys.argv[2]}{j}")
    update_archive(sys.argv[1], [ScanRecord(scan, lodbuilder.euclidean_fps(scan.points))])
"""


def test_concurrent_writers_keep_every_scan(base_archive):
    """Writers of one archive are serialised by its lock: two processes adding scans at the same
    time both see all of theirs in the end, and leave nothing behind."""
    path = base_archive
    procs = [
        subprocess.Popen([sys.executable, "-c", CONCURRENT_CHILD, str(path), prefix],
                         stderr=subprocess.PIPE, text=True)
        for prefix in ("a", "b")
    ]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    with lodbuilder.open_archive(path) as arc:
        assert arc.scans == ["a0", "a1", "a2", "a3", "b0", "b1", "b2", "b3", "base"]
        listed = {r.part for r in arc.rows}
    assert validate_archive(path) == []
    assert sorted(_files(path)) == sorted(["arch.h5"] + [f"arch.h5.scans/{p}" for p in listed])
