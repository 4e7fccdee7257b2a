"""CRS across the scans of one ordering (issue 20, finding 17 of reliability-3): a joint build
keeps the CRS its inputs share, refuses inputs in different CRSs or without one, and --to-crs
reprojects them with pyproj (checked against pyproj directly)."""

from __future__ import annotations

import numpy as np
import pytest
from clirun import run as run_cli

import lodbuilder
from lodbuilder.errors import InputError
from lodbuilder.io import read_scan, write_points

pyproj = pytest.importorskip("pyproj")

UTM10 = pyproj.CRS.from_epsg(32610)



@pytest.fixture(scope="module")
def autzen(shared_data):
    return read_scan(shared_data / "autzen_trim.laz")


@pytest.fixture
def halves(autzen, tmp_path):
    """Two tiles of autzen (every 4th point, split at the median x), as LAZ files with its CRS."""
    pts = autzen.points[::4]
    left = pts[:, 0] < np.median(pts[:, 0])
    wkt = autzen.metadata["crs_wkt"]
    a = write_points(tmp_path / "a.laz", pts[left], crs=wkt)
    b = write_points(tmp_path / "b.laz", pts[~left], crs=wkt)
    return a, b, pts[left], pts[~left], wkt


def test_joint_build_keeps_the_shared_crs(halves, tmp_path, capsys):
    a, b, _, _, wkt = halves
    rc, out, err = run_cli(capsys, "build", a, b, "--joint", "-o", tmp_path / "j.h5", "--no-progress")
    assert rc == 0, err
    with lodbuilder.open_archive(tmp_path / "j.h5") as arc:
        assert arc.scan().crs == wkt and arc.scan().units == "foot"
    rc, out, err = run_cli(capsys, "info", tmp_path / "j.h5")
    assert "crs        none" not in out and "units foot" in out


@pytest.mark.parametrize("joint", [["--joint"], []], ids=["joint", "collection"])
def test_scans_in_different_crss_are_refused_before_any_work(halves, tmp_path, capsys, joint):
    a, _, _, right, _ = halves
    utm = write_points(tmp_path / "u.laz", right, crs=UTM10.to_wkt("WKT1_GDAL"))
    rc, out, err = run_cli(capsys, "build", a, utm, *joint, "-o", tmp_path / "j.h5", "--no-progress")
    assert rc == 2 and not (tmp_path / "j.h5").exists() and not (tmp_path / "j.h5.scans").exists()
    assert err == (
        "lodbuilder build: error: scans 'a.laz' and 'u.laz' are in different CRSs "
        "(NAD_1983_HARN_Lambert_Conformal_Conic and WGS 84 / UTM zone 10N (EPSG:32610)); reproject them "
        "to one with --to-crs EPSG:XXXX (needs pyproj), or build them separately\n"
    )


@pytest.mark.parametrize("joint", [["--joint"], []], ids=["joint", "collection"])
def test_one_crs_written_two_ways_is_one_crs(halves, tmp_path, capsys, joint):
    """Tiles of one survey written by different software: autzen's WKT1 and the same CRS in ESRI
    WKT (pyproj reads it as EPSG:2994). They were refused as 'different CRSs' with advice to
    reproject (an identity transform, and float64 coordinates); now one CRS, the first tile's WKT,
    and a joint scan keeps the tiles' integer coordinates."""
    a, _, _, right, wkt = halves
    esri = pyproj.CRS.from_wkt(wkt).to_wkt("WKT1_ESRI")
    assert esri != wkt
    b = write_points(tmp_path / "esri.laz", right, crs=esri)
    rc, out, err = run_cli(capsys, "build", a, b, *joint, "-o", tmp_path / "j.h5", "--no-progress")
    assert rc == 0, err
    with lodbuilder.open_archive(tmp_path / "j.h5") as arc:
        crss = [arc.scan(n).crs for n in arc.scans]
        assert crss == ([wkt] if joint else [wkt, esri])
        if joint:
            assert arc.scan().encoding == "int32"


def test_a_scan_without_crs_among_scans_with_one(halves, tmp_path, capsys):
    a, _, _, right, wkt = halves
    bare = write_points(tmp_path / "bare.npy", right)
    rc, out, err = run_cli(capsys, "build", a, bare, "--joint", "-o", tmp_path / "j.h5", "--no-progress")
    assert rc == 2 and not (tmp_path / "j.h5").exists()
    assert err == (
        "lodbuilder build: error: scan 'bare.npy' has no CRS while 'a.laz' is in "
        "NAD_1983_HARN_Lambert_Conformal_Conic; give the scans without one a CRS with --crs EPSG:XXXX "
        "(or WKT), or build them separately\n"
    )
    prj = tmp_path / "autzen.prj"
    prj.write_text(wkt)
    rc, out, err = run_cli(capsys, "build", a, bare, "--joint", "--crs", prj, "-o", tmp_path / "j.h5",
                           "--no-progress")
    assert rc == 0, err
    with lodbuilder.open_archive(tmp_path / "j.h5") as arc:
        assert arc.scan().crs == wkt


def test_to_crs_reprojects_like_pyproj(halves, tmp_path, capsys):
    a, _, left, right, wkt = halves
    utm_wkt = UTM10.to_wkt("WKT1_GDAL")
    t = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(utm_wkt), pyproj.CRS.from_wkt(wkt), always_xy=True)
    x, y, z = t.transform(right[:, 0], right[:, 1], right[:, 2])
    utm = write_points(tmp_path / "u.npy", np.c_[x, y, z], crs=utm_wkt)  # the right half, in UTM metres
    rc, out, err = run_cli(capsys, "build", a, utm, "--joint", "--to-crs", "EPSG:32610", "-o", tmp_path / "j.h5",
                           "--no-progress")
    assert rc == 0, err
    back = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(wkt), UTM10, always_xy=True)
    with lodbuilder.open_archive(tmp_path / "j.h5") as arc:
        scan = arc.scan()
        assert scan.units == "metre" and scan.crs and "UTM zone 10N" in scan.crs
        pts = scan.points()
        sid = scan.attributes(None)["scan_id"]
        spt = scan.attributes(None)["scan_point"]
        prov = scan.provenance
    ex, ey, ez = back.transform(left[:, 0], left[:, 1], left[:, 2])
    want_left = np.c_[ex, ey, ez]
    np.testing.assert_allclose(pts[sid == 0][np.argsort(spt[sid == 0])], want_left, rtol=0, atol=1e-6)
    np.testing.assert_allclose(pts[sid == 1][np.argsort(spt[sid == 1])], np.c_[x, y, z], rtol=0, atol=1e-9)
    rec = prov["crs_reprojection"]
    assert rec[0]["from_units"] == "foot" and rec[0]["to_units"] == "metre"
    assert "UTM zone 10N" in rec[0]["to"] and rec[0]["transform"]
    assert "+proj=utm +zone=10" in rec[0]["pipeline"] or "unavailable" in rec[0]["pipeline"]


def test_to_crs_for_a_collection_of_scans(halves, tmp_path):
    a, b, left, _, wkt = halves
    lodbuilder.build_archive([a, b], tmp_path / "c.h5", to_crs="EPSG:32610", workers=1)
    t = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(wkt), UTM10, always_xy=True)
    with lodbuilder.open_archive(tmp_path / "c.h5") as arc:
        scan = arc.scan("a")
        assert scan.units == "metre"
        pts = scan.points()[np.argsort(scan.source_index[:])]
        assert scan.provenance["crs_reprojection"]["to"] == "WGS 84 / UTM zone 10N (EPSG:32610)"
    x, y, z = t.transform(left[:, 0], left[:, 1], left[:, 2])
    np.testing.assert_allclose(pts, np.c_[x, y, z], rtol=0, atol=1e-6)
    with pytest.raises(InputError, match="is not a CRS pyproj understands"):
        lodbuilder.build_archive(a, tmp_path / "d.h5", to_crs="EPSG:999999")


# ------------------------------------------------------------------ collections (issue 20, item 4)

def test_a_collection_scan_without_crs_needs_crs(halves, tmp_path, capsys):
    a, _, _, right, wkt = halves
    bare = write_points(tmp_path / "bare.npz", right)  # the CRS would be in the NPZ's metadata
    rc, out, err = run_cli(capsys, "build", a, bare, "-o", tmp_path / "c.h5", "--no-progress")
    assert rc == 2 and not (tmp_path / "c.h5").exists()
    assert err == (
        "lodbuilder build: error: scan 'bare.npz' has no CRS while 'a.laz' is in "
        "NAD_1983_HARN_Lambert_Conformal_Conic; give the scans without one a CRS with --crs EPSG:XXXX "
        "(or WKT), or build them separately\n"
    )
    prj = tmp_path / "autzen.prj"
    prj.write_text(wkt)
    rc, out, err = run_cli(capsys, "build", a, bare, "--crs", prj, "-o", tmp_path / "c.h5", "--no-progress")
    assert rc == 0, err
    with lodbuilder.open_archive(tmp_path / "c.h5") as arc:
        assert arc.scan("a").crs == wkt and arc.scan("bare").crs == wkt


def test_a_collection_keeps_a_shared_crs_and_scans_without_any(halves, tmp_path):
    a, b, left, right, wkt = halves
    lodbuilder.build_archive([a, b], tmp_path / "c.h5", workers=1)
    p = write_points(tmp_path / "p.ply", left)
    q = write_points(tmp_path / "q.npy", right)
    lodbuilder.build_archive([p, q], tmp_path / "d.h5", workers=1)
    with lodbuilder.open_archive(tmp_path / "c.h5") as c, lodbuilder.open_archive(tmp_path / "d.h5") as d:
        assert c.scan("a").crs == c.scan("b").crs == wkt
        assert d.scan("p").crs is None and d.scan("q").crs is None


def test_the_crs_a_file_declares_is_read_from_its_header(halves, tmp_path):
    from lodbuilder.io.stream import declared_crs

    a, _, left, _, wkt = halves
    assert declared_crs(a) == wkt
    for name in ("x.ply", "x.npz", "x.npy", "x.csv"):
        assert declared_crs(write_points(tmp_path / name, left[:50], crs=wkt)) == wkt, name
        assert declared_crs(write_points(tmp_path / ("bare_" + name), left[:50])) is None, name


# ------------------------------------------------------- scans added to an archive (issue 20, item 4)

def test_a_scan_added_in_another_crs_is_refused_naming_both(halves, tmp_path, capsys):
    a, _, _, right, wkt = halves
    arc = tmp_path / "c.h5"
    assert run_cli(capsys, "build", a, "-o", arc, "--no-progress")[0] == 0
    before = arc.read_bytes()
    utm = write_points(tmp_path / "u.laz", right, crs=UTM10.to_wkt("WKT1_GDAL"))
    rc, out, err = run_cli(capsys, "build", utm, "-o", arc, "--no-progress")
    assert rc == 2 and arc.read_bytes() == before
    assert err == (
        "lodbuilder build: error: scan 'u.laz' is in WGS 84 / UTM zone 10N (EPSG:32610) while the scans of "
        "archive 'c.h5' are in NAD_1983_HARN_Lambert_Conformal_Conic (scan 'a'); reproject it to theirs with "
        "--to-crs EPSG:XXXX or a WKT file of that CRS (needs pyproj), or build it into another archive\n"
    )
    bare = write_points(tmp_path / "bare.npy", right)
    rc, out, err = run_cli(capsys, "build", bare, "-o", arc, "--no-progress")
    assert rc == 2 and arc.read_bytes() == before
    assert err == (
        "lodbuilder build: error: scan 'bare.npy' has no CRS while the scans of archive 'c.h5' are in "
        "NAD_1983_HARN_Lambert_Conformal_Conic (scan 'a'); give it a CRS with --crs EPSG:XXXX (or WKT), or "
        "build it into another archive\n"
    )
    rc, out, err = run_cli(capsys, "build", utm, "-o", arc, "--to-crs", "EPSG:32611", "--no-progress")
    assert rc == 2 and arc.read_bytes() == before
    assert err == (
        "lodbuilder build: error: --to-crs would put the new scans in WGS 84 / UTM zone 11N (EPSG:32611), but "
        "the scans of archive 'c.h5' are in NAD_1983_HARN_Lambert_Conformal_Conic (scan 'a'); ask --to-crs for "
        "their CRS, or build the new scans into another archive\n"
    )
    # scan 'a' rebuilt (--overwrite) from a file in another CRS replaces the one that held the CRS
    (tmp_path / "sub").mkdir()
    same = write_points(tmp_path / "sub" / "a.laz", right, crs=UTM10.to_wkt("WKT1_GDAL"))
    rc, out, err = run_cli(capsys, "build", same, "-o", arc, "--overwrite", "--no-progress")
    assert rc == 0, err
    with lodbuilder.open_archive(arc) as c:
        assert c.scans == ["a"] and "UTM zone 10N" in c.scan("a").crs


def test_a_scan_in_a_crs_added_to_an_archive_without_one_is_refused(halves, tmp_path, capsys):
    a, _, left, right, wkt = halves
    arc = tmp_path / "d.h5"
    bare = write_points(tmp_path / "p.npy", left)
    assert run_cli(capsys, "build", bare, "-o", arc, "--no-progress")[0] == 0
    before = arc.read_bytes()
    for extra in ([], ["--to-crs", "EPSG:32610"]):
        rc, out, err = run_cli(capsys, "build", a, "-o", arc, *extra, "--no-progress")
        assert rc == 2 and arc.read_bytes() == before, err
    assert err == (
        "lodbuilder build: error: scan 'a.laz' is in WGS 84 / UTM zone 10N (EPSG:32610) while the scans of "
        "archive 'd.h5' have no CRS (scan 'p'); build it into another archive, or rebuild those scans with "
        "their CRS (--crs EPSG:XXXX --overwrite) first\n"
    )
    bare_too = write_points(tmp_path / "q.npy", right)  # another scan without a CRS: as before
    assert run_cli(capsys, "build", bare_too, "-o", arc, "--no-progress")[0] == 0
    # the archive's only scan rebuilt (--overwrite) in a CRS leaves no scan without one
    (tmp_path / "sub").mkdir()
    rc, out, err = run_cli(capsys, "build", write_points(tmp_path / "sub" / "p.laz", left, crs=wkt),
                           write_points(tmp_path / "sub" / "q.laz", right, crs=wkt), "-o", arc, "--overwrite",
                           "--no-progress")
    assert rc == 0, err
    with lodbuilder.open_archive(arc) as d:
        assert d.scans == ["p", "q"] and d.scan("p").crs == d.scan("q").crs == wkt


def test_a_scan_added_with_to_crs_or_crs_is_accepted(halves, tmp_path, capsys):
    a, b, _, right, wkt = halves
    arc = tmp_path / "c.h5"
    assert run_cli(capsys, "build", a, "-o", arc, "--no-progress")[0] == 0
    prj = tmp_path / "autzen.prj"
    prj.write_text(wkt)
    # the right half in UTM metres, reprojected back to the archive's CRS: pyproj's coordinates
    to_utm = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(wkt), UTM10, always_xy=True)
    x, y, z = to_utm.transform(right[:, 0], right[:, 1], right[:, 2])
    utm = write_points(tmp_path / "u.npy", np.c_[x, y, z], crs=UTM10.to_wkt("WKT1_GDAL"))
    rc, out, err = run_cli(capsys, "build", utm, "-o", arc, "--to-crs", prj, "--no-progress")
    assert rc == 0, err
    bare = write_points(tmp_path / "bare.npy", right)
    rc, out, err = run_cli(capsys, "build", bare, "-o", arc, "--crs", prj, "--no-progress")
    assert rc == 0, err
    rc, out, err = run_cli(capsys, "build", b, "-o", arc, "--no-progress")  # the same CRS: as before
    assert rc == 0, err
    back = pyproj.Transformer.from_crs(UTM10, pyproj.CRS.from_wkt(wkt), always_xy=True)
    with lodbuilder.open_archive(arc) as c:
        assert c.scans == ["a", "b", "bare", "u"]
        assert all(c.scan(n).crs == wkt for n in c.scans)
        u = c.scan("u")
        pts = u.points()[np.argsort(u.source_index[:])]
    wx, wy, wz = back.transform(np.asarray(x), np.asarray(y), np.asarray(z))
    np.testing.assert_allclose(pts, np.c_[wx, wy, wz], rtol=0, atol=1e-9)


def test_a_utm_archive_takes_autzen_reprojected_to_its_zone(halves, tmp_path, capsys):
    a, _, left, right, wkt = halves
    to_utm = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(wkt), UTM10, always_xy=True)
    x, y, z = to_utm.transform(right[:, 0], right[:, 1], right[:, 2])
    arc = tmp_path / "u.h5"
    utm = write_points(tmp_path / "u.npy", np.c_[x, y, z], crs=UTM10.to_wkt("WKT1_GDAL"))
    assert run_cli(capsys, "build", utm, "-o", arc, "--no-progress")[0] == 0
    rc, out, err = run_cli(capsys, "build", a, "-o", arc, "--no-progress")
    assert rc == 2 and "reproject it to theirs with --to-crs" in err
    rc, out, err = run_cli(capsys, "build", a, "-o", arc, "--to-crs", "EPSG:32610", "--no-progress")
    assert rc == 0, err
    with lodbuilder.open_archive(arc) as c:
        s = c.scan("a")
        assert s.units == "metre" and "UTM zone 10N" in s.crs
        pts = s.points()[np.argsort(s.source_index[:])]
    ex, ey, ez = to_utm.transform(left[:, 0], left[:, 1], left[:, 2])
    np.testing.assert_allclose(pts, np.c_[ex, ey, ez], rtol=0, atol=1e-6)


def test_a_tiled_joint_build_keeps_and_reprojects_the_crs(halves, tmp_path):
    """The out-of-core path (tiny tiles) of a joint build: the shared CRS kept, and --to-crs
    reprojecting both files like pyproj."""
    a, b, left, right, wkt = halves
    lodbuilder.build_archive([a, b], tmp_path / "k.h5", joint="k", _tile_points=3000)
    lodbuilder.build_archive([a, b], tmp_path / "u.h5", joint="u", _tile_points=3000, to_crs="EPSG:32610")
    t = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(wkt), UTM10, always_xy=True)
    with lodbuilder.open_archive(tmp_path / "k.h5") as k, lodbuilder.open_archive(tmp_path / "u.h5") as u:
        assert k.scan().build["method"] == u.scan().build["method"] == "tiled"
        assert k.scan().build["tiled"]["tiles"] > 1
        assert k.scan().crs == wkt and "UTM zone 10N" in u.scan().crs and u.scan().units == "metre"
        s = u.scan()
        pts, sid, spt = s.points(), s.attributes(None)["scan_id"], s.attributes(None)["scan_point"]
    for i, half in enumerate((left, right)):
        x, y, z = t.transform(half[:, 0], half[:, 1], half[:, 2])
        got = pts[sid == i][np.argsort(spt[sid == i])]
        np.testing.assert_allclose(got, np.c_[x, y, z], rtol=0, atol=1e-6)
