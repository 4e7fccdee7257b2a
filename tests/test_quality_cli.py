"""``lodbuilder evaluate`` on real and doctored archives."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from lodbuilder.cli.main import main


@pytest.fixture(scope="module")
def res3_archive(shared_data, tmp_path_factory):
    import lodbuilder

    out = tmp_path_factory.mktemp("arc") / "res3.h5"
    lodbuilder.build_archive(shared_data / "bun_zipper_res3.ply", out, name="res3")
    return out


@pytest.fixture(scope="module")
def doctored_archive(tmp_path_factory):
    """An archive whose stored radii claim twice the density the points have."""
    from lodbuilder import euclidean_fps
    from lodbuilder.archive.writer import ScanRecord, update_archive
    from lodbuilder.io.base import Scan

    rng = np.random.default_rng(7)
    pts = rng.random((1500, 3)) * np.array([1.0, 1.0, 0.05])
    o = euclidean_fps(pts)
    bad = replace(o, radius=o.radius * 0.5)
    out = tmp_path_factory.mktemp("arc") / "doctored.h5"
    update_archive(out, [ScanRecord(scan=Scan(points=pts, name="liar"), ordering=bad)])
    return out


def test_evaluate_json_and_plot(res3_archive, tmp_path, capsys):
    js, png = tmp_path / "q.json", tmp_path / "q.png"
    rc = main(
        ["evaluate", str(res3_archive), "--sizes", "20", "200", "1889"]
        + ["--json", str(js), "--plot", str(png)]
    )
    assert rc == 0
    out = capsys.readouterr().out
    assert "scan 'res3': 1,889 points" in out and "wrote" in out
    doc = json.loads(js.read_text())
    assert doc["scan"] == "res3" and doc["n_points"] == 1889
    sizes = [lv["size"] for lv in doc["levels"]]
    assert sizes == [20, 200, 1889]
    for lv in doc["levels"]:
        assert lv["meets_rho"] is True
        assert lv["covering_radius"] <= lv["rho"] * (1 + 1e-9)  # equal up to float rounding
        assert lv["hausdorff_level_to_input"] == 0.0  # a level is a subset of the scan
    covers = [lv["covering_radius"] for lv in doc["levels"]]
    assert covers[0] > covers[1] > covers[2] == 0.0
    assert png.stat().st_size > 10_000


def test_evaluate_by_rho_and_mls_to_stdout(res3_archive, capsys):
    rc = main(
        ["evaluate", str(res3_archive), "--rhos", "0.02", "0.005", "--surface", "mls"]
        + ["--json", "-"]
    )
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    rhos = [lv["rho"] for lv in doc["levels"]]
    assert rhos[0] <= 0.02 and rhos[1] <= 0.005
    assert all(lv["surface_method"] == "mls" and lv["surface_k"] == 16 for lv in doc["levels"])


def test_evaluate_flags_archive_that_breaks_its_guarantee(doctored_archive, capsys):
    rc = main(["evaluate", str(doctored_archive), "--sizes", "10", "100", "500"])
    captured = capsys.readouterr()
    assert rc == 1
    assert "NO" in captured.out
    assert "3 level(s) violate their rho (sizes 10, 100, 500)" in captured.err


def test_evaluate_errors(res3_archive, tmp_path, capsys):
    arc = str(res3_archive)
    assert main(["evaluate", arc, "--plot", str(tmp_path / "q.pdf")]) == 2
    assert f"--plot {tmp_path / 'q.pdf'} must end in .png" in capsys.readouterr().err
    assert main(["evaluate", arc, "--sizes", "0"]) == 2
    assert (
        "size must be between 1 and the number of points (1889), got 0" in capsys.readouterr().err
    )
    assert main(["evaluate", arc, "--rhos", "-1"]) == 2
    assert "rho must be a finite number > 0, got -1" in capsys.readouterr().err
    assert main(["evaluate", arc, "--json", arc]) == 2
    assert f"--json {arc} is the input archive; choose another output" in capsys.readouterr().err
    assert main(["evaluate", arc, "--scan", "nope"]) == 2
    assert "has no scan 'nope'" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def weighted_archive(shared_data, tmp_path_factory):
    import lodbuilder

    out = tmp_path_factory.mktemp("arc") / "weighted.h5"
    lodbuilder.build_archive(shared_data / "bun_zipper_res3.ply", out, name="res3", adaptive=0.8)
    return out


def test_evaluate_extra_ordering(weighted_archive, capsys):
    rc = main(
        ["evaluate", str(weighted_archive), "--ordering", "weighted", "--fractions", "0.05", "0.2"]
        + ["--json", "-"]
    )
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ordering"] == "weighted"
    assert [lv["size"] for lv in doc["levels"]] == [94, 378]
    # weighted radii are not Euclidean covering radii: no rho claimed, nothing to violate
    assert all(lv["rho"] is None and lv["meets_rho"] is None for lv in doc["levels"])
    assert (
        main(["evaluate", str(weighted_archive), "--ordering", "weighted", "--rhos", "0.01"]) == 2
    )
    assert "its radii are not Euclidean" in capsys.readouterr().err
    assert main(["evaluate", str(weighted_archive), "--ordering", "nope"]) == 2
    assert "has no ordering 'nope'" in capsys.readouterr().err


def test_evaluate_default_levels(res3_archive, capsys):
    assert main(["evaluate", str(res3_archive), "--json", "-"]) == 0
    levels = json.loads(capsys.readouterr().out)["levels"]
    sizes = [lv["size"] for lv in levels]
    assert sizes == sorted(set(sizes)) and sizes[0] == 2 and sizes[-1] == 1889 and len(sizes) >= 8
    assert all(lv["meets_rho"] for lv in levels)
