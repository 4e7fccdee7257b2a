"""One export of a collection: ``export A.h5 --all-scans -o OUT.copc.laz | OUT.html`` merges
every scan's level at one rho (a joint scan counts as its members) into one file whose points
carry their scan (``scan_id``) and whose names the file holds; a joint scan's own export names
its members too."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lodbuilder.cli.main import main

laspy = pytest.importorskip("laspy")


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """Three synthetic sheets side by side, as PLY files."""
    from lodbuilder.datasets import demo_scan
    from lodbuilder.io import write_points

    root = tmp_path_factory.mktemp("scans")
    files = []
    for i in range(3):
        s = demo_scan(2500, seed=i)
        f = root / f"part{i}.ply"
        write_points(f, s.points + [i * 1.5, 0, 0], {"red": s.attributes["red"],
                                                     "green": s.attributes["green"],
                                                     "blue": s.attributes["blue"]})
        files.append(str(f))
    return files


@pytest.fixture(scope="module")
def collection(scans, tmp_path_factory):
    out = tmp_path_factory.mktemp("col") / "col.h5"
    assert main(["build", *scans, "-o", str(out), "-q"]) == 0
    return out


@pytest.fixture(scope="module")
def joint(scans, tmp_path_factory):
    out = tmp_path_factory.mktemp("joint") / "joint.h5"
    assert main(["build", *scans, "-o", str(out), "--joint", "site", "-q"]) == 0
    return out


def test_one_copc_of_a_collection(collection, tmp_path, capsys):
    import lodbuilder

    out = tmp_path / "all.copc.laz"
    assert main(["export", str(collection), "--all-scans", "--rho", "0.02", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    with lodbuilder.open_archive(collection) as arc:
        names = list(arc.scans)
        levels = [arc.scan(n).level(rho=0.02) for n in names]
    n = sum(lv.size for lv in levels)
    assert text.startswith(f"wrote {n:,} of 7,500 points of 3 scans to {out} (")
    assert "attribute scan_id: 0 part0, 1 part1, 2 part2)" in text
    las = laspy.read(str(out))
    (vlr,) = [v for v in las.header.evlrs if v.user_id == "lodbuilder"]
    doc = json.loads(vlr.record_data)
    assert doc["scans"] == names == ["part0", "part1", "part2"]
    sid = np.asarray(las["scan_id"])
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    from scipy.spatial import cKDTree

    step = float(np.max(las.header.scales))
    for i, lv in enumerate(levels):  # each scan's level under its own id (quantised to the step)
        mine = xyz[sid == i]
        assert mine.shape[0] == lv.size
        d, j = cKDTree(lv.points).query(mine)
        assert d.max() <= step and np.unique(j).size == lv.size
    # the depths are prefixes of the merged ordering: the coarsest depth holds every scan
    with laspy.CopcReader.open(str(out)) as reader:
        top = np.asarray(reader.query(level=0)["scan_id"])
        assert set(top.tolist()) == {0, 1, 2}


def test_one_web_page_of_a_collection_and_errors(collection, tmp_path, capsys):
    out = tmp_path / "all.html"
    assert main(["export", str(collection), "--all-scans", "-o", str(out), "-q"]) == 0
    text = out.read_text()
    start = text.index('<script id="lod-header" type="application/json">') + len(
        '<script id="lod-header" type="application/json">')
    header = json.loads(text[start:text.index("</script>", start)])
    (scan,) = [c for c in header["cats"] if c["label"] == "scan"]
    assert [row[1] for row in scan["table"]] == ["part0", "part1", "part2"]
    assert header["n"] == header["n_total"] == 7500
    cases = [
        (["--size", "10"], "--all-scans merges every scan at one --rho; leave out --size"),
        (["--class", "2"], "--all-scans merges every scan at one --rho; leave out a survey filter"),
    ]
    for extra, message in cases:
        assert main(["export", str(collection), "--all-scans", *extra, "-o", str(out)]) == 2
        assert capsys.readouterr().err == f"lodbuilder export: error: {message}\n"
    tiles = tmp_path / "tileset.json"
    assert main(["export", str(collection), "--all-scans", "-o", str(tiles)]) == 2
    assert "3D Tiles take one scan (--scan NAME)" in capsys.readouterr().err


def test_a_joint_scan_names_its_members(joint, tmp_path):
    out = tmp_path / "j.copc.laz"
    assert main(["export", str(joint), "-o", str(out), "-q"]) == 0
    las = laspy.read(str(out))
    (vlr,) = [v for v in las.header.evlrs if v.user_id == "lodbuilder"]
    assert json.loads(vlr.record_data)["scans"] == ["part0", "part1", "part2"]
    assert np.bincount(np.asarray(las["scan_id"])).tolist() == [2500, 2500, 2500]
    # and --all-scans of an archive holding the joint scan counts its members
    both = tmp_path / "both.copc.laz"
    assert main(["export", str(joint), "--all-scans", "-o", str(both), "-q"]) == 0
    las = laspy.read(str(both))
    (vlr,) = [v for v in las.header.evlrs if v.user_id == "lodbuilder"]
    assert json.loads(vlr.record_data)["scans"] == ["part0", "part1", "part2"]
