"""LAS/LAZ, E57, text and NumPy readers and writers."""

from __future__ import annotations

import logging
import sys

import numpy as np
import pytest

from lodbuilder.errors import FormatError, MissingDependencyError
from lodbuilder.io import read_scan, read_scans, write_points, write_scan

LAS_DIMS = {"intensity", "return_number", "number_of_returns", "classification", "scan_angle_rank",
            "user_data", "point_source_id", "gps_time", "red", "green", "blue"}


# ---------------------------------------------------------------------------------------- LAS/LAZ

@pytest.mark.data
def test_autzen_laz(shared_data):
    import laspy

    scan = read_scan(shared_data / "autzen_trim.laz")
    las = laspy.read(str(shared_data / "autzen_trim.laz"))
    assert len(scan) == 110000 and scan.reader == "las"
    np.testing.assert_array_equal(scan.points[:, 0], np.asarray(las.x))
    assert LAS_DIMS <= set(scan.attributes)
    assert scan.attributes["classification"].dtype == np.uint8
    np.testing.assert_array_equal(scan.attributes["gps_time"], np.asarray(las.gps_time))
    m = scan.metadata
    assert m["las_point_format"] == 3 and m["las_version"] == "1.2"
    assert m["las_scales"] == [0.01, 0.01, 0.01]
    assert "NAD_1983_HARN_Lambert_Conformal_Conic" in m["las_crs_wkt"]
    assert {v["record_id"] for v in m["las_crs_vlrs"]} >= {34735, 2112}


@pytest.mark.data
@pytest.mark.parametrize("src,dst", [("autzen_trim.laz", "o.laz"), ("simple.las", "o.las"), ("simple.las", "o.laz")])
def test_las_round_trip_same_format(shared_data, tmp_path, src, dst):
    import laspy

    scan = read_scan(shared_data / src)
    # a level: every 7th point, as a slice would give
    keep = np.arange(0, len(scan), 7)
    out = write_points(tmp_path / dst, scan.points[keep], {k: v[keep] for k, v in scan.attributes.items()},
                       metadata=scan.metadata)
    back = read_scan(out)
    np.testing.assert_array_equal(back.points, scan.points[keep])
    for k, v in scan.attributes.items():
        np.testing.assert_array_equal(back.attributes[k], v[keep], err_msg=k)
    for key in ("las_point_format", "las_version", "las_scales", "las_offsets", "las_crs_wkt"):
        assert back.metadata[key] == scan.metadata[key], key
    hdr = laspy.read(str(out)).header
    assert hdr.are_points_compressed == dst.endswith(".laz")


def test_las_extra_bytes_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    pts = rng.random((300, 3)) * 100 + [5e5, 4e6, 10]
    attrs = {"red": rng.integers(0, 65535, 300).astype(np.uint16), "green": np.zeros(300, np.uint16),
             "blue": np.ones(300, np.uint16), "curvature": rng.random(300).astype(np.float32),
             "label": rng.integers(-3, 3, 300).astype(np.int16)}
    out = write_points(tmp_path / "e.laz", pts, attrs, rank=True)
    back = read_scan(out)
    assert back.metadata["las_point_format"] == 7
    assert {d["name"] for d in back.metadata["las_extra_dims"]} == {"curvature", "label", "rank"}
    for k, v in attrs.items():
        np.testing.assert_array_equal(back.attributes[k], v, err_msg=k)
    np.testing.assert_array_equal(back.attributes["rank"], np.arange(300))
    scale = back.metadata["las_scales"][0]
    assert np.abs(back.points - pts).max() <= scale / 2 + 1e-9
    # the rewritten extra bytes keep their definitions
    again = read_scan(write_scan(tmp_path / "e2.las", back))
    assert again.metadata["las_extra_dims"] == back.metadata["las_extra_dims"]


def test_las_missing_dependency(tmp_path, monkeypatch):
    p = tmp_path / "x.las"
    p.write_bytes(b"LASF" + b"\0" * 300)
    monkeypatch.setitem(sys.modules, "laspy", None)  # (an import of it then fails)
    with pytest.raises(MissingDependencyError) as info:
        read_scan(p)
    assert str(info.value) == (
        f"{p}: LAS/LAZ needs laspy, which is not installed; install it with: pip install 'lodbuilder[las]'"
    )


def test_las_garbage(tmp_path):
    p = tmp_path / "x.las"
    p.write_bytes(b"not a las file at all" * 20)
    with pytest.raises(FormatError, match=r"x\.las: .*LAS"):
        read_scan(p)


# ------------------------------------------------------------------------------------------- E57

@pytest.mark.data
def test_pump_e57_with_colours(shared_data):
    import pye57

    scan = read_scan(shared_data / "pumpAVisualReferenceImage.e57")
    raw = pye57.E57(str(shared_data / "pumpAVisualReferenceImage.e57")).read_scan_raw(0)
    assert len(scan) == 155201 and scan.reader == "e57"
    np.testing.assert_array_equal(scan.points[:, 2], raw["cartesianZ"])
    assert {"red", "green", "blue", "intensity", "rowIndex", "columnIndex"} == set(scan.attributes)
    np.testing.assert_array_equal(scan.attributes["red"], raw["colorRed"])
    assert scan.metadata["invalid_dropped"] == 0 and scan.metadata["e57_scan_name"] == "pumpA"


@pytest.mark.data
def test_bunny_double_e57(shared_data):
    scans = read_scans(shared_data / "bunnyDouble.e57")
    assert len(scans) == 1 and len(scans[0]) == 30571 and scans[0].attributes == {}
    assert scans[0].name == "bunnyDouble"


def _quat_matrix(x, y, z, w):
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def test_e57_several_scans_pose_and_invalid(tmp_path, caplog):
    import pye57

    rng = np.random.default_rng(4)
    path = tmp_path / "multi.e57"
    e = pye57.E57(str(path), mode="w")
    local, states = [], []
    q = np.array([0.2, -0.4, 0.1, 0.8])
    q /= np.linalg.norm(q)  # (x, y, z, w)
    t = np.array([10.0, -2.0, 3.5])
    for k in range(2):
        p = rng.random((120, 3))
        st = np.zeros(120, np.int8)
        st[rng.choice(120, 7 + k, replace=False)] = 2
        local.append(p)
        states.append(st)
        e.write_scan_raw({"cartesianX": p[:, 0], "cartesianY": p[:, 1], "cartesianZ": p[:, 2],
                          "cartesianInvalidState": st, "intensity": rng.random(120).astype(np.float32)},
                         name="station", rotation=np.array([q[3], q[0], q[1], q[2]]), translation=t)
    e.close()
    with caplog.at_level(logging.WARNING):
        scans = read_scans(path)
    assert [s.name for s in scans] == ["station", "station_2"]
    R = _quat_matrix(*q)
    for s, p, st in zip(scans, local, states, strict=True):
        keep = st == 0
        assert s.metadata["invalid_dropped"] == int((~keep).sum())
        np.testing.assert_allclose(s.points, p[keep] @ R.T + t, atol=1e-12)
        assert s.attributes["intensity"].shape == (int(keep.sum()),)
    assert "dropped 7 point(s) flagged invalid" in caplog.text
    with pytest.raises(FormatError, match=r"holds 2 scans \(station, station_2\); use lodbuilder\.io\.read_scans"):
        read_scan(path)


# ------------------------------------------------------------------------------------ text, numpy

def _cloud(n=40, seed=5):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)) * [1e5, 1, 1e-4]
    attrs = {"red": rng.integers(0, 256, n).astype(np.uint8), "intensity": rng.random(n).astype(np.float32),
             "t": rng.random(n)}
    return pts, attrs


@pytest.mark.parametrize("suffix", [".csv", ".xyz", ".npy", ".npz", ".ply"])
def test_round_trip_exact(tmp_path, suffix):
    pts, attrs = _cloud()
    out = write_points(tmp_path / f"c{suffix}", pts, attrs, metadata={"note": "x"}, rank=True)
    back = read_scan(out)
    np.testing.assert_array_equal(back.points, pts)
    for k, v in attrs.items():
        if suffix in (".csv", ".xyz"):  # text has no dtypes: the values cast back exactly
            np.testing.assert_array_equal(back.attributes[k].astype(v.dtype), v, err_msg=k)
        else:
            np.testing.assert_array_equal(back.attributes[k], v, err_msg=k)
            assert back.attributes[k].dtype == v.dtype, k
    np.testing.assert_array_equal(back.attributes["rank"], np.arange(len(pts)))


def test_npy_plain_without_attributes(tmp_path):
    pts, _ = _cloud()
    out = write_points(tmp_path / "p.npy", pts)
    arr = np.load(out)
    assert arr.shape == (40, 3) and arr.dtype == np.float64 and arr.dtype.names is None
    np.testing.assert_array_equal(read_scan(out).points, pts)


def test_npy_structured_layout(tmp_path):
    pts, attrs = _cloud()
    arr = np.load(write_points(tmp_path / "s.npy", pts, attrs))
    assert arr.dtype.names == ("x", "y", "z", "red", "intensity", "t")


def test_npz_metadata_kept(tmp_path):
    pts, _ = _cloud()
    back = read_scan(write_points(tmp_path / "m.npz", pts, metadata={"las_scales": [0.01, 0.01, 0.01]}))
    assert back.metadata["las_scales"] == [0.01, 0.01, 0.01]


def test_npy_bad_shape(tmp_path):
    p = tmp_path / "b.npy"
    np.save(p, np.zeros((5, 2)))
    with pytest.raises(FormatError, match=r"b\.npy: array has shape \(5, 2\); expected \(N, 3\)"):
        read_scan(p)


def test_npy_pickle_refused(tmp_path):
    p = tmp_path / "o.npy"
    np.save(p, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(FormatError, match=r"o\.npy: not a readable NumPy file"):
        read_scan(p)


@pytest.mark.parametrize("text,names", [
    ("1 2 3\n4 5 6\n", []),
    ("x,y,z,intensity\n1,2,3,0.5\n4,5,6,0.25\n", ["intensity"]),
    ("2\n1 2 3 -5 10 20 30\n4 5 6 7 40 50 255\n", ["intensity", "red", "green", "blue"]),
    ("1 2 3 10 20 30\n4 5 6 0 0 255\n", ["red", "green", "blue"]),
    ("1 2 3 0.1 0.2 0.9\n4 5 6 0 0 1\n", ["nx", "ny", "nz"]),
    ("//X Y Z Reflectance\n1 2 3 9\n4 5 6 8\n", ["Reflectance"]),
])
def test_text_header_detection(tmp_path, text, names):
    p = tmp_path / "t.pts"
    p.write_text(text)
    s = read_scan(p)
    np.testing.assert_array_equal(s.points, [[1, 2, 3], [4, 5, 6]])
    assert list(s.attributes) == names
    if "red" in names:
        assert s.attributes["red"].dtype == np.uint8


def test_text_ragged_line(tmp_path):
    p = tmp_path / "r.xyz"
    p.write_text("1 2 3\n4 5\n")
    with pytest.raises(FormatError, match=r"r\.xyz: malformed line"):
        read_scan(p)


def test_text_no_xyz_header(tmp_path):
    p = tmp_path / "h.csv"
    p.write_text("a,b,c\n1,2,3\n")
    with pytest.raises(FormatError, match=r"header has no x/y/z columns \(columns: a, b, c\)"):
        read_scan(p)


def test_text_nan(tmp_path):
    p = tmp_path / "n.xyz"
    p.write_text("1 2 3\nnan 5 6\n7 8 inf\n")
    with pytest.raises(FormatError, match=r"2 point\(s\) have NaN or inf"):
        read_scan(p)


def test_text_empty(tmp_path):
    p = tmp_path / "e.csv"
    p.write_text("x,y,z\n")
    with pytest.raises(FormatError, match="no point lines found"):
        read_scan(p)


@pytest.mark.data
@pytest.mark.parametrize("suffix", [".csv", ".npy", ".las", ".ply"])
def test_real_scan_through_every_writer(shared_data, tmp_path, suffix):
    from roundtrip import assert_same

    src = read_scan(shared_data / "frag_115.ply")
    back = read_scan(write_scan(tmp_path / f"f{suffix}", src))
    assert_same(src, back, suffix[1:])
