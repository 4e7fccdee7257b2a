"""Bad inputs are bounded, each a clear message (reliability-3 items 11, 13 and 15): a PLY header
with absurdly many properties (200,000 took minutes and 3.5 GB before anything was said), LAS with
a coordinate scale of 0 (built identical points silently), a PLY holding more vertex rows than its
header declares (read short silently), a bad LAS point-data offset ("holds no points", or a NumPy
message), a Dask scheduler address with an unknown scheme (a traceback)."""

from __future__ import annotations

import struct
import subprocess
import sys

import numpy as np
import pytest

from lodbuilder.errors import FormatError, InputError
from lodbuilder.io import ply as plyio
from lodbuilder.io import read_scan


def ply_binary(path, n_vertices, n_rows=None, extra_props=0):
    props = "".join(f"property float p{i}\n" for i in range(extra_props))
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n_vertices}\n"
            f"property float x\nproperty float y\nproperty float z\n{props}end_header\n")
    rows = np.arange((n_rows or n_vertices) * (3 + extra_props), dtype="<f4")
    path.write_bytes(head.encode() + rows.tobytes())
    return path


def test_absurdly_many_ply_properties_are_refused_at_once(tmp_path, monkeypatch):
    import plyfile

    def parsed(*args, **kwargs):
        raise AssertionError("plyfile parsed the header: the count was not refused first")

    p = ply_binary(tmp_path / "wide.ply", 2, extra_props=plyio.MAX_PROPERTIES)
    with monkeypatch.context() as m, pytest.raises(FormatError) as err:
        m.setattr(plyfile.PlyData, "_parse_header", staticmethod(parsed))
        read_scan(p)
    assert str(err.value) == (
        f"{p}: its PLY header declares more than {plyio.MAX_PROPERTIES:,} properties; lodbuilder "
        f"reads at most {plyio.MAX_PROPERTIES:,} (a scan has x, y, z and a few attributes): check "
        "that the header is not damaged")
    # one below the bound still reads
    ok = ply_binary(tmp_path / "ok.ply", 2, extra_props=plyio.MAX_PROPERTIES - 3)
    assert read_scan(ok).points.shape == (2, 3)


def test_ply_data_longer_than_its_header(tmp_path):
    p = ply_binary(tmp_path / "long.ply", 10, n_rows=25)
    with pytest.raises(FormatError) as err:
        read_scan(p)
    assert str(err.value) == (
        f"{p}: PLY header declares 10 vertices but 180 more bytes follow them (15 more vertices): "
        "the vertex count is wrong or the file has trailing data; fix the 'element vertex' line "
        "or re-export the scan")
    # fewer bytes than one vertex after the data (a trailing newline) is fine
    q = ply_binary(tmp_path / "nl.ply", 10)
    q.write_bytes(q.read_bytes() + b"\n")
    assert read_scan(q).points.shape == (10, 3)


def test_ascii_ply_data_longer_than_its_header(tmp_path):
    p = tmp_path / "long.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                 "property float z\nend_header\n0 0 0\n1 1 1\n2 2 2\n3 3 3\n\n")
    with pytest.raises(FormatError) as err:
        read_scan(p)
    assert str(err.value) == (
        f"{p}: PLY header declares 2 vertices but more vertex lines follow them: the vertex count "
        "is wrong or the file has trailing data; fix the 'element vertex' line or re-export the "
        "scan")


@pytest.fixture
def las(shared_data, tmp_path):
    return bytearray((shared_data / "simple.las").read_bytes()), tmp_path


@pytest.mark.data
def test_las_scale_zero(las):
    data, tmp = las
    struct.pack_into("<d", data, 131, 0.0)
    p = tmp / "scale0.las"
    p.write_bytes(data)
    with pytest.raises(FormatError) as err:
        read_scan(p)
    assert str(err.value) == (
        f"{p}: the LAS header's coordinate scale is 0, 0.01, 0.01 (x, y, z); a scale must be a "
        "finite number above 0 (with 0 every point has the same coordinate): the file is damaged; "
        "re-export it")


@pytest.mark.data
@pytest.mark.parametrize("where", ["past", "inside", "shifted"])
def test_a_bad_point_data_offset(las, where):
    data, tmp = las
    size = len(data)
    offset = {"past": size + 1000, "inside": 100, "shifted": 227 + 7}[where]
    struct.pack_into("<I", data, 96, offset)
    p = tmp / f"{where}.las"
    p.write_bytes(data)
    with pytest.raises(FormatError) as err:
        read_scan(p)
    if where == "inside":
        assert str(err.value) == (
            f"{p}: the LAS header says the points start at byte 100, inside the 227-byte header; "
            "the file is damaged")
    else:
        assert str(err.value) == (
            f"{p}: the LAS header declares 1065 points of 34 bytes from byte {offset} "
            f"({1065 * 34:,} bytes), but the file ends at byte {size}: its point-data offset or "
            "point count is wrong; the file is damaged")


def test_an_unknown_scheduler_scheme_is_one_line(tmp_path):
    from lodbuilder.build.executors import check_scheduler

    with pytest.raises(InputError) as err:
        check_scheduler("bogus://x")
    assert str(err.value) == (
        "scheduler address 'bogus://x' has an unknown scheme 'bogus'; give tcp://HOST:PORT "
        "(or inproc, tls, ucx, ws, wss)")
    assert check_scheduler("tcp://127.0.0.1:8786") == "tcp://127.0.0.1:8786"
    assert check_scheduler("127.0.0.1:8786") == "127.0.0.1:8786"
    src = tmp_path / "a.npy"
    np.save(src, np.random.default_rng(0).random((500, 3)))
    r = subprocess.run([sys.executable, "-m", "lodbuilder.cli.main", "build", str(src), "-o",
                        str(tmp_path / "a.h5"), "--scheduler", "bogus://x"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.splitlines() == [
        "lodbuilder build: error: scheduler address 'bogus://x' has an unknown scheme 'bogus'; "
        "give tcp://HOST:PORT (or inproc, tls, ucx, ws, wss)"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy"]
