"""PLY reader/writer: real files, round trips, and malformed input."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from lodbuilder.errors import FormatError, InputError, ScanFileError, UnsupportedFormatError
from lodbuilder.io import read_scan, write_points


def _plyfile_xyz(path: Path) -> np.ndarray:
    v = PlyData.read(str(path))["vertex"].data
    return np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)


@pytest.mark.data
@pytest.mark.parametrize("name,n", [("bun000.ply", 40256), ("igea.ply", 134345), ("bun_zipper_res2.ply", 8171)])
def test_real_ply_matches_plyfile(shared_data, name, n):
    scan = read_scan(shared_data / name)
    assert scan.points.shape == (n, 3) and scan.points.dtype == np.float64
    np.testing.assert_array_equal(scan.points, _plyfile_xyz(shared_data / name))
    assert scan.reader == "ply" and scan.name == Path(name).stem


@pytest.mark.data
def test_range_grid_skipped_and_recorded(shared_data):
    scan = read_scan(shared_data / "bun000.ply")
    assert scan.attributes == {}
    assert scan.metadata["elements"] == {"vertex": 40256, "range_grid": 204800}
    assert scan.metadata["ply_format"] == "ascii"
    assert any("num_cols 512" in s for s in scan.metadata["obj_info"])


@pytest.mark.data
def test_frag_colours_and_normals(shared_data):
    scan = read_scan(shared_data / "frag_115.ply", name="frag")
    assert scan.name == "frag"
    assert set(scan.attributes) == {"nx", "ny", "nz", "red", "green", "blue"}
    assert scan.attributes["red"].dtype == np.uint8 and scan.attributes["nx"].dtype == np.float32
    v = PlyData.read(str(shared_data / "frag_115.ply"))["vertex"].data
    np.testing.assert_array_equal(scan.attributes["green"], v["green"])
    np.testing.assert_array_equal(scan.attributes["nz"], v["nz"])


def _write_ply(path: Path, data: np.ndarray, text: bool, extra: list | None = None) -> None:
    els = [PlyElement.describe(data, "vertex")] + (extra or [])
    PlyData(els, text=text).write(str(path))


def _cloud(n: int = 50) -> np.ndarray:
    rng = np.random.default_rng(1)
    d = np.empty(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u2")])
    for c in "xyz":
        d[c] = rng.random(n)
    d["intensity"] = rng.integers(0, 60000, n)
    return d


@pytest.mark.parametrize("text", [True, False])
def test_ascii_and_binary_with_faces_after(tmp_path, text):
    d = _cloud()
    faces = np.empty(2, dtype=[("vertex_indices", "i4", (3,))])
    faces["vertex_indices"] = [[0, 1, 2], [1, 2, 3]]
    p = tmp_path / "c.ply"
    _write_ply(p, d, text, [PlyElement.describe(faces, "face")])
    scan = read_scan(p)
    np.testing.assert_array_equal(scan.points[:, 1], d["y"].astype(np.float64))
    assert scan.attributes["intensity"].dtype == np.uint16
    np.testing.assert_array_equal(scan.attributes["intensity"], d["intensity"])


@pytest.mark.parametrize("text", [True, False])
def test_element_before_vertex(tmp_path, text):
    d = _cloud(10)
    cam = np.zeros(1, dtype=[("a", "f4"), ("b", "i4")])
    p = tmp_path / "c.ply"
    PlyData([PlyElement.describe(cam, "camera"), PlyElement.describe(d, "vertex")], text=text).write(str(p))
    np.testing.assert_array_equal(read_scan(p).points[:, 0], d["x"].astype(np.float64))


def test_big_endian(tmp_path):
    d = _cloud(20)
    p = tmp_path / "be.ply"
    PlyData([PlyElement.describe(d, "vertex")], byte_order=">").write(str(p))
    s = read_scan(p)
    np.testing.assert_array_equal(s.points[:, 2], d["z"].astype(np.float64))
    assert s.attributes["intensity"].dtype.byteorder in "=|<"


# ------------------------------------------------------------------------------- malformed input

def test_missing_file(tmp_path):
    with pytest.raises(ScanFileError, match=r"nope\.ply: no such file"):
        read_scan(tmp_path / "nope.ply")


@pytest.mark.skipif(os.geteuid() == 0, reason="root can read anything")
def test_unreadable_file(tmp_path):
    p = tmp_path / "c.ply"
    _write_ply(p, _cloud(), False)
    p.chmod(0)
    with pytest.raises(ScanFileError, match="cannot be read"):
        read_scan(p)


def test_unknown_suffix(tmp_path):
    p = tmp_path / "c.obj"
    p.write_text("v 0 0 0\n")
    with pytest.raises(UnsupportedFormatError, match=r"no reader for suffix '\.obj'; known suffixes: .*\.ply"):
        read_scan(p)


def test_not_a_ply(tmp_path):
    p = tmp_path / "c.ply"
    p.write_bytes(b"hello world\n")
    with pytest.raises(FormatError, match="not a valid PLY header"):
        read_scan(p)


def test_truncated_binary_body(tmp_path):
    p = tmp_path / "c.ply"
    _write_ply(p, _cloud(100), False)
    raw = p.read_bytes()
    p.write_bytes(raw[: len(raw) - 37])
    with pytest.raises(FormatError, match=r"declares 100 vertices .* truncated"):
        read_scan(p)


def test_truncated_ascii_body(tmp_path):
    p = tmp_path / "c.ply"
    _write_ply(p, _cloud(100), True)
    lines = p.read_text().splitlines(keepends=True)
    p.write_text("".join(lines[:-30]))
    with pytest.raises(FormatError, match=r"declares 100 vertices .*(only \d+ vertex lines|bytes follow)"):
        read_scan(p)


@pytest.mark.parametrize("text", [True, False])
def test_count_larger_than_file(tmp_path, text):
    p = tmp_path / "c.ply"
    _write_ply(p, _cloud(100), text)
    raw = p.read_bytes().replace(b"element vertex 100", b"element vertex 150", 1)
    p.write_bytes(raw)
    with pytest.raises(FormatError, match=r"declares 150 vertices"):
        read_scan(p)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_trillion_vertices_refused_before_allocating(tmp_path, fmt):
    p = tmp_path / "huge.ply"
    p.write_bytes(
        f"ply\nformat {fmt} 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n".encode() + b"\x00" * 120
    )
    with pytest.raises(FormatError, match=r"declares 1000000000000 vertices .* only 120 bytes follow"):
        read_scan(p)


def test_no_xyz(tmp_path):
    d = np.zeros(5, dtype=[("u", "f4"), ("v", "f4")])
    p = tmp_path / "uv.ply"
    _write_ply(p, d, False)
    with pytest.raises(FormatError, match=r"vertices lack x/y/z \(properties: u, v\)"):
        read_scan(p)


def test_no_vertex_element(tmp_path):
    p = tmp_path / "f.ply"
    faces = np.zeros(1, dtype=[("vertex_indices", "i4", (3,))])
    PlyData([PlyElement.describe(faces, "face")]).write(str(p))
    with pytest.raises(FormatError, match="no 'vertex' element"):
        read_scan(p)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nonfinite_coordinates(tmp_path, bad):
    d = _cloud(30)
    d["y"][[3, 7]] = bad
    p = tmp_path / "c.ply"
    _write_ply(p, d, False)
    with pytest.raises(FormatError, match=r"2 point\(s\) have NaN or inf coordinates \(first at index 3\)"):
        read_scan(p)


@pytest.mark.parametrize("text", [True, False])
def test_empty_cloud(tmp_path, text):
    p = tmp_path / "e.ply"
    _write_ply(p, _cloud(0), text)
    with pytest.raises(FormatError, match="holds no points"):
        read_scan(p)


def test_malformed_ascii_value(tmp_path):
    p = tmp_path / "c.ply"
    _write_ply(p, _cloud(5), True)
    lines = p.read_text().splitlines(keepends=True)
    lines[-2] = "0.1 abc 0.3 7\n"
    p.write_text("".join(lines))
    with pytest.raises(FormatError, match="malformed PLY vertex line"):
        read_scan(p)


# ----------------------------------------------------------------------------------------- writer

def test_ply_round_trip_all_attributes(tmp_path):
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(200, 3)) * 1e5
    attrs = {
        "red": rng.integers(0, 256, 200).astype(np.uint8),
        "intensity": rng.random(200).astype(np.float32),
        "cls": rng.integers(-5, 5, 200).astype(np.int64),
        "normal": rng.normal(size=(200, 3)),
    }
    p = write_points(tmp_path / "o.ply", pts, attrs, rank=True)
    s = read_scan(p)
    np.testing.assert_array_equal(s.points, pts)
    np.testing.assert_array_equal(s.attributes["red"], attrs["red"])
    np.testing.assert_array_equal(s.attributes["intensity"], attrs["intensity"])
    np.testing.assert_array_equal(s.attributes["cls"], attrs["cls"])
    np.testing.assert_array_equal(s.attributes["normal_1"], attrs["normal"][:, 1])
    np.testing.assert_array_equal(s.attributes["rank"], np.arange(200))
    assert PlyData.read(str(p)).byte_order == "<"


@pytest.mark.data
def test_ply_rewrite_keeps_float32(shared_data, tmp_path):
    src = read_scan(shared_data / "frag_115.ply")
    out = write_points(tmp_path / "f.ply", src.points, src.attributes, metadata=src.metadata)
    assert PlyData.read(str(out))["vertex"].properties[0].val_dtype in ("f4", "float32")
    s = read_scan(out)
    np.testing.assert_array_equal(s.points, src.points)
    for k, v in src.attributes.items():
        np.testing.assert_array_equal(s.attributes[k], v)
        assert s.attributes[k].dtype == v.dtype


def test_write_unknown_suffix(tmp_path):
    with pytest.raises(UnsupportedFormatError, match=r"cannot write suffix '\.obj'; known output suffixes"):
        write_points(tmp_path / "o.obj", np.zeros((2, 3)))


def test_write_missing_directory(tmp_path):
    with pytest.raises(ScanFileError, match="does not exist"):
        write_points(tmp_path / "nodir" / "o.ply", np.zeros((2, 3)))


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_write_unwritable_directory(tmp_path):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    try:
        with pytest.raises(ScanFileError, match="is not writable"):
            write_points(d / "o.ply", np.zeros((2, 3)))
    finally:
        d.chmod(0o700)


def test_write_failure_leaves_no_partial_file(tmp_path):
    p = tmp_path / "o.ply"
    p.write_bytes(b"previous")
    with pytest.raises(InputError, match="attribute 'bad'"):
        write_points(p, np.zeros((3, 3)), {"bad": np.array(["a", "b", "c"])})
    assert p.read_bytes() == b"previous"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["o.ply"]


def test_write_attribute_length_checked(tmp_path):
    with pytest.raises(InputError, match=r"attribute 'a' has shape \(2,\); expected first dimension 3"):
        write_points(tmp_path / "o.ply", np.zeros((3, 3)), {"a": np.zeros(2)})


def test_write_unwritable_directory_reported(tmp_path, monkeypatch):
    import lodbuilder.io._files as files

    monkeypatch.setattr(files.os, "access", lambda *a, **k: False)
    with pytest.raises(ScanFileError, match=r"output directory .* is not writable; choose another output path"):
        write_points(tmp_path / "o.ply", np.zeros((2, 3)))


def test_unreadable_file_reported(tmp_path, monkeypatch):
    import lodbuilder.io._files as files

    p = tmp_path / "c.ply"
    _write_ply(p, _cloud(), False)
    monkeypatch.setattr(files.os, "access", lambda *a, **k: False)
    with pytest.raises(ScanFileError, match=r"c\.ply: cannot be read \(permission denied\)"):
        read_scan(p)
