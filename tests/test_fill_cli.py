"""``slice --fill`` and ``evaluate --gaps`` (issue 14)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from clirun import run
from surfaces import jittered_plane

import lodbuilder
from lodbuilder.archive.writer import ScanRecord, update_archive
from lodbuilder.io import read_scan, write_points
from lodbuilder.io.base import Scan

RHO = 0.04
HOLES = [((0.3, 0.35), 4.0), ((0.7, 0.6), 3.5)]


@pytest.fixture(scope="module")
def arc(tmp_path_factory):
    rng = np.random.default_rng(3)
    pts = jittered_plane(20_000, rng)
    keep = np.ones(len(pts), dtype=bool)
    for c, r in HOLES:
        keep &= np.hypot(pts[:, 0] - c[0], pts[:, 1] - c[1]) > r * RHO
    pts = pts[keep]
    attrs = {
        "red": np.round(255 * pts[:, 0]).astype(np.uint8),
        "green": np.full(len(pts), 7, np.uint8),
        "blue": np.round(255 * pts[:, 1]).astype(np.uint8),
    }
    scan = Scan(points=pts, attributes=attrs, name="p")
    path = tmp_path_factory.mktemp("fillcli") / "p.h5"
    update_archive(path, [ScanRecord(scan, lodbuilder.fastfps(pts))])
    return path




def test_slice_fill(arc, tmp_path, capsys):
    out = tmp_path / "f.ply"
    rc, text, err = run(capsys, "slice", arc, "--rho", RHO, "--fill", "-o", out)
    assert rc == 0, err
    with lodbuilder.open_archive(arc) as a:
        view = a.scan()
        lev = view.level(rho=RHO)
        n = view.n_points
    back = read_scan(out)
    flag = back.attributes["synthetic"]
    k = lev.size
    m = int(flag.sum())
    assert m > 10 and back.points.shape[0] == k + m
    assert (flag[:k] == 0).all() and (flag[k:] == 1).all()
    assert text.strip() == (
        f"wrote {k:,} of {n:,} points + {m:,} synthetic (synthetic = 1) in 2 filled gap(s) of scan "
        f"'p' to {out} (covering radius <= {lev.rho:.6g})"
    )
    # the measured points are the plain level's, in the same order, with the same attributes
    plain = tmp_path / "plain.ply"
    assert run(capsys, "slice", arc, "--rho", RHO, "-o", plain)[0] == 0
    ref = read_scan(plain)
    np.testing.assert_array_equal(back.points[:k], ref.points)
    for name in ("red", "green", "blue"):
        np.testing.assert_array_equal(back.attributes[name][:k], ref.attributes[name])
    assert (back.attributes["green"][k:] == 7).all()


def test_slice_fill_extra_columns(arc, tmp_path, capsys):
    out = tmp_path / "f.npz"
    assert run(capsys, "slice", arc, "--rho", RHO, "--fill", "--extra", "-o", out)[0] == 0
    z = np.load(out)
    syn = z["synthetic"] == 1
    assert (z["source_index"][syn] == -1).all() and (z["rank"][syn] == -1).all()
    assert (z["source_index"][~syn] >= 0).all()


def test_slice_without_fill_is_unchanged(arc, tmp_path, capsys):
    """Without --fill the output is byte for byte what the level API writes."""
    out = tmp_path / "plain.ply"
    assert run(capsys, "slice", arc, "--rho", RHO, "-o", out)[0] == 0
    with lodbuilder.open_archive(arc) as a:
        view = a.scan()
        lev = view.level(rho=RHO)
        ref = write_points(
            tmp_path / "ref.ply", lev.points, lev.attributes, metadata=view.format_metadata
        )
    assert out.read_bytes() == ref.read_bytes()
    assert "synthetic" not in read_scan(out).attributes


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--size", "100", "--fill"], "--fill needs --rho R (the density the filled level meets)"),
        (
            [
                "--rho",
                str(RHO),
                "--fill",
                "--box",
                "0",
                "0",
                "0",
                "1",
                "1",
                "1",
                "--box-rho",
                "0.01",
            ],
            "--fill fills the plain --rho level of the uniform ordering; leave out --box, "
            "--viewpoint and --ordering",
        ),
        (
            ["--rho", str(RHO), "--fill", "1"],
            "max_hole (the widest hole filled, in units of rho) must be a number > 1, got 1.0",
        ),
    ],
)
def test_slice_fill_errors(arc, tmp_path, capsys, extra, message):
    out = tmp_path / "x.ply"
    rc, _, err = run(capsys, "slice", arc, *extra, "-o", out)
    assert rc == 2
    assert err.strip() == f"lodbuilder slice: error: {message}"
    assert not out.exists()


def test_evaluate_gaps(arc, tmp_path, capsys):
    out = tmp_path / "q.json"
    rc, text, err = run(capsys, "evaluate", arc, "--rhos", RHO, "--gaps", "--json", out)
    assert rc == 0, err
    assert f"scan 'p': 2 gap(s) at rho {RHO:g}" in text
    doc = json.loads(out.read_text())
    (gaps,) = doc["gaps"]
    assert gaps["rho"] == RHO and gaps["n_gaps"] == 2 and gaps["n_fillable"] == 2
    assert gaps["sample_rho"] == 0.0  # evaluate measures against every input point
    for g, (c, r) in zip(
        sorted(gaps["gaps"], key=lambda g: g["bounds_min"][0]), HOLES, strict=True
    ):
        assert g["bounds_min"][0] < c[0] < g["bounds_max"][0]
        assert g["bounds_min"][1] < c[1] < g["bounds_max"][1]
        assert g["area"] == pytest.approx(np.pi * ((r - 1) * RHO) ** 2, rel=0.15)


def test_evaluate_gaps_needs_rhos(arc, capsys):
    rc, _, err = run(capsys, "evaluate", arc, "--gaps")
    assert rc == 2
    assert err.strip() == (
        "lodbuilder evaluate: error: --gaps needs --rhos R [R ...] (the densities whose gaps are "
        "listed)"
    )


def test_gap_colours(arc):
    from lodbuilder.viewer.data import GAP_COLOURS
    from lodbuilder.viewer.source import load_view_data

    data = load_view_data(arc)
    k = data.size_for_rho(RHO)
    col = data.colours("gaps", k)
    red = (col == GAP_COLOURS[1]).all(axis=1)
    assert (red | (col == GAP_COLOURS[0]).all(axis=1)).all()
    # red: the points around the two holes (within 1.5 rho of their far part), nothing else
    d = np.min([np.hypot(*(data.points[:, :2] - c).T) - r * RHO for c, r in HOLES], axis=0)
    assert red.sum() > 100
    assert d[red].max() <= 1.6 * RHO
    assert not red[d > 1.6 * RHO].any()
    # the far part (beyond rho) is sampled by grid nodes rho/4 apart: its outermost node is within
    # 0.18 rho of its edge, so every point within 1.5 - 1 - 0.18 rho of the hole's edge is red
    assert red[d < 0.3 * RHO].all()
    # a level too coarse for any gap: all grey
    assert (data.colours("gaps", 20) == GAP_COLOURS[0]).all()


@pytest.mark.viewer
def test_view_colour_gaps_screenshot(arc, tmp_path, capsys):
    out = tmp_path / "g.png"
    rc, text, err = run(
        capsys,
        "view",
        arc,
        "--rho",
        RHO,
        "--colour",
        "gaps",
        "--screenshot",
        out,
        "--window-size",
        400,
        300,
    )
    assert rc == 0, err
    assert "colour gaps" in text
    import imageio.v3 as iio

    img = iio.imread(out)
    reds = (img[..., 0] > 180) & (img[..., 1] < 80) & (img[..., 2] < 80)
    assert reds.sum() > 50
