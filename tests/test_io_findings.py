"""Input defects from ../shared/findings/reliability-2.md (10, 11 and the I/O items of 13).

Each test failed before its fix."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from clirun import in_child
from plyfile import PlyData, PlyElement

from lodbuilder.errors import FormatError, ScanFileError
from lodbuilder.io import read_scan

REPO = Path(__file__).resolve().parents[1]


def _cli(*args: str, cwd: Path, timeout: float = 60) -> subprocess.CompletedProcess:
    return in_child(*args, cwd=cwd, timeout=timeout)


def _cloud(n: int = 60, seed: int = 3) -> np.ndarray:
    g = np.random.default_rng(seed)
    return g.random((n, 3)).astype(np.float32)


def _list_ply(path: Path, lists: list[list[float]]) -> np.ndarray:
    pts = _cloud(len(lists))
    with open(path, "w") as f:
        f.write(f"ply\nformat ascii 1.0\nelement vertex {len(lists)}\nproperty float x\nproperty float y\n"
                "property float z\nproperty list uchar float extra\nend_header\n")
        for p, vals in zip(pts, lists, strict=True):
            f.write(f"{float(p[0])!r} {float(p[1])!r} {float(p[2])!r} {len(vals)} {' '.join(map(repr, vals))}\n")
    return pts


# --------------------------------------------------------------------- 10: per-vertex list property

def test_fixed_length_list_property_becomes_an_n_by_k_attribute(tmp_path):
    _list_ply(tmp_path / "l.ply", [[1.5, 2.5]] * 60)
    scan = read_scan(tmp_path / "l.ply")
    assert scan.attributes["extra"].shape == (60, 2) and scan.attributes["extra"].dtype == np.float32
    np.testing.assert_array_equal(scan.attributes["extra"][:, 1], 2.5)


def test_variable_length_list_property_is_skipped_with_a_note(tmp_path, caplog):
    _list_ply(tmp_path / "v.ply", [[1.0], [1.0, 2.0], []] * 20)
    scan = read_scan(tmp_path / "v.ply")
    assert "extra" not in scan.attributes
    note = ("list property 'extra' skipped: its lists have 0 to 2 values (only lists of one fixed, non-zero "
            "length are kept, as an (N, k) attribute)")
    assert scan.metadata["read_notes"] == [note]
    assert note in caplog.text


def test_build_with_a_list_property(tmp_path):
    """Finding 10: build crashed in layout.compression_pays with a TypeError."""
    from lodbuilder import build_archive, open_archive

    _list_ply(tmp_path / "l.ply", [[0.25, 0.5, 0.75]] * 60)
    build_archive(tmp_path / "l.ply", tmp_path / "l.h5")
    with open_archive(tmp_path / "l.h5") as arc:
        lev = arc.scan().level(fraction=1.0)
    assert lev.attributes["extra"].shape == (60, 3)


# ------------------------------------------------------------------ 11: FIFO and non-regular files

@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs mkfifo")
def test_fifo_is_refused_not_read(tmp_path):
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    # the command first, with a timeout: reading a FIFO used to wait forever
    r = _cli("build", fifo, "-o", tmp_path / "x.h5", cwd=tmp_path, timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().endswith("pipe.ply: is a FIFO (named pipe), not a regular file; save the scan to a file first")
    assert not (tmp_path / "x.h5").exists()
    with pytest.raises(ScanFileError, match=r"pipe\.ply: is a FIFO \(named pipe\), not a regular file; "
                                            r"save the scan to a file first$"):
        read_scan(fifo)


def test_device_is_refused():
    with pytest.raises(ScanFileError, match=r"/dev/null: is a character device, not a regular file"):
        read_scan("/dev/null")


# ---------------------------------------------------------------------------- 13: symlink loop

def test_symlink_loop_is_named(tmp_path):
    (tmp_path / "a.ply").symlink_to(tmp_path / "b.ply")
    (tmp_path / "b.ply").symlink_to(tmp_path / "a.ply")
    with pytest.raises(ScanFileError, match=r"a\.ply: symbolic link loop \(the link points back to itself\); "
                                            r"fix the link$"):
        read_scan(tmp_path / "a.ply")


def test_broken_symlink_is_named(tmp_path):
    (tmp_path / "a.ply").symlink_to(tmp_path / "gone.ply")
    with pytest.raises(ScanFileError, match=r"a\.ply: broken symbolic link \(its target does not exist\); fix the link$"):
        read_scan(tmp_path / "a.ply")


# ---------------------------------------------------------------------- 13: wrong-endian PLY

def test_wrong_endian_binary_ply_says_so(tmp_path):
    v = np.zeros(500, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    pts = _cloud(500) * 10 + 1
    for j, c in enumerate("xyz"):
        v[c] = pts[:, j]
    PlyData([PlyElement.describe(v, "vertex")], byte_order="<").write(str(tmp_path / "le.ply"))
    raw = (tmp_path / "le.ply").read_bytes().replace(b"binary_little_endian", b"binary_big_endian")
    (tmp_path / "be.ply").write_bytes(raw)
    with pytest.raises(FormatError, match=r"be\.ply: the header says binary_big_endian but the vertex data is "
                                          r"binary_little_endian \(\d+ of 1500 coordinates read as NaN, inf or "
                                          r"absurd magnitudes, none the other way\); fix the header line to "
                                          r"'format binary_little_endian 1\.0'$"):
        read_scan(tmp_path / "be.ply")
    np.testing.assert_array_equal(read_scan(tmp_path / "le.ply").points, pts)


# ---------------------------------------------------------------- 13: truncated LAZ, one line

@pytest.mark.data
def test_truncated_laz_gives_one_line(shared_data, tmp_path):
    pytest.importorskip("laspy")
    data = (shared_data / "autzen_trim.laz").read_bytes()
    (tmp_path / "t.laz").write_bytes(data[: len(data) // 2])
    r = _cli("build", "t.laz", "-o", "t.h5", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.splitlines() == [
        "lodbuilder build: error: t.laz: cannot be read as LAS (IoError: failed to fill whole buffer); "
        "check or re-export the file"
    ]


# --------------------------------------------------------------------- 13: a 50 MB PLY comment

@pytest.mark.data
def test_huge_ply_comment_is_capped(shared_data, tmp_path):
    from lodbuilder import build_archive, open_archive
    from lodbuilder.io.ply import COMMENTS_CAP, LINE_CAP

    src = (shared_data / "bun_zipper_res4.ply").read_bytes()
    i = src.index(b"element vertex")
    big = 5_000_000
    (tmp_path / "c.ply").write_bytes(src[:i] + b"comment " + b"A" * big + b"\ncomment after\n" + src[i:])
    scan = read_scan(tmp_path / "c.ply")
    assert len(scan) == 453
    comments = scan.metadata["comments"]
    assert comments[-2] == "A" * (LINE_CAP - len("comment ")) and comments[-1] == "after"
    assert sum(map(len, comments)) <= COMMENTS_CAP
    assert scan.metadata["read_notes"] == [
        "PLY header comments cut: at most 4,096 bytes a line and 64 KiB in all are kept; "
        f"{big + len(b'comment ') + 1 - LINE_CAP:,} bytes of comment text were not kept"
    ]
    build_archive(tmp_path / "c.ply", tmp_path / "c.h5")
    assert (tmp_path / "c.h5").stat().st_size < 200_000
    with open_archive(tmp_path / "c.h5") as arc:
        assert len(json.dumps(arc.scan().format_metadata)) < 2 * COMMENTS_CAP


def test_header_line_too_long_that_is_not_a_comment(tmp_path):
    (tmp_path / "h.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1 " + b"9" * 10000 + b"\nend_header\n")
    with pytest.raises(FormatError, match=r"h\.ply: not a valid PLY header \(a header line is longer than 4096 bytes\)"):
        read_scan(tmp_path / "h.ply")


def test_not_a_ply_file(tmp_path):
    (tmp_path / "n.ply").write_bytes(b"\x00" * 100000)
    with pytest.raises(FormatError, match=r"n\.ply: not a valid PLY header \(the file does not start with 'ply'\)"):
        read_scan(tmp_path / "n.ply")


# ------------------------------------------------------- atomic output: one rule for directories

def test_atomic_output_never_creates_a_directory(tmp_path):
    """Every writer leaves a missing directory to the caller (check_output's rule); the unused
    ``make_parents`` switch that could create one is gone."""
    from lodbuilder.io._files import atomic_output

    out = tmp_path / "new" / "x.ply"
    with pytest.raises(TypeError, match="make_parents"):
        atomic_output(out, make_parents=True)
    with pytest.raises(ScanFileError) as info, atomic_output(out):
        pass
    assert str(info.value) == f"{out}: output directory {tmp_path / 'new'} does not exist; create it first"
    assert list(tmp_path.iterdir()) == []


def test_exc_line_folds_white_space_and_names_a_silent_exception():
    from lodbuilder.io._files import exc_line

    assert exc_line(ValueError("bad\n  value\tthere ")) == "bad value there"
    assert exc_line(KeyError()) == "KeyError"  # (a bare "()" in a message said nothing)
