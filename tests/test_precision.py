"""Radii that cannot be promised are refused, the others are promised (issue 20, finding 2 of
reliability-3); ``validate`` checks the guarantee itself by brute force."""

from __future__ import annotations

import h5py
import numpy as np
import plyfile
import pytest
from clirun import run as run_cli
from scipy.spatial import cKDTree

from lodbuilder.archive import layout as L
from lodbuilder.archive.validate import validate_archive
from lodbuilder.cli.main import main
from lodbuilder.errors import PrecisionError
from lodbuilder.io import read_scan
from lodbuilder.sampling.fastfps import fastfps

OUTLIER = (
    "the points span {span} while most are too close to tell apart: float64 rounding at that spread "
    "may take all of their distances, so no radius can be promised; points far from the rest "
    "(outliers)? drop them (crop the scan to the part you need) and build again"
)
GRID = (
    "voxel_size={h} with band_radius={r} is far larger than the scan (extent 0.156): rounding in "
    "grid units may take {lost} the point distances, so no radius can be promised; use a voxel_size "
    "near the point spacing (leave --voxel-size and --band-radius out for the automatic one)"
)


def unit_cloud(n=3000, seed=0):
    pts = np.random.default_rng(seed).random((n, 3))
    pts[:, 2] *= 0.01
    return pts



def worst_shortfall(pts, o, sizes):
    """Largest (true covering radius - stored bound) over the prefixes of ``sizes``."""
    worst = -np.inf
    for k in sizes:
        true = cKDTree(pts[o.order[:k]]).query(pts)[0].max()
        worst = max(worst, true - o.radius[k])
    return worst


def test_float64_outlier_at_1e18_is_refused(tmp_path, capsys):
    pts = np.vstack([unit_cloud(), [[1e18, 0, 0]]])
    with pytest.raises(PrecisionError) as exc:
        fastfps(pts)
    assert str(exc.value) == OUTLIER.format(span="1e+18")
    np.save(tmp_path / "far.npy", pts)
    rc, out, err = run_cli(capsys, "build", tmp_path / "far.npy", "-o", tmp_path / "a.h5", "--no-progress")
    assert rc == 2 and not (tmp_path / "a.h5").exists()
    assert err == f"lodbuilder build: error: {OUTLIER.format(span='1e+18')}\n"


def test_float32_ply_outlier_at_1e20_is_refused(tmp_path, capsys):
    pts = np.vstack([unit_cloud(), [[1e20, 0, 0]]]).astype(np.float32)
    v = np.zeros(len(pts), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = pts.T
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(tmp_path / "far.ply"))
    rc, out, err = run_cli(capsys, "build", tmp_path / "far.ply", "-o", tmp_path / "a.h5", "--no-progress")
    assert rc == 2 and not (tmp_path / "a.h5").exists()
    assert err == f"lodbuilder build: error: {OUTLIER.format(span='1e+20')}\n"


@pytest.mark.parametrize(
    "option, value, h, r, lost",
    [
        ("--voxel-size", "1e16", "1e+16", "2.5e+16", "all of"),
        ("--band-radius", "1e30", "4e+29", "1e+30", "all of"),
        ("--voxel-size", "1e8", "1e+08", "2.5e+08", "0.00046 of"),
    ],
)
def test_grid_far_larger_than_the_scan_is_refused(tmp_path, capsys, shared_data, option, value, h, r, lost):
    rc, out, err = run_cli(capsys, "build", shared_data / "bun_zipper_res2.ply", "-o", tmp_path / "a.h5",
                           option, value, "--no-progress")
    assert rc == 2 and not (tmp_path / "a.h5").exists()
    assert err == f"lodbuilder build: error: {GRID.format(h=h, r=r, lost=lost)}\n"


@pytest.mark.parametrize("voxel_size", [None, 2.0, 4.8e5])
def test_accepted_radii_are_never_below_the_truth(shared_data, voxel_size):
    """A coarse grid the build still accepts (rounding of about 1e-5 of the radii at 4.8e5, which
    stored 5e-9 relative too little before): every checked prefix covers within its radius."""
    pts = read_scan(shared_data / "bun_zipper_res2.ply").points
    o = fastfps(pts, voxel_size=voxel_size)
    sizes = [1, 2, 5, 10, 30, 100, 300, 1000, 3000, len(pts) - 1]
    assert worst_shortfall(pts, o, sizes) <= 0.0


def test_outlier_advice_leads_to_a_clear_refusal():
    """An outlier at 1e16 needs a voxel too large for the grid's index; the advice names outliers,
    and following the voxel-size advice gives the precision refusal, not radii of 0."""
    pts = np.vstack([unit_cloud(), [[1e16, 0, 0]]])
    with pytest.raises(Exception, match=r"use a voxel_size of at least 4\.77e\+09, or drop points far from the rest"):
        fastfps(pts)
    with pytest.raises(PrecisionError, match="points far from the rest"):
        fastfps(pts, voxel_size=4.8e9)


@pytest.fixture(scope="module")
def built(res3_cli_archive):
    return res3_cli_archive


def test_validate_checks_the_covering_guarantee(built, tmp_path):
    assert validate_archive(built) == []
    bad = tmp_path / "lie.h5"
    bad.write_bytes(built.read_bytes())
    with h5py.File(bad, "r+") as f:
        g = f["scans/bun_zipper_res3"]
        r = g[L.D_RADIUS][:]
        r[10:] *= 0.5  # still non-increasing: only the brute-force check can see it
        g[L.D_RADIUS][:] = r
        g[L.D_RADIUS_INDEX][:] = r[:: int(g.attrs[L.S_RADIUS_STEP])]
    faults = validate_archive(bad)
    assert faults and all("the radii lie, rebuild the scan from its source" in x for x in faults)
    assert faults[0].startswith("scan 'bun_zipper_res3': the first 10 points claim to cover every point within ")


def test_validate_checks_a_partial_builds_stop_radius(tmp_path, shared_data):
    arc = tmp_path / "p.h5"
    assert main(["build", str(shared_data / "bun_zipper_res3.ply"), "-o", str(arc), "--size", "150",
                 "--no-progress"]) == 0
    assert validate_archive(arc) == []
    with h5py.File(arc, "r+") as f:
        f["scans/bun_zipper_res3"].attrs[L.S_STOP_RADIUS] *= 0.5
    faults = validate_archive(arc)
    assert len(faults) == 1 and faults[0].startswith("scan 'bun_zipper_res3': the first 150 points claim")
