"""Every bad input of issue 3 section 5: a one-line error, exit 2, and no partial output."""

from __future__ import annotations

import os

import h5py
import numpy as np
import pytest

from lodbuilder.archive import layout as L
from lodbuilder.cli.main import main


def ply_bytes(n_header, rows, props=("x", "y", "z"), fmt="binary_little_endian", dtype="float"):
    head = ["ply", f"format {fmt} 1.0", f"element vertex {n_header}"]
    head += [f"property {dtype} {p}" for p in props]
    head.append("end_header")
    body_arr = np.asarray(rows, dtype=np.float32).reshape(-1, len(props))
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) for v in r) + "\n" for r in body_arr).encode()
    else:
        body = body_arr.astype("<f4").tobytes()
    return ("\n".join(head) + "\n").encode() + body


GOOD_ROWS = np.random.default_rng(0).random((100, 3))


def run_err(capsys, argv, cmd):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert rc == 2, (rc, out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"lodbuilder {cmd}: error: ")
    return lines[0]


@pytest.fixture
def arc(tmp_path):
    """A small valid archive built from a generated PLY."""
    src = tmp_path / "in.ply"
    src.write_bytes(ply_bytes(100, GOOD_ROWS))
    a = tmp_path / "a.h5"
    assert main(["build", str(src), "-o", str(a), "--no-progress"]) == 0
    return a


def assert_no_output(d, before):
    assert sorted(p.name for p in d.iterdir()) == before


# --- build inputs ---------------------------------------------------------------------------

BAD_PLY = {
    "truncated binary body": (
        ply_bytes(100, GOOD_ROWS)[:-50],
        r"declares 100 vertices .* truncated",
    ),
    "vertex count larger than the file": (
        ply_bytes(1000, GOOD_ROWS),
        r"declares 1000 vertices .* truncated",
    ),
    "10^12 vertices": (ply_bytes(10**12, GOOD_ROWS), r"declares 1000000000000 vertices"),
    "no x/y/z": (ply_bytes(100, GOOD_ROWS, props=("a", "b", "c")), r"lack x/y/z"),
    "NaN coordinates": (
        ply_bytes(3, [[0, 0, 0], [np.nan, 1, 2], [1, 1, 1]], fmt="ascii"),
        r"NaN or inf",
    ),
    "inf coordinates": (ply_bytes(3, [[0, 0, 0], [np.inf, 1, 2], [1, 1, 1]]), r"NaN or inf"),
    "empty cloud": (ply_bytes(0, np.zeros((0, 3))), r"holds no points"),
}


@pytest.mark.parametrize("case", list(BAD_PLY))
def test_build_rejects_malformed_ply(tmp_path, capsys, case):
    data, pattern = BAD_PLY[case]
    src = tmp_path / "bad.ply"
    src.write_bytes(data)
    before = sorted(p.name for p in tmp_path.iterdir())
    line = run_err(capsys, ["build", src, "-o", tmp_path / "out.h5", "--no-progress"], "build")
    assert "bad.ply" in line
    import re

    assert re.search(pattern, line), line
    assert_no_output(tmp_path, before)


def test_build_refuses_10e12_without_allocating(tmp_path, capsys):
    import resource

    src = tmp_path / "huge.ply"
    src.write_bytes(ply_bytes(10**12, GOOD_ROWS))
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    run_err(capsys, ["build", src, "-o", tmp_path / "o.h5", "--no-progress"], "build")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 200_000  # KiB


def test_build_missing_file(tmp_path, capsys):
    line = run_err(capsys, ["build", tmp_path / "nope.ply", "-o", tmp_path / "o.h5"], "build")
    assert "nope.ply" in line and "no such file" in line
    assert not (tmp_path / "o.h5").exists()


def test_build_unreadable_file(tmp_path, capsys, monkeypatch):
    src = tmp_path / "locked.ply"
    src.write_bytes(ply_bytes(100, GOOD_ROWS))
    src.chmod(0)
    if os.geteuid() == 0:  # root reads anything: emulate the permission check a user would hit
        real = os.access
        monkeypatch.setattr(
            os, "access", lambda p, m, **k: False if str(p) == str(src) else real(p, m, **k)
        )
    line = run_err(capsys, ["build", src, "-o", tmp_path / "o.h5"], "build")
    assert "locked.ply" in line and "permission" in line
    assert not (tmp_path / "o.h5").exists()


def test_build_directory_as_input(tmp_path, capsys):
    line = run_err(capsys, ["build", tmp_path, "-o", tmp_path / "o.h5"], "build")
    # a directory is a collection for the collections issue: without scan files it is an error
    assert "is a directory" in line or "holds no scan files" in line
    assert not (tmp_path / "o.h5").exists()


def test_build_unknown_extension(tmp_path, capsys):
    src = tmp_path / "scan.foo"
    src.write_text("1 2 3\n")
    line = run_err(capsys, ["build", src, "-o", tmp_path / "o.h5"], "build")
    assert "no reader for suffix '.foo'" in line
    assert not (tmp_path / "o.h5").exists()


def test_build_output_equal_to_input(tmp_path, capsys):
    src = tmp_path / "in.ply"
    data = ply_bytes(100, GOOD_ROWS)
    src.write_bytes(data)
    line = run_err(capsys, ["build", src, "-o", src], "build")
    assert line == f"lodbuilder build: error: -o {src} must end in .h5 or .hdf5"
    assert src.read_bytes() == data


def test_build_into_non_archive_is_refused(tmp_path, capsys):
    src = tmp_path / "in.ply"
    src.write_bytes(ply_bytes(100, GOOD_ROWS))
    target = tmp_path / "notes.h5"
    target.write_text("my notes")
    line = run_err(capsys, ["build", src, "-o", target], "build")
    assert "is not an lodbuilder archive" in line and target.read_text() == "my notes"


def test_build_bad_parameters(tmp_path, capsys):
    src = tmp_path / "in.ply"
    src.write_bytes(ply_bytes(100, GOOD_ROWS))
    line = run_err(capsys, ["build", src, "-o", tmp_path / "o.h5", "--voxel-size", "-1"], "build")
    assert "--voxel-size must be a finite number > 0" in line
    line = run_err(capsys, ["build", src, "-o", tmp_path / "o.h5", "--band-radius", "nan"], "build")
    assert "--band-radius must be a finite number > 0" in line
    assert not (tmp_path / "o.h5").exists()


def _deny_write(monkeypatch, directory):
    directory.chmod(0o555)
    if os.geteuid() == 0:  # root writes anywhere: emulate the check a user would hit
        real = os.access
        monkeypatch.setattr(
            os,
            "access",
            lambda p, m, **k: (
                False if (str(p) == str(directory) and m & os.W_OK) else real(p, m, **k)
            ),
        )


def test_build_output_directory_not_writable(tmp_path, capsys, monkeypatch):
    src = tmp_path / "in.ply"
    src.write_bytes(ply_bytes(100, GOOD_ROWS))
    ro = tmp_path / "ro"
    ro.mkdir()
    _deny_write(monkeypatch, ro)
    try:
        line = run_err(capsys, ["build", src, "-o", ro / "o.h5"], "build")
        assert "is not writable" in line and str(ro) in line
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


def test_build_output_directory_missing(tmp_path, capsys):
    src = tmp_path / "in.ply"
    src.write_bytes(ply_bytes(100, GOOD_ROWS))
    line = run_err(capsys, ["build", src, "-o", tmp_path / "no" / "o.h5"], "build")
    assert "does not exist" in line


# --- archives and slices --------------------------------------------------------------------


@pytest.mark.parametrize("cmd", ["slice", "info", "validate"])
def test_not_an_archive(tmp_path, capsys, cmd):
    f = tmp_path / "text.h5"
    f.write_text("hello")
    extra = ["--size", "3", "-o", tmp_path / "o.ply"] if cmd == "slice" else []
    line = run_err(capsys, [cmd, f, *extra], cmd)
    assert "text.h5 is not an lodbuilder archive" in line
    other = tmp_path / "plain.h5"
    with h5py.File(other, "w") as h:
        h["data"] = np.arange(3)
    line = run_err(capsys, [cmd, other, *extra], cmd)
    assert "HDF5 file but not an lodbuilder archive" in line
    line = run_err(capsys, [cmd, tmp_path / "missing.h5", *extra], cmd)
    assert "missing.h5 does not exist" in line
    assert not (tmp_path / "o.ply").exists()


def test_newer_schema_version(arc, tmp_path, capsys):
    with h5py.File(arc, "r+") as f:
        f.attrs[L.A_SCHEMA_VERSION] = np.int64(L.SCHEMA_VERSION + 5)
    for cmd, extra in [
        ("slice", ["--size", "3", "-o", tmp_path / "o.ply"]),
        ("info", []),
        ("validate", []),
    ]:
        line = run_err(capsys, [cmd, arc, *extra], cmd)
        assert (
            f"schema version {L.SCHEMA_VERSION + 5}, newer than" in line
            and "upgrade lodbuilder" in line
        )
    assert not (tmp_path / "o.ply").exists()


@pytest.mark.parametrize(
    "args,message",
    [
        (["--rho", "0"], "rho must be a finite number > 0, got 0.0"),
        (["--rho", "-0.5"], "rho must be a finite number > 0"),
        (["--rho", "nan"], "rho must be a finite number > 0, got nan"),
        (["--size", "0"], r"size must be between 1 and the number of points (100), got 0"),
        (["--size", "-3"], r"size must be between 1 and the number of points (100), got -3"),
        (["--size", "101"], r"size must be between 1 and the number of points (100), got 101"),
        (["--fraction", "0"], "fraction must be a number in (0, 1]"),
        (["--fraction", "2"], "fraction must be a number in (0, 1]"),
        (["--size", "5", "--scan", "nope"], "has no scan 'nope'; it holds 'in'"),
        (["--rho", "0.1", "--box", "0", "0", "0", "1", "1", "1"], "--box needs --box-rho"),
        (["--size", "5", "--ordering", "weighted"], "has no ordering 'weighted'"),
    ],
)
def test_bad_slice_arguments(arc, tmp_path, capsys, args, message):
    out = tmp_path / "lvl.ply"
    line = run_err(capsys, ["slice", arc, *args, "-o", out], "slice")
    assert message in line
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".lvl.ply")]


def test_slice_output_equal_to_input(arc, capsys):
    before = arc.read_bytes()
    line = run_err(capsys, ["slice", arc, "--size", "5", "-o", arc], "slice")
    assert "is the input archive" in line
    assert arc.read_bytes() == before


def test_slice_unknown_output_suffix(arc, tmp_path, capsys):
    line = run_err(capsys, ["slice", arc, "--size", "5", "-o", tmp_path / "lvl.xyzw"], "slice")
    assert "cannot write suffix '.xyzw'" in line
    assert not (tmp_path / "lvl.xyzw").exists()


def test_slice_output_directory_not_writable(arc, tmp_path, capsys, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    _deny_write(monkeypatch, ro)
    try:
        line = run_err(capsys, ["slice", arc, "--size", "5", "-o", ro / "lvl.ply"], "slice")
        assert "not writable" in line
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)
