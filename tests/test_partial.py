"""Partial builds (``--size N`` / ``--rho R``) store and report where their ordering stops
(issue 20, finding 3 of reliability-3)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from clirun import run as run_cli
from scipy.spatial import cKDTree

import lodbuilder
from lodbuilder.archive import layout as L
from lodbuilder.cli.main import main
from lodbuilder.errors import LevelBeyondOrderingError
from lodbuilder.io import read_scan
from lodbuilder.sampling.fastfps import euclidean_fps, fastfps


def cover(all_pts, kept):
    return float(cKDTree(kept).query(all_pts)[0].max())


@pytest.fixture(scope="module")
def res3(shared_data):
    return read_scan(shared_data / "bun_zipper_res3.ply")


@pytest.mark.parametrize("how", [{"size": 150}, {"rho": 0.01}])
def test_engine_stop_radius_bounds_the_covering_radius(res3, how):
    """The stop radius is >= the true covering radius of the whole partial ordering and <= its
    last radius; a full ordering stops at 0."""
    pts = res3.points
    o = fastfps(pts, **how)
    assert len(o) < len(pts)
    true = cover(pts, pts[o.order])
    assert true <= o.stop_radius <= o.radius[-1]
    assert o.stop_radius > 0
    if "rho" in how:
        assert o.stop_radius <= how["rho"]
    assert fastfps(pts).stop_radius == 0.0


def test_euclidean_stop_radius_is_exact(res3):
    pts = res3.points[:400]
    o = euclidean_fps(pts, size=37)
    assert o.stop_radius == pytest.approx(cover(pts, pts[o.order]), rel=1e-12)
    full = euclidean_fps(pts)
    assert o.stop_radius == full.radius[37]


@pytest.fixture(scope="module")
def partial(tmp_path_factory, shared_data):
    d = tmp_path_factory.mktemp("partial")
    arc = d / "sz.h5"
    rc = main(["build", str(shared_data / "bun_zipper_res3.ply"), "-o", str(arc), "--size", "150",
               "--no-progress"])
    assert rc == 0
    return arc


def test_archive_stores_the_stop_radius(partial, res3):
    with lodbuilder.open_archive(partial) as arc:
        scan = arc.scan()
        assert scan.n_ordered == 150
        stop = scan.stop_radius
        level = scan.level(size=150)
        assert level.rho == stop
        assert cover(res3.points, level.points) <= stop
        assert scan.level(rho=stop).size <= 150
    with h5py.File(partial, "r") as f:
        assert f["scans/bun_zipper_res3"].attrs[L.S_STOP_RADIUS] == stop


def test_build_line_says_how_many_points_were_ordered(tmp_path, capsys, shared_data):
    rc, out, err = run_cli(capsys, "build", shared_data / "bun_zipper_res3.ply", "-o", tmp_path / "a.h5",
                           "--size", "150", "--no-progress")
    assert rc == 0
    assert "ordered 150 of 1,889 points" in out
    rc, out, err = run_cli(capsys, "build", shared_data / "bun_zipper_res3.ply", "-o", tmp_path / "b.h5",
                           "--no-progress")
    assert "ordered" not in out


def test_finer_level_is_refused_with_the_rebuild(partial, tmp_path, capsys):
    with lodbuilder.open_archive(partial) as arc:
        stop = arc.scan().stop_radius
    rc, out, err = run_cli(capsys, "slice", partial, "--rho", "0.001", "-o", tmp_path / "x.ply")
    assert rc != 0 and not (tmp_path / "x.ply").exists()
    assert err.strip() == (
        f"lodbuilder slice: error: scan 'bun_zipper_res3' is ordered only down to covering radius "
        f"{stop:.4g} (150 of 1,889 points: a partial build), so no level covers within rho=0.001; "
        "rebuild it without --size to order every point: lodbuilder build SOURCE -o ARCHIVE --force"
    )
    with lodbuilder.open_archive(partial) as arc, pytest.raises(
        LevelBeyondOrderingError, match="no level holds 151 points; rebuild it with --size 151 or without --size"
    ):
        arc.scan().level(size=151)


def test_slice_info_evaluate_report_the_stop_radius(partial, tmp_path, capsys, res3):
    with lodbuilder.open_archive(partial) as arc:
        stop = arc.scan().stop_radius
    rc, out, err = run_cli(capsys, "slice", partial, "--size", "150", "-o", tmp_path / "x.ply", "--json")
    doc = json.loads(out)
    assert doc["rho"] == stop > 0
    rc, out, err = run_cli(capsys, "info", partial)
    assert (f"stops at   covering radius {stop:.4g}: the ordering holds 150 of 1,889 points "
            "(a partial build); no level is finer") in out
    rc, out, err = run_cli(capsys, "info", partial, "--json")
    assert json.loads(out)["scans"][0]["stop_radius"] == stop
    rc, out, err = run_cli(capsys, "evaluate", partial, "--json", tmp_path / "e.json")
    assert rc == 0, err  # every level meets its claim, the whole ordering included
    levels = json.loads((tmp_path / "e.json").read_text())["levels"]
    last = max(levels, key=lambda r: r["size"])
    assert last["size"] == 150 and last["rho"] == stop


def test_viewer_data_knows_the_stop(partial):
    from lodbuilder.viewer.source import view_data_from_scan

    with lodbuilder.open_archive(partial) as arc:
        scan = arc.scan()
        data = view_data_from_scan(scan)
        assert data.rho_for_size(len(data)) == scan.stop_radius
        assert data.rho_for_size(150) == scan.stop_radius


def test_old_archive_without_the_attribute(partial, tmp_path):
    """An archive written before stop_radius: a partial one reads as 'no bound known' (inf)."""
    old = tmp_path / "old.h5"
    old.write_bytes(partial.read_bytes())
    with h5py.File(old, "r+") as f:
        del f["scans/bun_zipper_res3"].attrs[L.S_STOP_RADIUS]
    with lodbuilder.open_archive(old) as arc:
        assert arc.scan().stop_radius == np.inf
        assert arc.scan().level(size=150).rho == np.inf
