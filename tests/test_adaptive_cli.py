"""``lodbuilder build --importance/--adaptive/--density-floor/--outlier-threshold``,
``slice --ordering/--floor-rho`` and ``info`` listing maps and orderings."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lodbuilder.cli.main import main
from lodbuilder.io import read_scan, write_points


@pytest.fixture(scope="module")
def ply(tmp_path_factory):
    from test_adaptive import flat_and_curved

    pts, curved = flat_and_curved(half=30, r=4.0)
    pts[465, 2] += 5.0  # one point far off the surface (flat half)
    rgb = np.where(curved, 220, 20).astype(np.uint8)
    path = tmp_path_factory.mktemp("cli") / "halves.ply"
    write_points(path, pts, {"red": rgb, "green": rgb, "blue": rgb})
    return path, pts


def test_build_info_slice_with_features(ply, tmp_path, capsys):
    path, pts = ply
    arc = tmp_path / "a.h5"
    rc = main(
        [
            "build", str(path), "-o", str(arc), "--no-progress",
            "--importance", "curvature,colour", "--adaptive", "0.8",
            "--density-floor", "3", "--outlier-threshold", "20",
        ]
    )  # fmt: skip
    assert rc == 0
    capsys.readouterr()
    assert main(["info", str(arc), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)["scans"][0]
    assert info["importance"] == ["colour", "curvature", "noise"]
    assert info["orderings"] == ["uniform", "floor", "weighted"]
    assert info["n_points"] - info["n_ordered"] == 1
    assert info["build"]["outliers"]["count"] == 1
    assert main(["info", str(arc)]) == 0
    text = capsys.readouterr().out
    assert "importance colour, curvature, noise; orderings uniform, floor, weighted" in text

    out = tmp_path / "floor.ply"
    assert main(["slice", str(arc), "--ordering", "floor", "--size", "500", "-o", str(out)]) == 0
    assert "(covering radius <= 3 (the density floor); weighted radius" in capsys.readouterr().out
    assert main(["slice", str(arc), "--ordering", "weighted", "--size", "500", "-o", str(out)]) == 0
    assert "not a Euclidean covering radius" in capsys.readouterr().out
    assert main(["slice", str(arc), "--ordering", "floor", "--size", "500", "-o", str(out)]) == 0
    lvl = read_scan(out)
    assert len(lvl.points) == 500 and not lvl.attributes["outlier"].any()
    inliers = np.delete(pts, 465, axis=0)
    d, _ = cKDTree(lvl.points).query(inliers)
    assert d.max() <= 3.0

    out2 = tmp_path / "q.npz"
    rc = main(["slice", str(arc), "--floor-rho", "5", "--size", "300", "-o", str(out2)])
    assert rc == 0
    q = np.load(out2)
    assert q["points"].shape == (300, 3)
    d, _ = cKDTree(q["points"]).query(inliers)
    assert d.max() <= 5.0
    assert "wrote 300 of 1,800 points" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--adaptive", "1.5"], "adaptivity must be a number in \\[0, 1\\], got 1.5"),
        (["--importance", "curvature,wiggle"], "unknown importance map 'wiggle'"),
        (["--density-floor", "-1"], "--density-floor must be a finite number > 0, got -1"),
        (["--outlier-threshold", "nan"], "--outlier-threshold must be a finite number > 0"),
        (["--importance-k", "2"], "--importance-k \\(neighbours per point\\) must be a whole"),
        (["--combine", "max"], "--combine needs --adaptive or --density-floor"),
        (["--importance", "attr:gps_time"], "scan 'halves' has no attribute 'gps_time'"),
    ],
)
def test_build_bad_feature_options(ply, tmp_path, capsys, extra, message):
    path, _ = ply
    arc = tmp_path / "bad.h5"
    assert main(["build", str(path), "-o", str(arc), "--no-progress", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lodbuilder build: error: ")
    assert len(err.strip().splitlines()) == 1
    import re

    assert re.search(message, err)
    assert not arc.exists()  # no partial output


def test_slice_floor_rho_errors(ply, tmp_path, capsys):
    path, _ = ply
    arc = tmp_path / "w.h5"
    assert main(["build", str(path), "-o", str(arc), "--no-progress", "--adaptive", "1"]) == 0
    capsys.readouterr()
    out = tmp_path / "x.npy"
    assert main(["slice", str(arc), "--floor-rho", "3", "--fraction", "0.1", "-o", str(out)]) == 2
    assert "--floor-rho needs --size N" in capsys.readouterr().err
    assert main(["slice", str(arc), "--floor-rho", "0.5", "--size", "10", "-o", str(out)]) == 2
    assert "size 10 is too small for rho = 0.5" in capsys.readouterr().err
    rc = main(["slice", str(arc), "--floor-rho", "3", "--size", "900", "--ordering", "floor",
               "-o", str(out)])  # fmt: skip
    assert rc == 2
    assert "has no ordering 'floor'; it has 'uniform', 'weighted'" in capsys.readouterr().err
    assert not out.exists()
