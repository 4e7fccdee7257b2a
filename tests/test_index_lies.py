"""An index or a part that lies is caught (findings 6, 7 and 15 of reliability-3): duplicate scan
names, names that are not scan names (used as HDF5 paths), parts whose content is not what the
index says; no write deletes a part it cannot see, and no command writes its output over a file
of the archive, of its parts or of its work directory."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import h5py
import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive.index import write_index
from lodbuilder.archive.validate import validate_archive
from lodbuilder.archive.writer import ScanRecord, update_archive
from lodbuilder.datasets import demo_scan
from lodbuilder.errors import CorruptArchiveError

CLI = [sys.executable, "-c", "import sys; from lodbuilder.cli.main import main; sys.exit(main())"]


def record(n, name, seed=0):
    scan = demo_scan(n, kind="wavy", seed=seed, name=name)
    return ScanRecord(scan, lodbuilder.euclidean_fps(scan.points))


def _parted(tmp_path):
    path = tmp_path / "a.h5"
    update_archive(path, [record(600, "one", 1)])
    update_archive(path, [record(500, "two", 2)])
    with lodbuilder.open_archive(path) as arc:
        rows = arc.rows
    return path, rows


def _rewrite(path, rows):
    with h5py.File(path, "r+") as f:
        write_index(f, rows)


def _parts(path):
    return sorted(p.name for p in path.with_name(path.name + ".scans").iterdir())


def test_a_scan_name_listed_twice_is_refused_and_no_part_is_deleted(tmp_path):
    """Finding 6: the reader kept one of two rows of the same name, validate said valid, and the
    next build deleted the other row's part (it could not see it)."""
    path, (one, two) = _parted(tmp_path)
    _rewrite(path, [one, replace(two, name="one")])
    before = _parts(path)
    msg = (f"archive {path}: its index lists scan 'one' twice (parts {one.part} and {two.part}); the index is "
           "damaged or crafted: restore the archive from a copy or rebuild it")
    with pytest.raises(CorruptArchiveError) as e:
        validate_archive(path)
    assert str(e.value) == msg
    with pytest.raises(CorruptArchiveError) as e:
        update_archive(path, [record(300, "three", 3)])
    assert str(e.value) == msg
    with pytest.raises(CorruptArchiveError):
        lodbuilder.build_archive(demo_scan(300, seed=4, name="four"), path)
    assert _parts(path) == before
    r = subprocess.run([*CLI, "validate", str(path)], capture_output=True, text=True)
    assert (r.returncode, r.stderr) == (2, f"lodbuilder validate: error: {msg}\n")


@pytest.mark.parametrize("name", ["one/x", "../two", ".hidden", ""])
def test_an_index_name_that_is_no_scan_name_is_refused(tmp_path, name):
    """Finding 15: an index name with '/' was used as an HDF5 path into the part."""
    path, (one, two) = _parted(tmp_path)
    _rewrite(path, [one, replace(two, name=name)])
    with pytest.raises(CorruptArchiveError) as e:
        lodbuilder.open_archive(path)
    assert str(e.value) == (f"archive {path}: its index lists a scan named {name!r}, which is not a scan name "
                            "(at most 255 bytes, no '/', '\\' or NUL, not starting with '.'); the index is damaged "
                            "or crafted: restore the archive from a copy or rebuild it")


def test_an_index_row_whose_bounds_lie_is_a_fault(tmp_path):
    path, (one, two) = _parted(tmp_path)
    _rewrite(path, [one, replace(two, bounds_max=tuple(b + 1.0 for b in two.bounds_max))])
    faults = validate_archive(path)
    assert len(faults) == 1
    assert faults[0].startswith("index: scan 'two' has bounds ")
    assert faults[0].endswith("the scan's points span [" + ", ".join(f"{x:.6g}" for x in two.bounds_min) + "] .. ["
                              + ", ".join(f"{x:.6g}" for x in two.bounds_max) + "]")


def test_a_part_holding_another_scan_too_is_a_fault(tmp_path):
    path, (one, two) = _parted(tmp_path)
    pdir = path.with_name("a.h5.scans")
    with h5py.File(pdir / one.part, "r") as src, h5py.File(pdir / two.part, "r+") as dst:
        src.copy(src["scans/one"], dst["scans"], "one")
    _rewrite(path, [one, replace(two, part_bytes=(pdir / two.part).stat().st_size)])
    faults = validate_archive(path)
    assert f"part {two.part} of scan 'two' holds scans ['one', 'two']; a part holds its one scan only" in faults


@pytest.fixture
def grown(tmp_path):
    path, rows = _parted(tmp_path)
    return path, path.with_name("a.h5.scans") / rows[1].part


def _refused(r, option, out, what, path):
    assert r.returncode == 2, r.stderr
    cmd = r.args[3]
    assert r.stderr == f"lodbuilder {cmd}: error: {option} {out} is {what} of the archive {path}; choose another output\n"


def test_evaluate_json_cannot_overwrite_a_part(grown):
    """Finding 7: `evaluate --json z.h5.scans/<part>.h5` overwrote the part."""
    path, part = grown
    before = part.read_bytes()
    r = subprocess.run([*CLI, "evaluate", str(path), "--scan", "two", "--sizes", "50", "--json", str(part)],
                       capture_output=True, text=True)
    _refused(r, "--json", part, "in the parts directory", path)
    assert part.read_bytes() == before
    assert validate_archive(path) == []


def test_evaluate_json_cannot_overwrite_the_lock_file(grown, tmp_path):
    path, _ = grown
    lock = tmp_path / ".a.h5.lock"
    r = subprocess.run([*CLI, "evaluate", str(path), "--scan", "two", "--sizes", "50", "--json", str(lock)],
                       capture_output=True, text=True)
    _refused(r, "--json", lock, "the lock file", path)


@pytest.mark.parametrize("where", ["scans", "work", "link"])
def test_no_output_goes_into_the_archive_s_own_files(grown, tmp_path, where):
    path, part = grown
    before = part.read_bytes()
    for cmd, suffix in (("slice", ".ply"), ("export", ".html")):
        if where == "scans":
            out, what = path.with_name("a.h5.scans") / f"x{suffix}", "in the parts directory"
        elif where == "work":
            (tmp_path / ".a.h5.parts").mkdir(exist_ok=True)
            out, what = tmp_path / ".a.h5.parts" / f"x{suffix}", "in the build work directory"
        else:
            out = tmp_path / f"elsewhere{suffix}"
            out.hardlink_to(part)
            what = f"a link to {part.name}, a file"
        r = subprocess.run([*CLI, cmd, str(path), "--scan", "one", "--size", "10", "-o", str(out)],
                           capture_output=True, text=True)
        _refused(r, "-o", out, what, path)
    assert part.read_bytes() == before
    assert np.all(validate_archive(path) == [])


def test_build_cannot_write_an_archive_into_another_archive_s_parts(grown, tmp_path):
    path, part = grown
    src = tmp_path / "s.npy"
    np.save(src, np.random.default_rng(0).random((200, 3)))
    before = part.read_bytes()
    for out in (part, path.with_name("a.h5.scans") / "new.h5", tmp_path / ".b.h5.parts" / "c.h5"):
        out.parent.mkdir(exist_ok=True)
        r = subprocess.run([*CLI, "build", str(src), "-o", str(out)], capture_output=True, text=True)
        archive = path if out.parent.name.endswith(".scans") else tmp_path / "b.h5"
        where = "in the parts directory" if archive == path else "in the build work directory"
        assert (r.returncode, r.stderr) == (2, f"lodbuilder build: error: -o {out} is {where} of the archive "
                                               f"{archive}; choose another output\n")
    assert part.read_bytes() == before
