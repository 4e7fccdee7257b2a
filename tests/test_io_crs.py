"""CRS and units (issue 13.2): read, assign, store, show, carry through levels and writers."""

from __future__ import annotations

import builtins
import json

import numpy as np
import pytest
from clirun import run as run_cli

from lodbuilder.cli.main import main
from lodbuilder.errors import InputError, MissingDependencyError
from lodbuilder.io import crs as C
from lodbuilder.io import read_scan, write_points, write_scan

pytest.importorskip("laspy")
pyproj = pytest.importorskip("pyproj")

AUTZEN_WKT_START = 'PROJCS["NAD_1983_HARN_Lambert_Conformal_Conic",GEOGCS["GCS_North_American_1983_HARN"'




@pytest.fixture(scope="module")
def autzen_small(tmp_path_factory, shared_data):
    """2,000 points of autzen_trim.laz as a LAS file (its CRS and scale kept)."""
    scan = read_scan(shared_data / "autzen_trim.laz")
    keep = np.arange(0, len(scan), 55)
    d = tmp_path_factory.mktemp("crs")
    return write_points(d / "autzen_small.las", scan.points[keep], {k: v[keep] for k, v in scan.attributes.items()},
                        metadata=scan.metadata)


@pytest.fixture(scope="module")
def autzen_archive(autzen_small):
    out = autzen_small.with_name("autzen.h5")
    assert main(["build", str(autzen_small), "-o", str(out), "--no-progress"]) == 0
    return out


# ------------------------------------------------------------------------------------- reading

def test_las_crs_and_units(shared_data):
    m = read_scan(shared_data / "autzen_trim.laz").metadata
    assert m["crs_wkt"].startswith(AUTZEN_WKT_START) and m["crs_source"] == "file"
    assert m["crs_units"] == "foot"
    assert "\n" not in m["crs_wkt"] and "\x00" not in m["crs_wkt"]


def test_files_without_crs(shared_data):
    for name in ("simple.las", "bun_zipper_res4.ply", "bunnyDouble.e57"):
        m = read_scan(shared_data / name).metadata
        assert m["crs_wkt"] is None and "crs_units" not in m, name


def test_e57_coordinate_metadata(monkeypatch):
    class Root:
        def __getitem__(self, key):
            assert key == "coordinateMetadata"

            class Node:
                def value(self):
                    return "EPSG:32633"

            return Node()

    class E57:
        root = Root()

    from lodbuilder.io import e57

    wkt = e57._coordinate_metadata(E57(), "x.e57")
    assert wkt.startswith('PROJCS["WGS 84 / UTM zone 33N"') and C.linear_units(wkt) == "metre"


# ------------------------------------------------------------------------------------ assigning

def test_crs_from_user():
    assert C.crs_from_user("EPSG:2992").startswith('PROJCS["NAD83 / Oregon GIC Lambert (ft)"')
    wkt = pyproj.CRS("EPSG:4326").to_wkt(pretty=True)
    assert "\n" in wkt
    one = C.crs_from_user(wkt)
    assert "\n" not in one and pyproj.CRS(one) == pyproj.CRS(wkt)
    with pytest.raises(InputError, match=r"crs 'EPSG:99999999' is not a CRS pyproj understands \(.*\); give EPSG:XXXX or WKT text"):
        C.crs_from_user("EPSG:99999999")


def test_crs_from_a_file(tmp_path):
    (tmp_path / "c.prj").write_text(pyproj.CRS("EPSG:32633").to_wkt("WKT1_GDAL", pretty=True))
    assert C.crs_from_user(str(tmp_path / "c.prj")).startswith('PROJCS["WGS 84 / UTM zone 33N"')


def test_build_crs_assigns_and_refuses_to_override(capsys, tmp_path, shared_data, autzen_small):
    rc, out, err = run_cli(capsys, "build", shared_data / "simple.las", "-o", tmp_path / "s.h5", "--crs", "EPSG:2992",
                           "--no-progress")
    assert rc == 0, err
    rc, out, _ = run_cli(capsys, "info", tmp_path / "s.h5")
    assert "  crs        NAD83 / Oregon GIC Lambert (ft) (EPSG:2992), units foot\n" in out
    rc, out, err = run_cli(capsys, "build", autzen_small, "-o", tmp_path / "a.h5", "--crs", "EPSG:2992", "--no-progress")
    assert rc == 2 and not (tmp_path / "a.h5").exists()
    assert err == (f"lodbuilder build: error: {autzen_small} already has a CRS (NAD_1983_HARN_Lambert_Conformal_Conic); "
                   "--crs would replace it: pass --crs-override (crs_override=True) to replace it, or leave --crs out\n")
    rc, out, err = run_cli(capsys, "build", autzen_small, "-o", tmp_path / "a.h5", "--crs", "EPSG:2992",
                           "--crs-override", "--no-progress")
    assert rc == 0, err
    import lodbuilder

    with lodbuilder.open_archive(tmp_path / "a.h5") as arc:
        v = arc.scan()
        assert v.crs == C.crs_from_user("EPSG:2992") and v.units == "foot"
        lev = v.level(fraction=1.0)
        meta = v.format_metadata
    # the assigned CRS replaces the LAS 1.2 source's VLRs: GeoTIFF keys + WKT
    out = write_points(tmp_path / "o.las", lev, metadata=meta)
    import laspy

    hdr = laspy.read(str(out)).header
    assert hdr.parse_crs() == pyproj.CRS("EPSG:2992")
    assert read_scan(out).metadata["crs_wkt"] == lev.crs


def test_bad_crs_option(capsys, tmp_path, shared_data):
    rc, out, err = run_cli(capsys, "build", shared_data / "bun_zipper_res4.ply", "-o", tmp_path / "b.h5",
                           "--crs", "nonsense", "--no-progress")
    assert rc == 2 and err.startswith("lodbuilder build: error: crs 'nonsense' is not a CRS pyproj understands (")
    assert not (tmp_path / "b.h5").exists()


def test_crs_option_applies_to_every_scan_of_a_collection(capsys, tmp_path, shared_data):
    """One pipeline (issue 10.1): --crs gives every scan without a CRS of a collection its CRS."""
    pytest.importorskip("pyproj")
    import lodbuilder

    rc, out, err = run_cli(capsys, "build", shared_data / "bun_zipper_res4.ply", shared_data / "simple.las",
                           "-o", tmp_path / "c.h5", "--crs", "EPSG:2992", "--workers", "1")
    assert rc == 0, err
    with lodbuilder.open_archive(tmp_path / "c.h5") as arc:
        crs = {n: arc.scan(n).crs for n in arc.scans}
    assert set(crs) == {"bun_zipper_res4", "simple"} and len(set(crs.values())) == 1
    assert "2992" in next(iter(crs.values())) or "Oregon" in next(iter(crs.values()))


# ----------------------------------------------------------------------- archive, levels, CLI

def test_scanview_and_every_level_carry_the_crs(autzen_archive):
    import lodbuilder

    with lodbuilder.open_archive(autzen_archive) as arc:
        v = arc.scan()
        assert v.crs.startswith(AUTZEN_WKT_START) and v.units == "foot"
        lo, hi = v.bounds
        levels = [
            v.level(rho=50.0),
            v.level(size=10),
            v.level(fraction=0.5),
            v.refine_box(np.concatenate([lo, (lo + hi) / 2]), 10.0, 50.0),
            v.refine_viewpoint(lo, 5.0, 0.1),
        ]
        crs = v.crs
    for lev in levels:
        assert lev.crs == crs and lev.units == "foot"


def test_crs_of_a_closed_archive_is_an_error(autzen_archive):
    """Before: ScanView.crs and .units read after the archive was closed returned None."""
    import lodbuilder
    from lodbuilder.errors import ArchiveError

    with lodbuilder.open_archive(autzen_archive) as arc:
        v = arc.scan()
        assert v.crs.startswith(AUTZEN_WKT_START)
    for attr in ("crs", "units"):
        with pytest.raises(ArchiveError) as info:
            getattr(v, attr)
        assert str(info.value) == (
            f"archive {autzen_archive} is closed; read it inside `with open_archive(...)`"
        )


def test_write_points_takes_a_level(autzen_archive, tmp_path):
    import lodbuilder

    with lodbuilder.open_archive(autzen_archive) as arc:
        lev = arc.scan().level(size=100)
    for fmt in ("ply", "laz", "csv", "npy", "npz"):
        back = read_scan(write_points(tmp_path / f"l.{fmt}", lev))
        assert back.metadata["crs_wkt"] == lev.crs, fmt
        # without the source's LAS scale (metadata=view.format_metadata) LAS quantises from the spacing
        tol = back.metadata["las_scales"][0] / 2 * (1 + 1e-6) if fmt == "laz" else 0
        np.testing.assert_allclose(back.points, lev.points, rtol=0, atol=tol)


def test_info_json_and_text(autzen_archive, capsys):
    rc, out, _ = run_cli(capsys, "info", autzen_archive, "--json")
    s = json.loads(out)["scans"][0]
    assert s["crs"].startswith(AUTZEN_WKT_START) and s["units"] == "foot"
    assert s["crs_name"] == "NAD_1983_HARN_Lambert_Conformal_Conic" and s["crs_epsg"] is None
    rc, out, _ = run_cli(capsys, "info", autzen_archive)
    assert "  crs        NAD_1983_HARN_Lambert_Conformal_Conic, units foot\n" in out


def test_info_without_crs(capsys, tmp_path, shared_data):
    assert main(["build", str(shared_data / "bun_zipper_res4.ply"), "-o", str(tmp_path / "b.h5"), "--no-progress"]) == 0
    capsys.readouterr()
    rc, out, _ = run_cli(capsys, "info", tmp_path / "b.h5")
    assert "  crs        none (units unknown)\n" in out
    rc, out, _ = run_cli(capsys, "evaluate", tmp_path / "b.h5", "--sizes", "50")
    assert "scan 'bun_zipper_res4': 453 points, ordering uniform; distances in scan units (unit unknown)\n" in out


def test_evaluate_reports_the_unit(autzen_archive, capsys, tmp_path):
    rc, out, _ = run_cli(capsys, "evaluate", autzen_archive, "--sizes", "100", "--json", tmp_path / "e.json")
    assert "scan 'autzen_small': 2,000 points, ordering uniform; distances in foot\n" in out
    assert json.loads((tmp_path / "e.json").read_text())["units"] == "foot"


def test_slice_summary_lists_the_changes(autzen_archive, capsys, tmp_path):
    out_path = tmp_path / "s.ply"
    rc, out, _ = run_cli(capsys, "slice", autzen_archive, "--size", "100", "-o", out_path, "--colour-depth", "16")
    assert rc == 0 and "property ushort red" in out_path.read_bytes()[:2000].decode("ascii", "replace")
    rc, out, _ = run_cli(capsys, "slice", autzen_archive, "--size", "100", "-o", tmp_path / "s.csv")
    assert rc == 0 and "changed" not in out
    import lodbuilder

    assert (tmp_path / "s.csv.prj").read_text().startswith(AUTZEN_WKT_START)
    with lodbuilder.open_archive(autzen_archive) as arc:  # an LAS 1.2 level rewritten as PLY then LAS 1.4
        lev = arc.scan().level(size=100)
    ply = read_scan(write_points(tmp_path / "t.ply", lev))
    p = tmp_path / "t.laz"
    write_scan(p, ply)
    rc, out, _ = run_cli(capsys, "slice", autzen_archive, "--size", "100", "-o", tmp_path / "u.ply")
    assert rc == 0 and "changed" not in out  # 8-bit values in 16-bit fields: uchar without loss


# ------------------------------------------------------------------------------ without pyproj

def test_without_pyproj_units_are_unknown_never_guessed(monkeypatch, autzen_archive):
    real_import = builtins.__import__

    def no_pyproj(name, *args, **kwargs):
        if name == "pyproj" or name.startswith("pyproj."):
            raise ImportError("no pyproj")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_pyproj)
    wkt = C.crs_from_user('GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
                          'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]]')
    assert C.linear_units(wkt) is None and C.crs_name(wkt) is None
    with pytest.raises(MissingDependencyError, match=r"crs 'EPSG:2992': EPSG codes need pyproj; "
                                                     r"pip install 'lodbuilder\[crs\]', or pass the WKT text"):
        C.crs_from_user("EPSG:2992")
    import lodbuilder

    with lodbuilder.open_archive(autzen_archive) as arc:  # units stored at build time answer
        assert arc.scan().units == "foot"


def test_slice_with_a_crs_imports_no_pyproj(autzen_archive, tmp_path):
    """The CRS travels as WKT text: slicing (and writing it) needs no pyproj, numba or scipy.
    (laspy imports pyproj by itself when it is installed, so the check writes PLY.)"""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from lodbuilder.cli.main import main\n"
        f"rc = main(['slice', {str(autzen_archive)!r}, '--size', '50', '-o', {str(tmp_path / 'h.ply')!r}])\n"
        "print(rc, [m for m in ('pyproj', 'numba', 'scipy') if m in sys.modules])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "0 []"
    assert read_scan(tmp_path / "h.ply").metadata["crs_wkt"].startswith(AUTZEN_WKT_START)
