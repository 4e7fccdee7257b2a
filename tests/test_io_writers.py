"""Writers that lose nothing or say what they changed (issue 13.1): LAS mapping, PLY, CSV."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from lodbuilder.io import read_scan, write_points, write_scan
from lodbuilder.io.api import collect_notes

laspy = pytest.importorskip("laspy")

WKT_UTM33 = (
    'PROJCS["WGS 84 / UTM zone 33N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
    'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],'
    'PARAMETER["latitude_of_origin",0],PARAMETER["central_meridian",15],PARAMETER["scale_factor",0.9996],'
    'PARAMETER["false_easting",500000],PARAMETER["false_northing",0],UNIT["metre",1]]'
)


def _ply_like(n=200, seed=1):
    g = np.random.default_rng(seed)
    pts = (g.random((n, 3)) * [0.15, 0.15, 0.12]).astype(np.float32).astype(np.float64)
    attrs = {
        "intensity": g.random(n).astype(np.float32),
        "red": g.integers(0, 256, n).astype(np.uint8),
        "green": g.integers(0, 256, n).astype(np.uint8),
        "blue": g.integers(0, 256, n).astype(np.uint8),
        "confidence": g.random(n).astype(np.float32),
    }
    return pts, attrs


# ---------------------------------------------------------------------------------------- LAS

def test_float_intensity_is_kept_exactly_and_scaled_for_viewers(tmp_path):
    """Before: a float intensity became 0 for every point."""
    pts, attrs = _ply_like()
    out = write_points(tmp_path / "a.las", pts, attrs)
    las = laspy.read(str(out))
    assert las.header.point_format.id == 7 and str(las.header.version) == "1.4"
    exact = np.asarray(las["intensity_float32"])
    np.testing.assert_array_equal(exact, attrs["intensity"])
    std = np.asarray(las.intensity)
    assert std.max() == 65535 and std.min() > 0
    np.testing.assert_array_equal(std, np.rint(attrs["intensity"].astype(np.float64) / attrs["intensity"].max() * 65535))
    back = read_scan(out)  # our reader restores the attribute under its own name
    assert "intensity_float32" not in back.attributes
    np.testing.assert_array_equal(back.attributes["intensity"], attrs["intensity"])
    np.testing.assert_array_equal(back.attributes["confidence"], attrs["confidence"])


def test_8bit_colour_scaled_x257(tmp_path):
    pts, attrs = _ply_like()
    las = laspy.read(str(write_points(tmp_path / "c.las", pts, attrs)))
    for c in ("red", "green", "blue"):
        np.testing.assert_array_equal(np.asarray(las[c]), attrs[c].astype(np.uint16) * 257)


def test_scale_from_the_point_spacing(tmp_path, shared_data):
    """Before: 1e-8 / 1e-9 scales (LAZ 1.6-1.9x larger)."""
    scan = read_scan(shared_data / "bun_zipper.ply")
    las = laspy.read(str(write_scan(tmp_path / "b.laz", scan)))
    np.testing.assert_array_equal(las.header.scales, [1e-6] * 3)
    assert np.abs(np.stack([las.x, las.y, las.z], 1) - scan.points).max() <= 0.5e-6 * (1 + 1e-6)


def test_a_copc_name_is_refused_not_written_as_plain_laz(tmp_path):
    """Before: write_points("x.copc.laz", ...) wrote a plain LAZ under a COPC name."""
    from lodbuilder.errors import UnsupportedFormatError

    pts, attrs = _ply_like()
    for name in ("x.copc.laz", "Y.COPC.LAZ"):
        out = tmp_path / name
        with pytest.raises(UnsupportedFormatError) as info:
            write_points(out, pts, attrs)
        assert str(info.value) == (
            f"{out}: cannot write a COPC file (only plain LAS/LAZ); use lodbuilder export ARCHIVE "
            f"-o {out} (in Python: lodbuilder.export.copc.export_copc)"
        )
    assert list(tmp_path.iterdir()) == []
    assert read_scan(write_points(tmp_path / "copc.laz", pts, attrs)).points.shape == pts.shape


def test_las_source_scale_and_format_kept(tmp_path, shared_data):
    scan = read_scan(shared_data / "simple.las")
    las = laspy.read(str(write_scan(tmp_path / "s.las", scan)))
    np.testing.assert_array_equal(las.header.scales, [0.01] * 3)
    assert las.header.point_format.id == 3 and str(las.header.version) == "1.2"


def test_wkt_bit_and_vlr_for_point_formats_6_to_10(tmp_path):
    pts, attrs = _ply_like()
    out = write_points(tmp_path / "w.laz", pts, attrs, crs=WKT_UTM33)
    hdr = laspy.read(str(out)).header
    assert hdr.point_format.id == 7 and hdr.global_encoding.wkt
    wkts = [v for v in hdr.vlrs if type(v).__name__ == "WktCoordinateSystemVlr"]
    assert len(wkts) == 1 and wkts[0].string.rstrip("\x00") == WKT_UTM33
    assert read_scan(out).metadata["crs_wkt"] == WKT_UTM33


def test_no_crs_no_crs_vlr_and_the_wkt_bit_by_point_format(tmp_path):
    """Without a CRS no CRS VLR is written; the WKT bit is set for point formats 6-10 all the
    same (LAS 1.4 requires it: it failed before, the bit was left 0) and not for formats 0-5."""
    pts, attrs = _ply_like()
    hdr = laspy.read(str(write_points(tmp_path / "n.las", pts, attrs))).header
    assert hdr.point_format.id == 7 and hdr.global_encoding.wkt
    assert not any(v.user_id == "LASF_Projection" for v in hdr.vlrs)
    old = write_points(tmp_path / "o.las", pts, attrs, metadata={"las_point_format": 3, "las_version": "1.2"})
    hdr = laspy.read(str(old)).header
    assert hdr.point_format.id == 3 and not hdr.global_encoding.wkt


def _survey_source(path, fmt=7, crs=True):
    """A LAS 1.4 file of point format ``fmt`` with the WKT bit set and three extra-bytes fields:
    a float with a no-data value, a uint16 with one, a scaled int32 (scale and offset)."""
    rng = np.random.default_rng(4)
    n = 3000
    h = laspy.LasHeader(point_format=fmt, version="1.4")
    h.scales, h.offsets = [0.01] * 3, [0.0, 0.0, 0.0]
    h.add_extra_dim(laspy.ExtraBytesParams("alpha", "f4", "first field", no_data=[-9999.0]))
    h.add_extra_dim(laspy.ExtraBytesParams("beta", "u2", "second field", no_data=[65535]))
    h.add_extra_dim(laspy.ExtraBytesParams("gamma", "i4", "scaled", scales=[0.1], offsets=[5.0]))
    h.add_extra_dim(laspy.ExtraBytesParams("vec", "3f4", "three", no_data=[np.nan, 0, 0]))
    if crs:
        pytest.importorskip("pyproj")
        import pyproj

        h.add_crs(pyproj.CRS.from_epsg(32633))
    h.global_encoding.wkt = True
    las = laspy.LasData(h)
    xy = rng.random((n, 2)) * 100
    las.x, las.y, las.z = xy[:, 0], xy[:, 1], np.sin(xy[:, 0] / 10)
    las.alpha = rng.random(n).astype("f4")
    las.alpha[:10] = -9999
    las.beta = rng.integers(0, 100, n)
    las.gamma = np.round(rng.random(n) * 10, 1) + 5
    las.vec = rng.random((n, 3))
    las.write(str(path))
    return path


def _extra_structs(path) -> list:
    hdr = laspy.read(str(path)).header
    (vlr,) = [v for v in hdr.vlrs if type(v).__name__ == "ExtraBytesVlr"]
    return [(s.name.rstrip(b"\0"), s.description.rstrip(b"\0"), int(s.data_type), int(s.options) & 25,
             None if s.no_data is None else np.asarray(s.no_data).tolist(),
             None if s.scale is None else np.asarray(s.scale).tolist(),
             None if s.offset is None else np.asarray(s.offset).tolist())
            for s in vlr.extra_bytes_structs]


@pytest.mark.parametrize("crs", [True, False])
def test_wkt_bit_and_extra_bytes_from_every_source(tmp_path, crs):
    """A LAS 1.4 format-7 source with the WKT bit and extra bytes with names, descriptions,
    no-data values (option bit 0), scales and offsets; built, then written as LAS, LAZ and COPC,
    and built again from the COPC file: every output keeps the WKT bit and every extra-bytes
    field as laspy reads it (the no-data options were dropped before, 7 -> 6)."""
    from lodbuilder.cli.main import main

    src = _survey_source(tmp_path / "src.las", crs=crs)
    want = _extra_structs(src)
    assert [w[3] for w in want] == [1, 1, 24, 1]  # no-data / scale+offset bits of the source
    arc, arc2 = tmp_path / "a.h5", tmp_path / "b.h5"
    assert main(["build", str(src), "-o", str(arc), "-q"]) == 0
    outs = [tmp_path / "o.las", tmp_path / "o.laz", tmp_path / "o.copc.laz"]
    for out in outs:
        cmd = "export" if out.name.endswith(".copc.laz") else "slice"
        assert main([cmd, str(arc), "--size", "3000", "-o", str(out), "-q"]) == 0
    assert main(["build", str(outs[2]), "-o", str(arc2), "-q"]) == 0
    outs.append(tmp_path / "again.laz")
    assert main(["slice", str(arc2), "--size", "3000", "-o", str(outs[3]), "-q"]) == 0
    s = laspy.read(str(src))
    for out in outs:
        got = laspy.read(str(out))
        assert got.header.global_encoding.wkt, out.name
        assert _extra_structs(out) == want or _nan_equal(_extra_structs(out), want), out.name
        order = np.lexsort((np.asarray(got.Y), np.asarray(got.X)))
        ref = np.lexsort((np.asarray(s.Y), np.asarray(s.X)))
        for name in ("alpha", "beta", "gamma", "vec"):
            np.testing.assert_array_equal(np.asarray(got[name])[order], np.asarray(s[name])[ref], name)


def _nan_equal(a, b) -> bool:
    return repr(a).replace("nan", "N") == repr(b).replace("nan", "N")


def test_every_cast_is_a_warning(tmp_path, caplog):
    pts, attrs = _ply_like()
    p = tmp_path / "x.las"
    with caplog.at_level(logging.WARNING, logger="lodbuilder.io"):
        write_points(p, pts, attrs)
        logged = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        caplog.clear()
        with collect_notes() as notes:  # a command's report takes them out of the log
            write_points(p, pts, attrs)
        assert caplog.records == []
    assert logged == notes == [
        f"{p}: coordinates quantised to scale 0.0001 (error <= 5e-05) with offset 0, 0, 0",
        f"{p}: intensity: float32 values do not fit the LAS field; exact values in extra bytes 'intensity_float32', "
        "the standard field holds a scaled copy (mapped [0, 0.998559] -> [0, 65535])",
        f"{p}: red: 8-bit values scaled x 257 into the 16-bit LAS field",
        f"{p}: green: 8-bit values scaled x 257 into the 16-bit LAS field",
        f"{p}: blue: 8-bit values scaled x 257 into the 16-bit LAS field",
    ]
    assert logging.getLogger("lodbuilder.io").propagate  # left as it was


def test_collect_notes_whatever_the_level_and_passes_the_rest_on(tmp_path, caplog):
    """Warnings below the log level (``-q``) are still collected; INFO lines still reach the log."""
    pts, attrs = _ply_like()
    lg = logging.getLogger("lodbuilder")
    for level, info in ((logging.ERROR, []), (logging.INFO, [f"wrote 200 points to {tmp_path / 'q.las'} (las)"])):
        caplog.clear()
        old = lg.level
        lg.setLevel(level)
        try:
            with collect_notes() as notes:
                write_points(tmp_path / "q.las", pts, attrs)
        finally:
            lg.setLevel(old)
        assert len(notes) == 5
        assert [r.getMessage() for r in caplog.records if r.name.startswith("lodbuilder")] == info


def test_las_layout_is_public_and_plain(shared_data):
    """The mapping helper "interop" reuses for COPC: plain data plus a laspy header."""
    from lodbuilder.io.las import las_layout

    scan = read_scan(shared_data / "autzen_trim.laz")
    lay = las_layout(scan.points, scan.attributes, scan.metadata)
    assert lay.point_format == 3 and lay.version == "1.2" and lay.notes == []
    np.testing.assert_array_equal(lay.scales, [0.01] * 3)
    assert lay.crs_wkt == scan.metadata["crs_wkt"]
    assert {v["record_id"] for v in lay.vlrs} == {34735, 34736, 34737, 2112}
    hdr = lay.header()
    assert hdr.point_format.id == 3


def test_bool_and_int64_and_vector_attributes(tmp_path):
    n = 50
    pts = np.random.default_rng(0).random((n, 3))
    attrs = {"flag": np.arange(n) % 2 == 0, "big": np.arange(n, dtype=np.int64) * 2**40,
             "normal3": np.ones((n, 3), np.float32), "radius": np.full(n, np.inf)}
    back = read_scan(write_points(tmp_path / "v.laz", pts, attrs))
    np.testing.assert_array_equal(back.attributes["flag"], attrs["flag"].astype(np.uint8))
    np.testing.assert_array_equal(back.attributes["big"], attrs["big"])
    np.testing.assert_array_equal(back.attributes["normal3"], attrs["normal3"])
    assert np.isinf(back.attributes["radius"]).all()


# ---------------------------------------------------------------------------------------- PLY

def _ply_header(path):
    head = []
    with open(path, "rb") as f:
        for line in f:
            head.append(line.decode().strip())
            if head[-1] == "end_header":
                return head
    return head


def test_ply_standard_property_order(tmp_path):
    n = 10
    pts = np.zeros((n, 3))
    attrs = {"zeta": np.zeros(n), "blue": np.zeros(n, np.uint8), "nz": np.zeros(n, np.float32),
             "red": np.zeros(n, np.uint8), "alpha": np.zeros(n, np.uint8), "nx": np.zeros(n, np.float32),
             "green": np.zeros(n, np.uint8), "ny": np.zeros(n, np.float32), "a": np.zeros(n, np.int16)}
    props = [line.split()[-1] for line in _ply_header(write_points(tmp_path / "o.ply", pts, attrs)) if line.startswith("property")]
    assert props == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha", "zeta", "a"]


def test_ply_uchar_colour_by_default_16_on_request(tmp_path, shared_data):
    scan = read_scan(shared_data / "simple.las")  # 8-bit values in 16-bit fields
    head = _ply_header(write_scan(tmp_path / "d.ply", scan))
    assert "property uchar red" in head and "property uchar blue" in head
    back = read_scan(tmp_path / "d.ply")
    np.testing.assert_array_equal(back.attributes["red"], scan.attributes["red"])
    head16 = _ply_header(write_points(tmp_path / "e.ply", scan.points, scan.attributes, colour_depth=16))
    assert "property ushort red" in head16


def test_ply_16bit_colours_above_255_divided_with_a_note(tmp_path):
    pts = np.zeros((3, 3))
    with collect_notes() as notes:
        out = write_points(tmp_path / "c.ply", pts, {"red": np.array([0, 257 * 100, 65535], np.uint16)})
    np.testing.assert_array_equal(read_scan(out).attributes["red"], [0, 100, 255])
    assert notes == [f"{out}: red: 16-bit values divided by 257 to uchar (use colour depth 16 to keep them)"]


def test_ply_crs_comment(tmp_path):
    out = write_points(tmp_path / "k.ply", np.zeros((2, 3)), crs=WKT_UTM33)
    assert f"comment crs {WKT_UTM33}" in _ply_header(out)
    assert read_scan(out).metadata["crs_wkt"] == WKT_UTM33


def test_ply_crs_with_non_ascii_text(tmp_path):
    wkt = WKT_UTM33.replace('UNIT["metre",1]]', 'UNIT["metre",1],REMARK["12°E to 18°E"]]')
    out = write_points(tmp_path / "k.ply", np.zeros((2, 3)), metadata={"crs_wkt": wkt})
    assert read_scan(out).metadata["crs_wkt"] == wkt


# ---------------------------------------------------------------------------------------- CSV

def test_csv_starts_with_the_header_and_reads_with_numpy(tmp_path):
    """Before: a '# dtypes:' line came first, which numpy and pandas take as the header."""
    pts = np.array([[0.1, 0.2, 0.3], [1.5, 2.5, 3.5]], dtype=np.float32).astype(np.float64)
    attrs = {"intensity": np.array([0.1, 0.7], np.float32), "red": np.array([1, 255], np.uint8)}
    out = write_points(tmp_path / "p.csv", pts, attrs, metadata={"vertex_properties": {"x": "f4"}})
    lines = out.read_text().splitlines()
    assert lines == ["x,y,z,intensity,red", "0.1,0.2,0.3,0.1,1", "1.5,2.5,3.5,0.7,255"]
    table = np.genfromtxt(out, delimiter=",", names=True)
    assert table.dtype.names == ("x", "y", "z", "intensity", "red")
    np.testing.assert_array_equal(table["intensity"].astype(np.float32), attrs["intensity"])


def test_csv_float64_exact(tmp_path):
    pts = np.array([[0.1 + 2e-17, 1 / 3, 637012.2400000001]])
    back = read_scan(write_points(tmp_path / "d.csv", pts))
    np.testing.assert_array_equal(back.points, pts)


def test_csv_crs_sidecar(tmp_path):
    out = write_points(tmp_path / "s.csv", np.zeros((2, 3)), crs=WKT_UTM33)
    assert (tmp_path / "s.csv.prj").read_text() == WKT_UTM33 + "\n"
    assert read_scan(out).metadata["crs_wkt"] == WKT_UTM33
    write_points(tmp_path / "s.csv", np.zeros((2, 3)))  # replaced by a file without CRS
    assert not (tmp_path / "s.csv.prj").exists()
    assert read_scan(out).metadata["crs_wkt"] is None


def test_decimal_coordinates_keep_their_grid(tmp_path):
    """Coordinates with fixed decimals (text scans, E57 scaled integers) are written at that scale,
    so they come back up to float64 rounding, and no quantisation is reported."""
    g = np.random.default_rng(4)
    pts = np.round(g.random((500, 3)) * [1000, 1000, 50] + [5e5, 4e6, 0], 3)
    with collect_notes() as notes:
        out = write_points(tmp_path / "d.laz", pts)
    hdr = laspy.read(str(out)).header
    np.testing.assert_array_equal(hdr.scales, [0.001] * 3)
    assert notes == []
    back = read_scan(out).points
    assert np.abs(back - pts).max() <= 4 * np.finfo(float).eps * 4e6
    np.testing.assert_array_equal(np.round(back, 3), pts)


def test_las_layout_to_another_point_format(shared_data, tmp_path):
    """COPC needs LAS 1.4 with point format 6-8: a LAS 1.2 format 3 source maps onto 7 losslessly."""
    from lodbuilder.io.las import las_layout

    scan = read_scan(shared_data / "simple.las", crs=WKT_UTM33)
    lay = las_layout(scan.points, scan.attributes, scan.metadata, point_format=7, version="1.4")
    assert (lay.point_format, lay.version, lay.wkt_bit, lay.write_wkt_vlr) == (7, "1.4", True, True)
    assert [d.name for d in lay.extra_dims] == ["scan_angle_rank"]
    # format 7's scan_angle (0.006-degree units) holds format 3's scan_angle_rank (degrees) for
    # viewers; before, it was left 0 (the exact degrees stay in the extra bytes)
    assert lay.notes == [
        "scan_angle: filled from scan_angle_rank (degrees to 0.006-degree units, rounded); "
        "scan_angle_rank keeps its exact values in extra bytes"
    ]
    rank = scan.attributes["scan_angle_rank"]
    assert rank.min() == -19 and rank.max() == 18
    want = np.rint(rank.astype(np.float64) / 0.006).astype(np.int16)
    out = tmp_path / "c.las"
    lay.las_data(scan.points).write(str(out))
    las = laspy.read(str(out))
    np.testing.assert_array_equal(np.asarray(las["scan_angle"]), want)
    assert np.abs(want * 0.006 - rank).max() <= 0.003
    back = read_scan(out)
    assert back.metadata["las_point_format"] == 7 and back.metadata["crs_wkt"] == WKT_UTM33
    np.testing.assert_array_equal(back.points, scan.points)
    for k, v in scan.attributes.items():
        np.testing.assert_array_equal(back.attributes[k], v, err_msg=k)
    np.testing.assert_array_equal(back.attributes["scan_angle"], want)
    # written again (format 7 kept), both fields come back as they are: no note, nothing lost
    again = las_layout(back.points, back.attributes, back.metadata)
    assert again.point_format == 7 and again.notes == []
    np.testing.assert_array_equal(again.dimensions["scan_angle"], want)


def test_scan_angle_to_an_older_point_format():
    """The other way (6-10 -> 0-5): scan_angle_rank gets the whole degrees, clipped to int8."""
    from lodbuilder.io.las import las_layout

    angle = np.array([0, 1, -2, 15000, -30000, 30000], dtype=np.int16)
    lay = las_layout(np.zeros((6, 3)), {"scan_angle": angle}, point_format=1, version="1.2")
    np.testing.assert_array_equal(lay.dimensions["scan_angle_rank"], [0, 0, -0, 90, -128, 127])
    assert [d.name for d in lay.extra_dims] == ["scan_angle"]
    assert lay.notes == [
        "scan_angle_rank: filled from scan_angle (0.006-degree units to degrees, rounded; 2 "
        "value(s) clipped to [-128, 127]); scan_angle keeps its exact values in extra bytes"
    ]


def test_vector_attribute_flattened_with_a_note(tmp_path):
    pts = np.zeros((4, 3))
    for fmt in ("ply", "csv"):
        with collect_notes() as notes:
            out = write_points(tmp_path / f"v.{fmt}", pts, {"normal": np.ones((4, 3), np.float32)})
        assert notes == [f"{out}: normal: 3 values per point written as normal_0 .. normal_2"]
        assert {"normal_0", "normal_1", "normal_2"} <= set(read_scan(out).attributes)
