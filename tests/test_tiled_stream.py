"""Streaming readers (lodbuilder.io.stream): chunk by chunk, exactly what read_scan gives."""

from __future__ import annotations

import numpy as np
import pytest

from lodbuilder.errors import FormatError
from lodbuilder.io import read_scan, write_points
from lodbuilder.io.stream import open_stream, peek_stream, streams


def _same(path, chunk=777, **kw):
    s = open_stream(path, **kw)
    ref = read_scan(path, **kw)
    chunks = list(s.chunks(chunk))
    assert [c.start for c in chunks] == list(range(0, len(ref), chunk))
    np.testing.assert_array_equal(np.concatenate([c.points for c in chunks]), ref.points)
    assert list(s.fields) == list(ref.attributes)
    for k, v in ref.attributes.items():
        a = np.concatenate([c.attributes[k] for c in chunks])
        assert a.dtype == v.dtype == s.fields[k][0] and a.shape[1:] == s.fields[k][1]
        np.testing.assert_array_equal(a, v)
    assert s.metadata == ref.metadata and s.n_points == len(ref) and s.reader == ref.reader
    return s


@pytest.mark.data
@pytest.mark.parametrize("name,streaming", [
    ("autzen_trim.laz", True), ("simple.las", True), ("igea.ply", True), ("frag_115.ply", True),
    ("bun000.ply", False), ("bunnyDouble.e57", False),
])
def test_real_files_stream_like_read_scan(shared_data, name, streaming):
    s = _same(shared_data / name, chunk=30_011)
    assert s.streams is streaming and streams(shared_data / name) is streaming
    assert (peek_stream(shared_data / name) is not None) is streaming


def test_npy_and_ply_layouts(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.random((2000, 3))
    attrs = {"intensity": rng.random(2000).astype(np.float32), "cls": rng.integers(0, 9, 2000).astype(np.uint8)}
    for f in (write_points(tmp_path / "plain.npy", pts), write_points(tmp_path / "rec.npy", pts, attrs),
              write_points(tmp_path / "b.ply", pts, attrs)):
        assert _same(f).streams
    big = tmp_path / "big.ply"  # big-endian binary PLY
    from plyfile import PlyData, PlyElement

    data = np.empty(2000, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("q", ">i2")])
    data["x"], data["y"], data["z"], data["q"] = pts[:, 0], pts[:, 1], pts[:, 2], np.arange(2000)
    PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order=">").write(str(big))
    assert _same(big).streams


def test_truncated_and_bad_values(tmp_path):
    rng = np.random.default_rng(1)
    f = write_points(tmp_path / "t.ply", rng.random((1000, 3)))
    raw = f.read_bytes()
    f.write_bytes(raw[:-100])
    with pytest.raises(FormatError, match="PLY header declares 1000 vertices"):
        open_stream(f)
    pts = rng.random((1000, 3))
    pts[700, 1] = np.nan
    g = write_points(tmp_path / "nan.npy", pts)
    with pytest.raises(FormatError) as exc:
        list(open_stream(g).chunks(256))
    assert str(exc.value) == (f"{g}: 1 point(s) in rows 512..767 have NaN or inf coordinates (first at index "
                              "700); remove them from the file before building")


def test_stream_refuses_what_read_scan_refuses(tmp_path):
    """One read per format: a binary PLY with more rows than its header declares, or whose header
    names the wrong byte order, is refused by the stream with read_scan's message (the stream read
    such files before)."""
    rng = np.random.default_rng(2)
    rows = np.empty(25, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for c in "xyz":
        rows[c] = rng.random(25)
    head = ("ply\nformat {} 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n"
            "end_header\n")
    long = tmp_path / "long.ply"
    long.write_bytes(head.format("binary_little_endian", 10).encode() + rows.tobytes())
    swapped = tmp_path / "swapped.ply"
    swapped.write_bytes(head.format("binary_big_endian", 25).encode() + rows.tobytes())
    for f in (long, swapped):
        with pytest.raises(FormatError) as whole:
            read_scan(f)
        with pytest.raises(FormatError) as chunked:
            list(open_stream(f).chunks(7))
        assert str(chunked.value) == str(whole.value)


def test_a_copc_file_is_named_alike_by_every_path(tmp_path):
    """``a.b.copc.laz``: the whole read named the scan 'a', the stream and the build 'a.b'."""
    import shutil

    from lodbuilder.build.inputs import scan_name

    pts = np.random.default_rng(0).random((50, 3))
    p = tmp_path / "a.b.copc.laz"
    shutil.copy(write_points(tmp_path / "plain.laz", pts), p)
    assert read_scan(p).name == open_stream(p).name == scan_name(p) == "a.b"


@pytest.mark.parametrize("fmt", [0, 1, 3, 6, 8, 10])
def test_las_fields_come_from_the_header_as_the_read_gives_them(tmp_path, fmt):
    """The stream learns every attribute's dtype and shape from the header (a one-point record made
    for it) instead of decompressing the first chunk: they equal what the read returns, extra bytes
    (scaled, unscaled, arrays) included."""
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=fmt, version="1.4")
    header.add_extra_dims([laspy.ExtraBytesParams("height", "int32", scales=np.array([0.01]), offsets=np.array([0.0])),
                           laspy.ExtraBytesParams("flags", "uint8"),
                           laspy.ExtraBytesParams("normal", "3f4")])
    las = laspy.LasData(header)
    rng = np.random.default_rng(fmt)
    las.x, las.y, las.z = rng.random(20), rng.random(20), rng.random(20)
    las.height = rng.random(20)
    p = tmp_path / f"f{fmt}.laz"
    las.write(str(p))
    stream = open_stream(p)
    whole = read_scan(p)
    got = {k: (np.asarray(v).dtype, np.asarray(v).shape[1:]) for k, v in whole.attributes.items()}
    assert stream.fields == got
    chunk = next(stream.chunks(7))
    assert {k: (v.dtype, v.shape[1:]) for k, v in chunk.attributes.items()} == got
