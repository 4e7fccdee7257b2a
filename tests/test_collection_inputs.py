"""Collection inputs: files, directories, globs, manifests, poses, names."""

from __future__ import annotations

import numpy as np
import pytest

from lodbuilder.build.inputs import safe_name, unique_names
from lodbuilder.collection import expand_inputs, read_manifest
from lodbuilder.errors import InputError, ScanFileError
from lodbuilder.io import read_scan, write_points
from lodbuilder.io.pose import apply_pose, bmesh_pose, quaternion_matrix


def _touch_ply(path, n=5, seed=0):
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_points(path, rng.random((n, 3)))
    return path


def test_directories_globs_and_files(tmp_path):
    a = _touch_ply(tmp_path / "d" / "a.ply")
    b = _touch_ply(tmp_path / "d" / "sub" / "b.ply")
    _touch_ply(tmp_path / "d" / ".hidden" / "h.ply")
    (tmp_path / "d" / "notes.md").write_text("not a scan")
    c = _touch_ply(tmp_path / "e" / "a.ply")
    srcs = expand_inputs([tmp_path / "d", str(tmp_path / "e" / "*.ply")])
    assert [s.path for s in srcs] == [a, b, c]
    assert [s.name for s in srcs] == ["a", "b", "a_2"]
    assert all(s.pose is None for s in srcs)


def test_missing_and_empty_inputs(tmp_path):
    with pytest.raises(ScanFileError, match=r"nope\.ply: no such file or directory"):
        expand_inputs([tmp_path / "nope.ply"])
    with pytest.raises(InputError, match=r"matches no files"):
        expand_inputs([str(tmp_path / "*.ply")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=r"holds no scan files"):
        expand_inputs([tmp_path / "empty"])
    with pytest.raises(InputError, match=r"no input scans given"):
        expand_inputs([])


def test_safe_and_unique_names():
    assert safe_name("../etc/passwd") == "etc_passwd"
    assert safe_name("scan 01 (north)") == "scan_01_north"
    assert safe_name(".hidden") == "hidden"
    assert safe_name("///") == "scan"
    assert unique_names(["a", "a", "b", "a"]) == ["a", "a_2", "b", "a_3"]
    names = unique_names(["a", "a", "a_2"])
    assert len(set(names)) == 3


def test_manifest_matrix_lines(tmp_path):
    _touch_ply(tmp_path / "s" / "one.ply")
    _touch_ply(tmp_path / "s" / "two words.ply")
    m = tmp_path / "s" / "list.manifest"
    m.write_text(
        "# my scans\n\none.ply  1 0 0 10  0 1 0 20  0 0 1 30  0 0 0 1\n"
        "'two words.ply'   # no pose\ncamera 1 2 3 0 0 0 1\n"
    )
    srcs = expand_inputs([m])
    assert [s.name for s in srcs] == ["one", "two_words"]
    np.testing.assert_array_equal(srcs[0].pose[:3, 3], [10, 20, 30])
    assert srcs[1].pose is None
    p = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(apply_pose(p, srcs[0].pose), [[11, 22, 33]])


@pytest.mark.parametrize("line,msg", [
    ("a.ply 1 2 3", r"line 1: a pose is 16 numbers .* got 3"),
    ("a.ply " + " ".join(["1"] * 15) + " 2", r"line 1: the last row of the 4x4 pose must be 0 0 0 1"),
    ("bmesh a.ply 0 0 0 0 0 0", r"line 1: 'bmesh' needs FILE tx ty tz qx qy qz qw, got 7 fields"),
    ("bmesh a.ply 0 0 0 0 0 0 0", r"quaternion .* has zero or non-finite length"),
    ("a.ply 1 0 0 x 0 1 0 0 0 0 1 0 0 0 0 1", r"line 1: expected numbers after the file name"),
])
def test_manifest_errors(tmp_path, line, msg):
    m = tmp_path / "m.conf"
    m.write_text(line + "\n")
    with pytest.raises(InputError, match=msg):
        read_manifest(m)


def test_manifest_empty(tmp_path):
    m = tmp_path / "m.conf"
    m.write_text("# nothing\ncamera 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="lists no scans"):
        read_manifest(m)


def test_quaternion_matrix_is_a_rotation(rng):
    q = rng.normal(size=4)
    R = quaternion_matrix(*q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # a quarter turn about z: (x, y, z, w) = (0, 0, sin 45, cos 45)
    s = np.sqrt(0.5)
    np.testing.assert_allclose(quaternion_matrix(0, 0, s, s) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # bun.conf convention: world = p @ R + t
    pose = bmesh_pose([1, 2, 3], [0, 0, s, s])
    np.testing.assert_allclose(apply_pose(np.array([[1.0, 0, 0]]), pose), [[1, 1, 3]], atol=1e-12)


@pytest.mark.data
def test_bunny_scans_register_onto_zipper(shared_data):
    from scipy.spatial import cKDTree

    srcs = expand_inputs([shared_data / "bun.conf"])
    assert sorted(s.name for s in srcs) == ["bun000", "bun045", "bun090", "bun180", "bun270", "bun315",
                                            "chin", "ear_back", "top2", "top3"]
    tree = cKDTree(read_scan(shared_data / "bun_zipper.ply").points)
    wrong_far = 0
    for s in srcs:
        pts = read_scan(s.path).points
        med = float(np.median(tree.query(apply_pose(pts, s.pose))[0]))
        assert med < 0.6e-3, (s.name, med)
        # the other convention (R p + t) misplaces most scans: the test can tell them apart
        R, t = s.pose[:3, :3].T, s.pose[:3, 3]
        wrong = float(np.median(tree.query(pts @ R.T + t)[0]))
        wrong_far += wrong > 5e-3
    assert wrong_far >= 6


def test_multi_scan_e57_expands(tmp_path):
    import pye57

    path = tmp_path / "site.e57"
    e = pye57.E57(str(path), mode="w")
    rng = np.random.default_rng(0)
    for _ in range(2):
        p = rng.random((20, 3))
        e.write_scan_raw({"cartesianX": p[:, 0], "cartesianY": p[:, 1], "cartesianZ": p[:, 2]}, name="st 1")
    e.close()
    srcs = expand_inputs([path])
    assert [(s.name, s.scan_index) for s in srcs] == [("site-st_1", 0), ("site-st_1_2", 1)]
