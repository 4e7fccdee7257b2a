"""``lodbuilder build`` with several inputs, a manifest or collection options."""

from __future__ import annotations

import numpy as np
import pytest

from lodbuilder.cli.main import main
from lodbuilder.collection import list_scans
from lodbuilder.io import write_points


def _clouds(tmp_path, n=3):
    rng = np.random.default_rng(11)
    out = []
    for k in range(n):
        t = rng.random(600) * 2 * np.pi
        pts = np.stack([np.cos(t), np.sin(t), rng.random(600)], 1) + k
        out.append(write_points(tmp_path / f"s{k}.ply", pts))
    return out


def test_several_inputs_and_a_bad_one_exit_nonzero(tmp_path, capsys):
    files = _clouds(tmp_path)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(files[0].read_bytes()[:300])
    rc = main(["build", *map(str, files), str(bad), "-o", str(tmp_path / "c.h5"), "--workers", "2", "--no-progress"])
    out, err = capsys.readouterr()
    assert rc == 1
    assert "3 built, 1 failed scan(s) into" in out
    assert "bad: FAILED: " in err and "declares 600 vertices" in err
    assert [r["name"] for r in list_scans(tmp_path / "c.h5")] == ["s0", "s1", "s2"]
    rc = main(["build", str(tmp_path / "s*.ply"), "-o", str(tmp_path / "c.h5"), "--workers", "1", "--no-progress"])
    out, _ = capsys.readouterr()
    assert rc == 0 and "3 skipped scan(s)" in out


def test_manifest_and_directory_inputs(tmp_path, capsys):
    d = tmp_path / "scans"
    d.mkdir()
    _clouds(d, 2)
    m = tmp_path / "m.lst"
    m.write_text("scans/s0.ply 1 0 0 5 0 1 0 0 0 0 1 0 0 0 0 1\n")
    rc = main(["build", "--manifest", str(m), "-o", str(tmp_path / "m.h5"), "--workers", "1", "--size", "50"])
    assert rc == 0
    (row,) = list_scans(tmp_path / "m.h5")
    assert row["bounds_min"][0] > 3.5  # the pose moved it by +5 in x
    rc = main(["build", str(d), "-o", str(tmp_path / "d.h5"), "--workers", "1", "--size", "50"])
    assert rc == 0
    assert [r["name"] for r in list_scans(tmp_path / "d.h5")] == ["s0", "s1"]
    capsys.readouterr()


def test_single_scan_keeps_the_single_build(tmp_path, capsys):
    (f,) = _clouds(tmp_path, 1)
    rc = main(["build", str(f), "-o", str(tmp_path / "one.h5"), "--name", "ring", "--no-progress"])
    out, _ = capsys.readouterr()
    assert rc == 0 and "added scan 'ring'" in out


@pytest.mark.parametrize("argv,msg", [
    (["--name", "x"], "--name (name=) names a single scan, but the inputs hold 2 scans; a collection names each scan after its file"),
    (["--scheduler", "tcp://127.0.0.1:1", "--dask-local", "1"], "either a Dask scheduler address or dask_local"),
    (["--size", "0"], "size must be a whole number"),
])
def test_collection_option_errors(tmp_path, capsys, argv, msg):
    files = _clouds(tmp_path, 2)
    rc = main(["build", *map(str, files), "-o", str(tmp_path / "e.h5"), *argv])
    _, err = capsys.readouterr()
    assert rc == 2 and msg in err
    assert not (tmp_path / "e.h5").exists()


def test_no_input(tmp_path, capsys):
    assert main(["build", "-o", str(tmp_path / "e.h5")]) == 2
    assert "give INPUT files" in capsys.readouterr().err


def test_slice_all_scans_merged_with_scan_id(tmp_path, capsys):
    files = _clouds(tmp_path)
    arc = tmp_path / "c.h5"
    assert main(["build", *map(str, files), "-o", str(arc), "--workers", "1", "--no-progress"]) == 0
    out = tmp_path / "all.ply"
    assert main(["slice", str(arc), "--all-scans", "--rho", "0.2", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "of 3 scans at rho 0.2" in text and "0=s0, 1=s1, 2=s2" in text
    from lodbuilder.collection import collection_level
    from lodbuilder.io import read_scan

    got = read_scan(out)
    lvl = collection_level(arc, 0.2)
    np.testing.assert_array_equal(got.points, lvl.points)
    np.testing.assert_array_equal(got.attributes["scan_id"], np.repeat([0, 1, 2], lvl.sizes))
    assert "scan_id 1 = s1" in got.metadata["comments"]
    assert main(["slice", str(arc), "--all-scans", "--size", "5", "-o", str(out)]) == 2
    assert "--all-scans needs --rho" in capsys.readouterr().err


def _two_formats(tmp_path, crs=("EPSG:32610", "EPSG:32610")):
    """Two scans whose format metadata differ (a PLY with an attribute, an NPY), CRSs as given."""
    rng = np.random.default_rng(5)
    arc = tmp_path / "c.h5"
    for k, (suffix, c) in enumerate(zip(("ply", "npy"), crs, strict=True)):
        t = rng.random(600) * 2 * np.pi
        pts = np.stack([np.cos(t), np.sin(t), rng.random(600)], 1) + k
        f = write_points(tmp_path / f"s{k}.{suffix}", pts, {"intensity": rng.random(600).astype(np.float32)})
        argv = ["build", str(f), "-o", str(arc), "--no-progress"] + (["--crs", c] if c else [])
        assert main(argv) == 0
    return arc


def test_slice_all_scans_keeps_the_shared_crs_and_prints_changes_once(tmp_path, capsys):
    import json

    from lodbuilder import open_archive
    from lodbuilder.io import read_scan

    arc = _two_formats(tmp_path)
    with open_archive(arc) as a:
        assert a.scan("s0").format_metadata != a.scan("s1").format_metadata
        wkt = a.scan("s0").crs
    assert "UTM zone 10N" in wkt
    capsys.readouterr()
    out = tmp_path / "all.las"
    assert main(["slice", str(arc), "--all-scans", "--rho", "0.2", "-o", str(out)]) == 0
    text, err = capsys.readouterr()
    lines = [ln for ln in text.splitlines() if ln.startswith("  changed: ")]
    assert f"  changed: {out}: coordinates quantised to scale 0.001 (error <= 0.0005) with offset -1, -1, 0" in lines
    assert len(lines) == 2 and any("intensity: float32 values do not fit" in ln for ln in lines)
    assert "quantised" not in err and "intensity" not in err  # printed once, not logged too
    got = read_scan(out)
    assert "UTM zone 10N" in got.metadata["crs_wkt"]
    assert main(["slice", str(arc), "--all-scans", "--rho", "0.2", "-o", str(tmp_path / "all.ply"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["crs"] == wkt and doc["units"] == "metre" and doc["changes"] == []
    assert "UTM zone 10N" in read_scan(tmp_path / "all.ply").metadata["crs_wkt"]


def test_slice_all_scans_with_different_crs_says_so(tmp_path, capsys, monkeypatch):
    from lodbuilder.build import archive_crs
    from lodbuilder.io import read_scan

    # (a build refuses to mix scans with and without a CRS in one archive; archives built before
    # that check may hold both: made here with the check turned off)
    monkeypatch.setattr(archive_crs, "check_append_crs", lambda *a: None)
    arc = _two_formats(tmp_path, (None, "EPSG:32610"))
    capsys.readouterr()
    out = tmp_path / "all.ply"
    assert main(["slice", str(arc), "--all-scans", "--rho", "0.2", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert ("  changed: the scans have different coordinate reference systems (s0: none, "
            "s1: WGS 84 / UTM zone 10N); the output has none") in text.splitlines()
    assert not read_scan(out).metadata.get("crs_wkt")


@pytest.mark.dask
def test_dask_local_build_prints_no_dask_start_up_logs(tmp_path):
    import contextlib
    import os
    import socket
    import subprocess
    import sys
    from pathlib import Path

    files = _clouds(tmp_path, n=2)
    with contextlib.ExitStack() as stack:
        # Dask's default dashboard port taken (another build, a notebook): the build must not mind
        busy = stack.enter_context(socket.socket())
        with contextlib.suppress(OSError):
            busy.bind(("", 8787))
            busy.listen()
        res = subprocess.run([sys.executable, "-m", "lodbuilder.cli.main", "build", *map(str, files), "-o",
                              str(tmp_path / "d.h5"), "--dask-local", "1", "--no-progress"],
                             capture_output=True, text=True, timeout=300,
                             env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert res.returncode == 0, res.stderr
    assert [line for line in res.stderr.splitlines() if "distributed" in line] == []
    assert "on Dask LocalCluster (1 worker)" in res.stdout


def test_slice_all_scans_of_a_missing_scan_quotes_the_names(tmp_path, capsys):
    files = _clouds(tmp_path, n=2)
    arc = tmp_path / "two.h5"
    assert main(["build", *map(str, files), "-o", str(arc), "--no-progress", "-q"]) == 0
    capsys.readouterr()
    assert main(["slice", str(arc), "--all-scans", "--rho", "0.5", "--scan", "nope", "-o",
                 str(tmp_path / "x.ply")]) == 2
    assert capsys.readouterr().err == (f"lodbuilder slice: error: archive {arc} has no scan 'nope'; "
                                       "it holds 's0', 's1'\n")
