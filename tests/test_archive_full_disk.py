"""A full disk is one line, exit 2, nothing partial, nothing lost (reliability-2 item 3: `build`
crashed with SIGSEGV creating an archive on a 3 MB tmpfs, and gave tracebacks adding to one).

On a real tmpfs when this process may mount one (root), and by simulated ENOSPC everywhere."""

from __future__ import annotations

import errno
import hashlib
import os
import re

import pytest
from clirun import in_child
from conftest import mounted_tmpfs

import lodbuilder
from lodbuilder.archive import files as F
from lodbuilder.archive.validate import validate_archive
from lodbuilder.archive.writer import ScanRecord, update_archive
from lodbuilder.datasets import demo_scan
from lodbuilder.errors import ArchiveError


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def record(n, name, seed=0):
    scan = demo_scan(n, seed=seed, name=name)
    return ScanRecord(scan, lodbuilder.euclidean_fps(scan.points))


def everything(d):
    return sorted(str(p.relative_to(d)) for p in d.rglob("*"))


@pytest.fixture
def tiny_disk(tmp_path):
    """A 3 MB tmpfs (skipped where this process may not mount one)."""
    with mounted_tmpfs(tmp_path / "disk", "the simulated full-disk tests cover the same paths") as d:
        yield d


def cli(*args):
    return in_child(*args)


NO_SPACE = re.compile(
    r"lodbuilder build: error: no space left on the device of (\S+) for scan '(\w+)' \(needs up "
    r"to [\d.]+ [kM]B\); free some space or choose another location; nothing was changed"
)


@pytest.mark.data
def test_build_on_a_full_tmpfs_is_one_line(tiny_disk, shared_data):
    r = cli("build", str(shared_data / "igea.ply"), "-o", str(tiny_disk / "igea.h5"), "--no-progress")
    assert r.returncode == 2, r.stderr  # it was -11 (SIGSEGV)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and NO_SPACE.fullmatch(lines[0]), lines
    assert everything(tiny_disk) == []


def test_adding_on_a_full_tmpfs_keeps_the_archive(tiny_disk):
    path = tiny_disk / "a.h5"
    update_archive(path, [record(2000, "first", 1)])
    update_archive(path, [record(1500, "second", 2)])
    before = {p: sha(tiny_disk / p) for p in everything(tiny_disk) if (tiny_disk / p).is_file()}
    st = os.statvfs(tiny_disk)
    filler = tiny_disk / "filler"
    filler.write_bytes(b"\0" * max(0, st.f_bavail * st.f_frsize - 300_000))
    with pytest.raises(ArchiveError) as err:
        update_archive(path, [record(60_000, "big", 3)])
    assert re.fullmatch(r"no space left on the device of \S+ for scan 'big' \(needs up to [\d.]+ "
                        r"MB\); free some space or choose another location; nothing was changed",
                        str(err.value)), str(err.value)
    filler.unlink()
    after = {p: sha(tiny_disk / p) for p in everything(tiny_disk) if (tiny_disk / p).is_file()}
    assert after == before  # the archive, its parts, nothing else
    assert validate_archive(path) == []
    # and the same through the command line: one line, exit 2
    src = tiny_disk.parent / "big.npy"
    import numpy as np

    np.save(src, demo_scan(60_000, seed=3).points)
    filler.write_bytes(b"\0" * max(0, st.f_bavail * st.f_frsize - 300_000))
    r = cli("build", str(src), "-o", str(path), "--no-progress")
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and NO_SPACE.fullmatch(r.stderr.strip())
    filler.unlink()
    assert {p: sha(tiny_disk / p) for p in everything(tiny_disk) if (tiny_disk / p).is_file()} == before


# ------------------------------------------------------------------------------- simulated


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_reserving_space_starts_no_process(tmp_path, monkeypatch):
    # ctypes.util.find_library("c") ran ldconfig and uname: two forks of the whole build process
    # (about 60 ms of CPU after a 1M-point ordering) for every first reservation
    import subprocess

    def no_process(*a, **k):
        raise AssertionError("a process was started")

    monkeypatch.setattr(F, "_libc", None)
    monkeypatch.setattr(subprocess.Popen, "__init__", no_process)
    path = tmp_path / "f.bin"
    path.write_bytes(b"")
    F.reserve(path, 1 << 16, "a test file")


def test_no_space_for_a_new_archive(tmp_path, monkeypatch):
    monkeypatch.setattr(F, "_fallocate", _enospc)
    with pytest.raises(ArchiveError, match=r"^no space left on the device of .* for scan 'a' \(needs up to [\d.]+ [kM]B\); free some space"):
        update_archive(tmp_path / "a.h5", [record(500, "a")])
    assert everything(tmp_path) == []


def test_no_space_for_the_index_after_the_part(tmp_path, monkeypatch):
    path = tmp_path / "a.h5"
    update_archive(path, [record(500, "a", 1)])
    update_archive(path, [record(400, "b", 2)])
    before = {p: sha(tmp_path / p) for p in everything(tmp_path) if (tmp_path / p).is_file()}
    real = F.reserve

    def reserve(p, nbytes, what):
        if what == "the archive index":
            _enospc()
        return real(p, nbytes, what)

    monkeypatch.setattr(F, "reserve", reserve)
    with pytest.raises(ArchiveError, match=r"^no space left on the device of .* while writing a.h5; free some space or choose another location; nothing was changed$"):
        update_archive(path, [record(300, "c", 3)])
    # the new part, written before the index failed, is gone again; the archive is as it was
    assert {p: sha(tmp_path / p) for p in everything(tmp_path) if (tmp_path / p).is_file()} == before


def test_hdf5_write_failure_is_one_line(tmp_path, monkeypatch):
    """If the disk fills between the reservation and a write (another process), HDF5's error
    becomes one line and the temporary is removed."""
    from lodbuilder.archive import scanwriter

    def write_rows(ds, lo, data):
        raise OSError(errno.ENOSPC, "Can't synchronously write data (file write failed: errno = 28, "
                      "error message = 'No space left on device')")

    monkeypatch.setattr(scanwriter, "_write_rows", write_rows)
    with pytest.raises(ArchiveError, match=r"^no space left on the device of .* while writing a.h5; free some space or choose another location; nothing was changed$"):
        update_archive(tmp_path / "a.h5", [record(500, "a")])
    assert everything(tmp_path) == []
