"""What the in-memory build does to keep its peak memory down must not change what it stores:
the scan set aside in its work directory while it is ordered, and the archive written a row group
at a time from the ordering."""

from __future__ import annotations

import mmap
from pathlib import Path

import h5py
import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive import layout as L
from lodbuilder.archive.reader import open_archive
from lodbuilder.archive.writer import ScanRecord, write_archive
from lodbuilder.build import jobs
from lodbuilder.io import Scan, write_points
from lodbuilder.sampling.ordering import Ordering


def _datasets(path) -> dict[str, bytes]:
    out: dict[str, bytes] = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            out[name] = obj[()].tobytes() if obj.shape != () else bytes(str(obj[()]), "utf8")

    with h5py.File(path) as f:
        f.visititems(visit)
    return out


def test_set_aside_keeps_values_dtypes_and_shapes(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.random((500, 3))
    attrs = {"intensity": rng.integers(0, 60000, 500).astype(np.uint16),
             "normals": rng.random((500, 3)).astype(np.float32)[:, ::-1],  # not C-contiguous
             "label": np.array(["a"] * 500, dtype=object)}
    scan = Scan(pts.copy(), {k: v.copy() for k, v in attrs.items()})
    seen = []
    progress = jobs.set_aside(scan, tmp_path / "x.work", lambda *a: seen.append(a))
    assert np.array_equal(scan.points, pts) and scan.points.dtype == np.float64
    # mapped from the file copy-on-write: writeable like the array it replaces (a read-only array
    # is another numba type: every kernel it reached compiled a second time)
    assert isinstance(scan.points.base, mmap.mmap) and scan.points.flags.writeable
    for k, v in attrs.items():
        assert scan.attributes[k].dtype == v.dtype and scan.attributes[k].shape == v.shape
        assert np.array_equal(scan.attributes[k], v)
    assert not isinstance(scan.attributes["label"].base, mmap.mmap)  # objects stay in memory
    progress("band", 1, 1)  # gives the points' pages back: the values read again from the file
    assert np.array_equal(scan.points, pts)
    assert seen == [("band", 1, 1)]


def test_build_with_scan_set_aside_is_identical(tmp_path, monkeypatch):
    rng = np.random.default_rng(1)
    src = tmp_path / "s.ply"
    g = np.stack(np.meshgrid(np.arange(60), np.arange(60)), -1).reshape(-1, 2) / 60.0
    pts = np.c_[g + rng.uniform(-0.003, 0.003, g.shape), 0.05 * np.sin(5 * g[:, 0])]
    write_points(src, pts.astype(np.float32).astype(np.float64),
                 attributes={"red": rng.integers(0, 255, len(pts)).astype(np.uint8)})
    monkeypatch.setattr(jobs, "ASIDE_MIN_POINTS", 10**12)
    lodbuilder.build_archive(src, tmp_path / "plain.h5")
    made = []
    real = jobs.set_aside
    monkeypatch.setattr(jobs, "set_aside", lambda *a: made.append(a[1]) or real(*a))
    monkeypatch.setattr(jobs, "ASIDE_MIN_POINTS", 0)
    lodbuilder.build_archive(src, tmp_path / "aside.h5")
    assert made and not made[0].exists()  # set aside, and its work directory removed after the write
    a, b = _datasets(tmp_path / "plain.h5"), _datasets(tmp_path / "aside.h5")
    assert a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []


@pytest.mark.parametrize("k", [20_000, 11_111, 6_667])
def test_archive_written_by_row_groups(tmp_path, k):
    n = 20_000  # 3 row groups of 6,667 rows
    assert L.row_group_rows(n) < n
    rng = np.random.default_rng(2)
    pts = rng.random((n, 3)) * 1e3
    attrs = {"intensity": rng.integers(0, 60000, n).astype(np.uint16), "rgb": rng.integers(0, 255, (n, 3)).astype(np.uint8)}
    imp = rng.random(n)
    order = rng.permutation(n)[:k]
    radius = np.r_[np.inf, np.sort(rng.random(k - 1))[::-1]]
    parent = np.r_[-1, rng.integers(0, np.arange(1, k))]
    ordg = Ordering(order, radius, parent, 0.1, 0.3, np.array([order[0]]), n, {}, 0.0 if k == n else 0.01)
    rec = ScanRecord(Scan(pts, attrs, name="s"), ordg, importance={"w": (imp, {"kind": "test"})})
    write_archive(tmp_path / "a.h5", [rec])
    seen = np.zeros(n, bool)
    seen[order] = True
    perm = np.r_[order, np.flatnonzero(~seen)]
    with open_archive(tmp_path / "a.h5") as arc:
        v = arc.scan("s")
        assert np.array_equal(v.points(), pts[perm])
        assert np.array_equal(v.source_index, perm)
        assert np.array_equal(v.radius, np.r_[radius, np.zeros(n - k)])
        assert np.array_equal(v.parent, np.r_[parent, np.full(n - k, -1)])
        got = v.attributes()
        for key, a in attrs.items():
            assert got[key].dtype == a.dtype and np.array_equal(got[key], a[perm])
    with h5py.File(tmp_path / "a.h5") as f:
        assert np.array_equal(f[f"{L.G_SCANS}/s/{L.G_IMPORTANCE}/w"][()], imp[perm].astype(np.float32))


def test_build_orders_in_memory_when_the_scan_cannot_be_set_aside(tmp_path, monkeypatch):
    """A full disk (or any failure to write the work files) is no reason to fail the build."""
    import errno

    src = tmp_path / "s.ply"
    rng = np.random.default_rng(3)
    write_points(src, rng.random((3000, 3)).astype(np.float32).astype(np.float64))
    monkeypatch.setattr(jobs, "ASIDE_MIN_POINTS", 10**12)
    lodbuilder.build_archive(src, tmp_path / "plain.h5")

    def full(arr, path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(jobs, "_map_aside", full)
    monkeypatch.setattr(jobs, "ASIDE_MIN_POINTS", 0)
    lodbuilder.build_archive(src, tmp_path / "full.h5")
    a, b = _datasets(tmp_path / "plain.h5"), _datasets(tmp_path / "full.h5")
    assert a.keys() == b.keys() and [k for k in a if a[k] != b[k]] == []


SMAPS = """\
7f0000000000-7f0000001000 r--p 00000000 08:01 11 /venv/llvmlite/binding/libllvmlite.so
Rss:                   4 kB
Anonymous:             0 kB
VmFlags: rd mr mw me
7f0000001000-7f0000005000 r-xp 00001000 08:01 11 /venv/llvmlite/binding/libllvmlite.so
Rss:                  16 kB
Anonymous:             0 kB
VmFlags: rd ex mr mw me
7f0000005000-7f0000006000 r--p 00005000 08:01 11 /venv/llvmlite/binding/libllvmlite.so
Rss:                   4 kB
Anonymous:             4 kB
VmFlags: rd mr mw me ac
7f0000006000-7f0000007000 rw-p 00006000 08:01 11 /venv/llvmlite/binding/libllvmlite.so
Rss:                   4 kB
Anonymous:             0 kB
7f0000007000-7f0000008000 r-xp 00000000 08:01 12 /usr/lib/libc.so.6
Rss:                   4 kB
Anonymous:             0 kB
7f0000008000-7f0000009000 rw-p 00000000 00:00 0
Rss:                   4 kB
Anonymous:             4 kB
"""


def test_compiler_pages_dropped_are_clean_copies_of_the_library_only():
    # the relocated (copied-on-write) and the writable mappings would lose their contents; another
    # library's code is not the compiler's
    from lodbuilder._resources import clean_mappings

    assert clean_mappings(SMAPS, "libllvmlite") == [(0x7F0000000000, 0x7F0000001000),
                                                     (0x7F0000001000, 0x7F0000005000)]


def _rss_kib(matches) -> int:
    """Resident KiB of this process's mappings whose path ``matches`` (from /proc/self/smaps)."""
    cur, tot = "", 0
    with open("/proc/self/smaps") as f:
        for line in f:
            p = line.split()
            if len(p) >= 5 and "-" in p[0] and not p[0].endswith(":"):
                cur = p[5] if len(p) >= 6 else ""
            elif p[0] == "Rss:" and matches(cur):
                tot += int(p[1])
    return tot


def _library_rss_kib(name: str) -> int:
    return _rss_kib(lambda path: name in path)


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="Linux only")
def test_large_builds_give_the_compilers_pages_back_and_the_kernels_still_run(tmp_path):
    # loading the kernels leaves ~69 MiB of LLVM's code resident that no kernel uses
    import numba

    from lodbuilder._resources import TRIM_MIN_POINTS, release_freed_memory

    lodbuilder.fastfps(np.random.default_rng(0).random((300, 3)))  # every kernel loaded
    release_freed_memory(TRIM_MIN_POINTS)
    assert _library_rss_kib("libllvmlite") < 8 << 10
    o = lodbuilder.fastfps(np.random.default_rng(1).random((300, 3)))
    assert sorted(o.order.tolist()) == list(range(300))

    @numba.njit
    def twice(x):  # LLVM still compiles (its pages come back from the file)
        return 2 * x

    assert twice(21) == 42


def _mapping_rss_kib(path) -> int:
    return _rss_kib(lambda cur: cur == str(path))


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="Linux only")
def test_band_gives_the_pages_of_points_set_aside_back_after_its_passes(tmp_path):
    # a scan set aside is read by the band a pass at a time: its pages are not resident meanwhile
    from lodbuilder._resources import PassMap, release_pages
    from lodbuilder.sampling.band import build_band, plan_and_build_band

    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid(np.arange(150), np.arange(150)), -1).reshape(-1, 2) / 150.0
    pts = np.c_[g + rng.uniform(-0.002, 0.002, g.shape), 0.05 * np.sin(5 * g[:, 0])]
    path = tmp_path / "points.bin"
    pts.tofile(path)
    with open(path, "rb") as f:
        mm = PassMap(f.fileno(), 0, access=mmap.ACCESS_COPY)
    aside = np.ndarray(pts.shape, pts.dtype, buffer=mm)
    assert aside.sum() > 0 and _mapping_rss_kib(path) > 0  # read: resident
    release_pages(aside)
    assert _mapping_rss_kib(path) == 0 and np.array_equal(aside, pts)  # read again from the file
    band, plan, _ = plan_and_build_band(aside, None, None)
    assert _mapping_rss_kib(path) == 0
    ref = build_band(pts, plan.h, plan.r)
    again = build_band(aside, plan.h, plan.r)
    assert _mapping_rss_kib(path) == 0
    for k in ("u", "perm", "keys", "nbr", "cs", "vcost", "foot", "near"):
        assert np.array_equal(getattr(ref, k), getattr(again, k)), k
    release_pages(pts)  # any other array: nothing happens
    assert np.array_equal(aside, pts)


_FREED_BACK = r"""
import os, sys
import numpy as np
from lodbuilder._resources import map_large_blocks
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
big = np.ones(20 << 17)  # 20 MiB, mapped; freed, it raises glibc's threshold to 20 MiB
del big
if sys.argv[1] == "1":
    map_large_blocks()
before = rss()
tmp = np.ones(6 << 17)  # 6 MiB
keep = np.ones(1000)  # (a block after it: freeing tmp cannot shrink the top of the heap)
del tmp
print((rss() - before) >> 20)
"""


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="Linux (glibc) only")
def test_large_temporaries_go_back_to_the_system_when_freed():
    import subprocess
    import sys

    def kept(flag: str) -> int:
        out = subprocess.run([sys.executable, "-c", _FREED_BACK, flag], capture_output=True, text=True, check=True)
        return int(out.stdout.strip())

    assert kept("0") >= 5  # glibc's own threshold: the freed 6 MiB stay in the heap
    assert kept("1") <= 1


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="Linux only")
def test_load_kernels_loads_every_engine_kernel_and_gives_the_compilers_pages_back():
    from lodbuilder._kernels.warm import _dispatcher, signatures

    jobs.load_kernels()
    for group in ("band", "thin", "ordering"):
        for name, sig in signatures(group).items():
            assert sig in _dispatcher(name).overloads, name
    assert _library_rss_kib("libllvmlite") < 8 << 10


_LIBRARY_PAGES = r"""
import sys
import lazrs  # its code is resident once loaded
sys.path.insert(0, sys.argv[1])
from test_build_memory import _library_rss_kib
from lodbuilder.build import jobs
before = _library_rss_kib("lazrs")
jobs.load_kernels()
print(before, _library_rss_kib("lazrs"))
"""


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="Linux only")
def test_load_kernels_gives_the_pages_of_the_readers_libraries_back():
    # a LAZ read leaves lazrs's code resident (about 1 MiB; with pyproj, libcrypto and the rest
    # 29 MiB), none of which the ordering calls. In a fresh process: here, objects of other tests
    # freed later by the garbage collector can run lazrs's code again (its pages come back then)
    import subprocess
    import sys

    pytest.importorskip("lazrs")
    out = subprocess.run([sys.executable, "-c", _LIBRARY_PAGES, str(Path(__file__).parent)],
                         capture_output=True, text=True, check=True)
    before, after = (int(x) for x in out.stdout.split())
    assert before > 256 and after < 64


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="Linux only")
def test_writing_a_scan_set_aside_gives_its_pages_back(tmp_path):
    rng = np.random.default_rng(4)
    pts = rng.random((30_000, 3)) * 1e3
    scan = Scan(pts.copy(), {"intensity": rng.integers(0, 60000, pts.shape[0]).astype(np.uint16)}, name="s")
    jobs.set_aside(scan, tmp_path / "s.work", None)
    order = np.arange(pts.shape[0])
    radius = np.r_[np.inf, np.linspace(1.0, 0.0, pts.shape[0] - 1)]
    ordg = Ordering(order, radius, np.r_[-1, np.zeros(pts.shape[0] - 1, np.int64)], 0.1, 0.3, order[:1],
                    pts.shape[0], {}, 0.0)
    write_archive(tmp_path / "a.h5", [ScanRecord(scan, ordg)])
    assert _mapping_rss_kib(tmp_path / "s.work" / "points.bin") == 0
    assert _mapping_rss_kib(tmp_path / "s.work" / "a0.bin") == 0
    with open_archive(tmp_path / "a.h5") as arc:
        assert np.array_equal(arc.scan("s").points(), pts)


_NO_SCIPY = r"""
import sys
import numba
import numpy as np
from lodbuilder.build import jobs
jobs.load_kernels()
print("scipy.linalg" in sys.modules)
@numba.njit
def dot(a, b):  # compiled after: numba takes its own loop for two vectors
    return np.dot(a, b)
print(dot(np.arange(3.0), np.arange(3.0)))
"""


def test_loading_the_kernels_does_not_import_scipy_linalg_for_numba():
    # numba's set-up imports scipy.linalg (14 MiB) only to check for a BLAS no kernel uses
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _NO_SCIPY], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "5.0"]
