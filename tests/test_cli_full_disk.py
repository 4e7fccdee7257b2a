"""Every command and output format on a full disk: one line, exit 2, nothing left behind
(reliability-3 item 8: `export -o x.copc.laz` was killed by SIGABRT from copclib; `slice -o x.laz`
(lazrs), `export -o x.html`, `evaluate --plot`, `view --screenshot` gave tracebacks; `demo` left an
empty folder).

On a real 3 MB tmpfs when this process may mount one (root); the conversion of a failed write to
one line is also tested by simulated ENOSPC, which runs everywhere."""

from __future__ import annotations

import errno
import os
import re

import pytest
from clirun import in_child
from conftest import mounted_tmpfs

from lodbuilder.errors import ScanFileError
from lodbuilder.io import _files


@pytest.fixture(scope="module")
def archive(small_archive):
    return small_archive(20_000, seed=3)


@pytest.fixture
def full_disk(tmp_path):
    """A 3 MB tmpfs filled to its last 16 kB (skipped where this process may not mount one)."""
    with mounted_tmpfs(tmp_path / "disk", "test_a_failed_write_is_one_line covers the conversion") as d:
        st = os.statvfs(d)
        (d / "filler").write_bytes(b"\0" * (st.f_bavail * st.f_frsize - 16_384))
        yield d


def cli(*args):
    return in_child(*args)


def no_space(command, path):
    return (f"lodbuilder {command}: error: {path}: no space left on the device; free some space "
            "or choose another location (nothing was written)")


CASES = {
    "copc": ("export", "{a}", "-o", "{o}.copc.laz"),
    "html": ("export", "{a}", "-o", "{o}.html"),
    "laz": ("slice", "{a}", "--fraction", "0.5", "-o", "{o}.laz"),
    "las": ("slice", "{a}", "--fraction", "0.5", "-o", "{o}.las"),
    "npy": ("slice", "{a}", "--fraction", "0.5", "-o", "{o}.npy"),
    "ply": ("slice", "{a}", "--fraction", "0.5", "-o", "{o}.ply"),
    "csv": ("slice", "{a}", "--fraction", "0.5", "-o", "{o}.csv"),
    "npz": ("slice", "{a}", "--fraction", "0.5", "-o", "{o}.npz"),
    "plot": ("evaluate", "{a}", "--plot", "{o}.png"),
    "screenshot": ("view", "{a}", "--size", "5000", "--screenshot", "{o}.png"),
    "animation": ("view", "{a}", "--size", "5000", "--animate", "{o}.gif", "--frames", "3"),
    "json": ("evaluate", "{a}", "--json", "{o}.json"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_every_format_on_a_full_disk_is_one_line(case, archive, full_disk):
    args = [a.format(a=archive, o=full_disk / "x") for a in CASES[case]]
    if case in ("screenshot", "animation"):
        pytest.importorskip("pyvista")
    if case == "json":  # a report of a few kB: the disk full to its last byte
        (full_disk / "last").write_bytes(b"\0" * os.statvfs(full_disk).f_bavail * os.statvfs(full_disk).f_frsize)
    r = cli(*args)
    out = next(a for a in args if a.startswith(str(full_disk)))
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])  # copc: -6 (SIGABRT)
    assert r.stderr.strip().splitlines() == [no_space(args[0], out)], r.stderr[-2000:]
    assert sorted(p.name for p in full_disk.iterdir() if p.name != "last") == ["filler"]


def test_demo_on_a_full_disk_leaves_no_folder(full_disk):
    out = full_disk / "demo"
    r = cli("demo", "-o", out, "--points", "20000", "--no-progress")
    assert r.returncode == 2, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lodbuilder demo: error: "), lines
    assert "no space left on the device" in lines[0], lines
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]


def test_demo_keeps_a_folder_it_did_not_create(full_disk):
    out = full_disk / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("x")
    r = cli("demo", "-o", out, "--points", "20000", "--no-progress")
    assert r.returncode == 2
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


# ----------------------------------------------------------------------------------- simulated


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_failed_write_is_one_line(tmp_path):
    out = tmp_path / "x.html"
    with pytest.raises(ScanFileError) as err, _files.atomic_output(out) as tmp:
        tmp.write_text("partial")
        _enospc()
    assert str(err.value) == (f"{out}: no space left on the device; free some space or choose "
                              "another location (nothing was written)")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ScanFileError) as err, _files.atomic_output(out):
        raise OSError(errno.EIO, os.strerror(errno.EIO))
    assert str(err.value) == (f"{out}: cannot be written (Input/output error); check the disk "
                              "and permissions (nothing was written)")


def test_a_native_abort_is_caught(tmp_path):
    """A library that aborts the process (copclib on a full disk) runs in a child process."""
    out = tmp_path / "x.bin"

    def crash(path):
        path.write_bytes(b"partial")
        os.write(2, b"terminate called after throwing an instance of 'std::runtime_error'\n")
        os.abort()

    with pytest.raises(ScanFileError) as err, _files.atomic_output(out) as tmp:
        _files.run_isolated(crash, tmp, "copclib")
    assert re.fullmatch(
        rf"{re.escape(str(out))}: cannot be written \(copclib was killed by SIGABRT: terminate "
        r"called after throwing an instance of 'std::runtime_error'\); check the disk and "
        r"permissions \(nothing was written\)", str(err.value)), str(err.value)
    assert list(tmp_path.iterdir()) == []
    # and a write that works comes back whole
    with _files.atomic_output(out) as tmp:
        _files.run_isolated(lambda p: p.write_bytes(b"whole"), tmp, "copclib")
    assert out.read_bytes() == b"whole"


def test_a_full_disk_anywhere_is_one_line(monkeypatch, capsys):
    from lodbuilder.cli import info, main

    def full(args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/x/y.tmp")

    monkeypatch.setattr(info, "run", full)
    assert main.main(["info", "a.h5"]) == 2
    assert capsys.readouterr().err == ("lodbuilder info: error: /x/y.tmp: no space left on the "
                                       "device; free some space or choose another location\n")
