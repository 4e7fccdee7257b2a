"""A build uses and cleans only the directories it made beside an archive: a work directory (or a
tiled build's work directory, or a lock file) that is a symbolic link, a mount point or was not
made by lodbuilder is refused with one line, never followed or emptied; a build that fails early
leaves nothing behind."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive.files import MARKER, make_own_dir
from lodbuilder.errors import ArchiveError
from lodbuilder.io import write_points

DATA = Path("/work/shared/data")


def _scan(tmp_path, name, n=1200, seed=0):
    rng = np.random.default_rng(seed)
    uv = rng.random((n, 2))
    return write_points(tmp_path / f"{name}.npy", np.c_[uv, 0.1 * np.sin(6 * uv[:, 0])])


def _foreign(tmp_path):
    """A folder of the user's: a file and a folder named like lodbuilder's own."""
    f = tmp_path / "F"
    (f / "keep.work").mkdir(parents=True)
    (f / "keep.work" / "x").write_text("x")
    (f / "precious.h5").write_text("x")
    (f / "old-0123456789abcdef.h5").write_text("x")
    return f


def _untouched(f):
    return sorted(str(p.relative_to(f)) for p in f.rglob("*")) == [
        "keep.work", "keep.work/x", "old-0123456789abcdef.h5", "precious.h5"]


def _refused(path, why):
    return (f"{path} {why}; lodbuilder uses and cleans only the files and directories it made beside an "
            "archive: move it away (or delete it yourself) and run again")


def test_a_symlinked_work_directory_is_refused_not_emptied(tmp_path):
    """Finding 4: `ln -s F .x.h5.parts` then a build deleted F/precious.h5 and F/keep.work/."""
    archive = tmp_path / "x.h5"
    lodbuilder.build_archive(_scan(tmp_path, "a"), archive)
    f = _foreign(tmp_path)
    parts = tmp_path / ".x.h5.parts"
    parts.symlink_to(f)
    with pytest.raises(ArchiveError) as e:
        lodbuilder.build_archive(_scan(tmp_path, "b", seed=1), archive)
    assert str(e.value) == _refused(parts, "is a symbolic link")
    assert _untouched(f) and parts.is_symlink()
    with lodbuilder.open_archive(archive) as arc:
        assert arc.scans == ["a"]


def test_a_work_directory_lodbuilder_did_not_make_is_refused(tmp_path):
    archive = tmp_path / "x.h5"
    parts = tmp_path / ".x.h5.parts"
    f = _foreign(tmp_path)
    f.rename(parts)
    with pytest.raises(ArchiveError) as e:
        lodbuilder.build_archive(_scan(tmp_path, "a"), archive)
    assert str(e.value) == _refused(parts, f"was not made by lodbuilder for x.h5 (it has no {MARKER} file naming it)")
    assert _untouched(parts) and not archive.exists()
    # a marker naming another archive is not ours either
    (parts / MARKER).write_text("lodbuilder work directory of y.h5\n")
    with pytest.raises(ArchiveError, match="was not made by lodbuilder for x.h5"):
        lodbuilder.build_archive(_scan(tmp_path, "a"), archive)


def test_a_mount_point_is_refused(tmp_path, monkeypatch):
    archive = tmp_path / "x.h5"
    parts = make_own_dir(tmp_path / ".x.h5.parts", "x.h5")
    (parts / "s.0123.h5").write_text("x")
    real = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: os.fspath(p) == str(parts) or real(p))
    with pytest.raises(ArchiveError) as e:
        lodbuilder.build_archive(_scan(tmp_path, "a"), archive)
    assert str(e.value) == _refused(parts, "is a mount point")
    assert (parts / "s.0123.h5").exists()


def test_a_symlinked_tiled_work_directory_is_refused(tmp_path):
    archive = tmp_path / "x.h5"
    parts = make_own_dir(tmp_path / ".x.h5.parts", "x.h5")
    f = _foreign(tmp_path)
    work = parts / "old.0123456789abcdef0123.work"  # the work of a killed tiled build, as a link
    work.symlink_to(f)
    with pytest.raises(ArchiveError) as e:
        lodbuilder.build_archive(_scan(tmp_path, "a"), archive)
    assert str(e.value) == _refused(work, "is a symbolic link")
    assert _untouched(f)
    # a plain directory without the marker is not emptied either
    work.unlink()
    f.rename(work)
    with pytest.raises(ArchiveError, match="was not made by lodbuilder"):
        lodbuilder.build_archive(_scan(tmp_path, "a"), archive)
    assert _untouched(work)


def test_a_symlinked_lock_file_is_refused(tmp_path):
    archive = tmp_path / "x.h5"
    precious = tmp_path / "precious.txt"
    precious.write_text("keep me")
    lock = tmp_path / ".x.h5.lock"
    lock.symlink_to(precious)
    with pytest.raises(ArchiveError) as e:
        lodbuilder.build_archive(_scan(tmp_path, "a"), archive)
    assert str(e.value) == _refused(lock, "is a symbolic link")
    lock.unlink()
    os.link(precious, lock)  # a hard link to the user's file: never written
    with pytest.raises(ArchiveError) as e:
        lodbuilder.build_archive(_scan(tmp_path, "a"), archive)
    assert str(e.value) == _refused(lock, "is not a plain file of its own (a hard link or a special file)")
    assert precious.read_text() == "keep me"


def test_a_symlinked_scans_directory_is_refused(tmp_path):
    """The parts directory of a grown archive (NAME.h5.scans) as a link: nothing in its target is
    deleted (before: files named like parts were collected from it)."""
    archive = tmp_path / "x.h5"
    lodbuilder.build_archive(_scan(tmp_path, "a"), archive)
    f = _foreign(tmp_path)
    scans = tmp_path / "x.h5.scans"
    scans.symlink_to(f)
    with pytest.raises(ArchiveError) as e:
        lodbuilder.build_archive(_scan(tmp_path, "b", seed=1), archive)
    assert str(e.value) == _refused(scans, "is a symbolic link")
    assert _untouched(f)
    with lodbuilder.open_archive(archive) as arc:
        assert arc.scans == ["a"]


def test_our_own_work_directory_is_removed_when_done(tmp_path):
    archive = tmp_path / "x.h5"
    lodbuilder.build_archive([_scan(tmp_path, "a"), _scan(tmp_path, "b", seed=1)], archive, workers=1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy", "b.npy", "x.h5", "x.h5.scans"]


def test_a_build_that_fails_early_leaves_no_work_directory(tmp_path):
    """Finding 11: a bad --scheduler address left an empty .NAME.h5.parts."""
    archive = tmp_path / "x.h5"
    src = _scan(tmp_path, "a")
    with pytest.raises(Exception):  # noqa: B017 - the message itself is another item's
        lodbuilder.build_archive(src, archive, scheduler="bogus://x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy"]
