"""Joint orderings of registered collections (issue 10.4): the posed bunny scans ordered as one
surface through the tiled path, against the merged cloud ordered as one scan."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import lodbuilder
from lodbuilder.cli.main import main
from lodbuilder.collection import collection_level, expand_inputs
from lodbuilder.io import Scan, read_scan, write_points
from lodbuilder.io.pose import apply_pose

STEP = 4


@pytest.fixture(scope="module")
def bunny(tmp_path_factory, shared_data):
    """Every 4th point of the 10 bunny range scans beside a copy of bun.conf (same poses)."""
    d = tmp_path_factory.mktemp("jbunny")
    conf = (shared_data / "bun.conf").read_text()
    for line in conf.splitlines():
        tok = line.split()
        if tok and tok[0] == "bmesh":
            write_points(d / tok[1], read_scan(shared_data / tok[1]).points[::STEP])
    (d / "bun.conf").write_text(conf)
    srcs = expand_inputs([d / "bun.conf"])
    merged = [apply_pose(read_scan(s.path).points, s.pose) for s in srcs]
    return d / "bun.conf", srcs, merged


@pytest.mark.data
def test_joint_bunny_keeps_scan_ids_and_slices_per_scan(bunny, tmp_path, capsys):
    manifest, srcs, parts = bunny
    out = tmp_path / "joint.h5"
    res = lodbuilder.build_archive(manifest, out, joint=True, workers=2, _tile_points=25_000)
    (st,) = res.scans
    assert (st.name, st.status, st.method) == ("bun", "built", "tiled")
    merged = np.vstack(parts)
    assert st.n_points == len(merged)
    with lodbuilder.open_archive(out) as arc:
        v = arc.scan("bun")
        assert [m["name"] for m in v.build["joint"]["scans"]] == [s.name for s in srcs]
        assert v.build["tiled"]["tiles"] >= 3
        pts = v.points()
        a = v.attributes()
    # every point keeps its scan id and its index in its own scan
    for i, p in enumerate(parts):
        sel = a["scan_id"] == i
        assert sel.sum() == len(p)
        np.testing.assert_array_equal(pts[sel], p[a["scan_point"][sel]])
    tree = cKDTree(merged)
    lvl = collection_level(out, 0.004)
    assert cKDTree(lvl.points).query(merged)[0].max() <= 0.004
    assert lvl.scans == [s.name for s in srcs] and sum(lvl.sizes) == len(lvl)
    np.testing.assert_array_equal(np.bincount(lvl.scan_id, minlength=len(srcs)), lvl.sizes)
    assert tree.query(lvl.points)[0].max() == 0.0  # input points, not new ones
    # per-scan slicing: a member's points of the joint level
    chin = collection_level(out, 0.004, scans=["chin"])
    i = lvl.scans.index("chin")
    np.testing.assert_array_equal(chin.points, lvl.points[lvl.scan_id == i])
    assert chin.scans == ["chin"] and set(chin.scan_id.tolist()) == {0}
    # slice --all-scans on a joint archive: the joint level with its member ids
    ply = tmp_path / "all.ply"
    assert main(["slice", str(out), "--all-scans", "--rho", "0.004", "-o", str(ply)]) == 0
    got = read_scan(ply)
    np.testing.assert_array_equal(got.points, lvl.points)
    np.testing.assert_array_equal(got.attributes["scan_id"], lvl.scan_id)
    assert f"of {len(srcs)} scans at rho 0.004" in capsys.readouterr().out
    # one member of the joint scan through the CLI: --all-scans --scan MEMBER
    assert main(["slice", str(out), "--all-scans", "--scan", "chin", "--rho", "0.004", "-o", str(ply)]) == 0
    got = read_scan(ply)
    np.testing.assert_array_equal(got.points, chin.points)
    assert f"wrote {len(chin):,} points of 1 scans at rho 0.004" in capsys.readouterr().out


@pytest.mark.data
def test_joint_level_against_the_merged_cloud_ordered_as_one(shared_data, tmp_path):
    """The issue's figure: the 10 bunny scans at rho = 2 mm gave 29,565 points as separate scans
    against 8,776 for the merged cloud ordered as one scan; the joint ordering is within 1.1x there,
    and on average over the levels from 12 to 1.5 mm. Single levels of two valid orders differ more:
    a region left uncovered for a few hundred points moves one level's count by up to about 20 %
    (the joint order before the deeper head: 1.19 x at 12 mm, mean 1.044; after: 1.22 x at 4 mm,
    mean 1.040)."""
    out = tmp_path / "joint.h5"
    lodbuilder.build_archive(shared_data / "bun.conf", out, joint=True)
    srcs = expand_inputs([shared_data / "bun.conf"])
    merged = np.vstack([apply_pose(read_scan(s.path).points, s.pose) for s in srcs])
    one = tmp_path / "one.h5"
    lodbuilder.build_archive(Scan(points=merged, name="merged"), one)
    ratios = []
    for rho in [*np.geomspace(0.012, 0.0015, 12), 0.002]:
        lvl = collection_level(out, rho)
        with lodbuilder.open_archive(one) as arc:
            ref = arc.scan("merged").level(rho=rho)
        ratios.append(len(lvl) / ref.size)
        if rho == 0.002:  # (the level)
            assert len(lvl) <= 1.1 * ref.size, (rho, len(lvl), ref.size)
        assert cKDTree(lvl.points).query(merged)[0].max() <= rho
    assert np.mean(ratios) <= 1.1 and max(ratios) <= 1.3, np.round(ratios, 3)


@pytest.mark.data
def test_joint_build_resumes_and_skips(bunny, tmp_path):
    manifest, srcs, _ = bunny
    out = tmp_path / "j.h5"
    lodbuilder.build_archive(manifest, out, joint="site", workers=1, _tile_points=30_000)
    again = lodbuilder.build_archive(manifest, out, joint="site", workers=1, _tile_points=30_000)
    assert [(s.name, s.status) for s in again.scans] == [("site", "skipped")]
    with pytest.raises(lodbuilder.errors.InputError, match="a joint build orders every point"):
        lodbuilder.build_archive(manifest, out, joint=True, size=100)
