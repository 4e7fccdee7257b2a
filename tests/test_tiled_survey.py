"""A survey of many files ordered as one surface (issue 19): the read, plan and distribute phases
run as tasks, one per file or range of a big file; guarantees against brute force, blocks that do
not change the archive, and a damaged tile file that fails the build by its name."""

from __future__ import annotations

import numpy as np
import pytest
from naive import prefix_covering_radii

import lodbuilder
from lodbuilder.errors import BuildError
from lodbuilder.io import Scan, read_scan

laspy = pytest.importorskip("laspy")


def _surface(n, seed=0):
    rng = np.random.default_rng(seed)
    side = int(np.sqrt(n))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2).astype(float)
    g = (g + rng.uniform(-0.3, 0.3, g.shape)) / side * 100.0
    return np.c_[g, 8 * np.sin(g[:, 0] / 8) * np.cos(g[:, 1] / 8)]


def _las(path, pts, fmt, extra=None, seed=0):
    """A LAS/LAZ file of point format ``fmt`` (with a float32 extra-bytes field ``extra``)."""
    hdr = laspy.LasHeader(point_format=fmt, version="1.4")
    hdr.scales = np.array([0.001, 0.001, 0.001])
    hdr.offsets = np.array([0.0, 0.0, 0.0])
    if extra:
        hdr.add_extra_dims([laspy.ExtraBytesParams(name=extra, type=np.float32)])
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.intensity = np.random.default_rng(seed).integers(0, 60000, len(pts)).astype(np.uint16)
    if extra:
        las[extra] = np.arange(len(pts), dtype=np.float32)
    las.write(str(path))
    return path


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    """Six files cut from one surface in strips: LAS and LAZ, point formats 0, 1, 3, 6, 7, 8, some
    with extra bytes."""
    d = tmp_path_factory.mktemp("survey")
    pts = _surface(3000)
    strips = np.array_split(np.argsort(pts[:, 0], kind="stable"), 6)
    spec = [(0, ".las", None), (1, ".laz", "height"), (3, ".laz", None), (6, ".las", "height"),
            (7, ".laz", "amp"), (8, ".las", None)]
    files = [_las(d / f"tile{i}{suf}", pts[idx], fmt, extra, seed=i)
             for i, (idx, (fmt, suf, extra)) in enumerate(zip(strips, spec, strict=True))]
    return files, [read_scan(f) for f in files]


def _read(out):
    with lodbuilder.open_archive(out) as arc:
        v = arc.scan()
        return {"order": v.source_index[:], "radius": v.radius[:], "points": v.points(), "attrs": v.attributes(),
                "build": v.build, "n_ordered": v.n_ordered}


@pytest.mark.slow
def test_a_survey_of_files_against_brute_force(survey, tmp_path):
    files, scans = survey
    out = tmp_path / "s.h5"
    res = lodbuilder.build_archive(files, out, joint="site", workers=2, _tile_points=250)
    assert [(s.name, s.status, s.method) for s in res.scans] == [("site", "built", "tiled")]
    d = _read(out)
    merged = np.vstack([s.points for s in scans])
    n = len(merged)
    assert d["build"]["tiled"]["tiles"] >= 10 and d["n_ordered"] == n
    # every point exactly once, with its own file's attributes (those every file has)
    assert np.array_equal(np.sort(d["order"]), np.arange(n))
    np.testing.assert_array_equal(d["points"], merged[d["order"]])
    a = d["attrs"]
    assert "height" not in a and "amp" not in a  # not in every file
    first = np.cumsum([0] + [len(s) for s in scans])
    np.testing.assert_array_equal(first[a["scan_id"]] + a["scan_point"], d["order"])
    intensity = np.concatenate([s.attributes["intensity"] for s in scans])
    np.testing.assert_array_equal(a["intensity"], intensity[d["order"]])
    # every stored radius a true Euclidean covering radius of the whole survey; never increasing
    cr = prefix_covering_radii(merged, d["order"])
    r = d["radius"]
    assert np.all(np.diff(r) <= 0)
    assert np.all(cr[1:n] <= r[1:n] * (1 + 1e-12)), int(np.argmax(cr[1:n] - r[1:n]))


@pytest.mark.slow
def test_blocks_do_not_change_the_archive(survey, tmp_path, monkeypatch):
    """A big file read in ranges (its reader seeks, LAZ through its chunk table), in small chunks,
    gives the archive of one block per file (and the ranks' transpose in many bands)."""
    import lodbuilder.build.tiled.ranks as ranks
    import lodbuilder.build.tiled.workdir as workdir

    files, scans = survey
    one = _las(tmp_path / "one.laz", np.vstack([s.points for s in scans]), 3)
    ref = _read(_build(one, tmp_path / "ref.h5"))
    monkeypatch.setattr(workdir, "BLOCK", 200)
    monkeypatch.setattr(ranks, "BAND", 500)  # the ranks' transpose: many bands to many read blocks
    small = _read(_build(one, tmp_path / "small.h5"))
    assert small["build"]["tiled"]["read_blocks"] >= 4 and ref["build"]["tiled"]["read_blocks"] == 1
    for key in ("order", "radius", "points"):
        np.testing.assert_array_equal(small[key], ref[key])
    np.testing.assert_array_equal(small["attrs"]["intensity"], ref["attrs"]["intensity"])


def _build(src, out):
    lodbuilder.build_archive(src, out, workers=2, _tile_points=400)
    return out


@pytest.mark.parametrize("damage", ["body", "truncated"])
def test_a_damaged_tile_file_fails_the_build_by_its_name(survey, tmp_path, damage):
    """A LAZ file whose compressed points are damaged (its header is fine): the read task that
    decodes it fails the build with the file's name; a file shorter than its header says is
    refused from its header, before any task. Either way the archive stays as it was."""
    from lodbuilder.errors import FormatError

    files, _ = survey
    bad = tmp_path / "bad.laz"
    data = bytearray(files[1].read_bytes())
    if damage == "body":
        mid = len(data) // 2
        data[mid:mid + 64] = bytes(b ^ 0xFF for b in data[mid:mid + 64])
    else:
        bad = tmp_path / "bad.las"
        data = bytearray(files[0].read_bytes())[:-2000]
    bad.write_bytes(bytes(data))
    keep = tmp_path / "t.h5"
    lodbuilder.build_archive(Scan(points=np.random.default_rng(1).random((300, 3)), name="other"), keep)
    before = keep.read_bytes()
    with pytest.raises((BuildError, FormatError)) as exc:
        lodbuilder.build_archive([files[2], bad], keep, joint="site", workers=2, _tile_points=250)
    msg = str(exc.value)
    if damage == "body":
        # the decoder's own words (lazrs) in the middle
        assert msg.startswith(f"scan 'site': reading {bad} failed: {bad}: cannot be read as LAS ("), msg
        assert msg.endswith("); check or re-export the file")
    else:
        assert msg.startswith(f"{bad}: the LAS header declares "), msg
    assert keep.read_bytes() == before
    with lodbuilder.open_archive(keep) as arc:
        assert arc.scans == ["other"]


def test_the_parent_reads_no_point_of_a_file(survey, tmp_path, monkeypatch):
    """Issue 19.1: the parent plans from the files' headers; the points are read by the workers'
    tasks only (a chunk read in the parent fails the build)."""
    from lodbuilder.io.stream import PointStream

    files, scans = survey

    def no_chunks(self, *args, **kwargs):
        raise AssertionError(f"the parent read points of {self.path}")

    monkeypatch.setattr(PointStream, "chunks", no_chunks)
    out = tmp_path / "p.h5"
    res = lodbuilder.build_archive(files[:3], out, joint="site", workers=2, _tile_points=400)
    assert [s.status for s in res.scans] == ["built"]
    with lodbuilder.open_archive(out) as arc:
        assert arc.scan().n_points == sum(len(s) for s in scans[:3])


def test_a_file_changed_during_the_build_fails_the_write_by_its_name(survey, tmp_path, monkeypatch):
    """The write reads the inputs again (the work directory keeps no copy of the points' attributes):
    a file rewritten during the build (one point's intensity changed) fails the build, naming the
    file and its rows, before anything is written; the archive stays as it was."""
    import shutil

    from lodbuilder.build.tiled import write

    files, scans = survey
    a, b = shutil.copy(files[0], tmp_path / "a.las"), shutil.copy(files[2], tmp_path / "b.laz")
    real = write.buckets_phase

    def rewrite_then_permute(*args, **kwargs):
        las = laspy.read(str(a))
        las.intensity[7] += 1
        las.write(str(a))
        return real(*args, **kwargs)

    monkeypatch.setattr(write, "buckets_phase", rewrite_then_permute)
    keep = tmp_path / "t.h5"
    lodbuilder.build_archive(Scan(points=np.random.default_rng(1).random((300, 3)), name="other"), keep)
    before = keep.read_bytes()
    with pytest.raises(BuildError) as exc:
        lodbuilder.build_archive([a, b], keep, joint="site", workers=2, _tile_points=250)
    assert str(exc.value) == (f"scan 'site': the permutation of block 1 failed: {a}: rows 0 to {len(scans[0])} are "
                              "not the rows this build read from it (the file changed during the build); run the "
                              "build again")
    assert keep.read_bytes() == before


def _empty_las(path):
    """A LAZ file with a header and no point (a survey tile over water)."""
    hdr = laspy.LasHeader(point_format=3, version="1.4")
    hdr.scales = np.array([0.001, 0.001, 0.001])
    laspy.LasData(hdr).write(str(path))
    return path


def test_an_empty_tile_file_is_a_member_with_no_points(survey, tmp_path, caplog):
    """A survey tile with no points (LAZ, or a PLY of 0 vertices) does not fail the survey: it is a
    member of the joint scan with none, said in the log; the points, their order and radii are
    those of the survey without it, and every point keeps its own file's scan_id."""
    import logging

    files, scans = survey
    empty_laz = _empty_las(tmp_path / "water.laz")
    empty_ply = tmp_path / "nothing.ply"
    empty_ply.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                         "property float z\nend_header\n")
    ref = _read(_build_joint(files[:3], tmp_path / "ref.h5"))
    with caplog.at_level(logging.WARNING, logger="lodbuilder"):
        got = _read(_build_joint([files[0], empty_laz, files[1], empty_ply, files[2]], tmp_path / "e.h5"))
    for key in ("order", "radius", "points"):
        np.testing.assert_array_equal(got[key], ref[key])
    members = got["build"]["joint"]["scans"]
    assert [m["name"] for m in members] == ["tile0", "water", "tile1", "nothing", "tile2"]
    np.testing.assert_array_equal(got["attrs"]["scan_id"], np.array([0, 2, 4])[ref["attrs"]["scan_id"]])
    np.testing.assert_array_equal(got["attrs"]["scan_point"], ref["attrs"]["scan_point"])
    np.testing.assert_array_equal(got["attrs"]["intensity"], ref["attrs"]["intensity"])
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        f"{empty_laz} holds no points: member 1 of the joint scan 'site', with none",
        f"{empty_ply} holds no points: member 3 of the joint scan 'site', with none"]


def _build_joint(files, out):
    lodbuilder.build_archive(files, out, joint="site", workers=1, _tile_points=400)
    return out


def test_a_joint_scan_of_empty_files_or_of_one_file_twice_is_refused(survey, tmp_path):
    """Nothing to build when every input is empty; a file given twice (a glob and the file named
    again) would store its points twice. One line each; the archive stays as it was."""
    from lodbuilder.errors import EmptyScanError, InputError

    files, _ = survey
    a, b = _empty_las(tmp_path / "a.laz"), _empty_las(tmp_path / "b.laz")
    keep = tmp_path / "t.h5"
    lodbuilder.build_archive(Scan(points=np.random.default_rng(1).random((300, 3)), name="other"), keep)
    before = keep.read_bytes()
    with pytest.raises(EmptyScanError) as exc:
        lodbuilder.build_archive([a, b], keep, joint="site", workers=1)
    assert str(exc.value) == "joint scan 'site': none of its 2 inputs holds a point; nothing to build"
    with pytest.raises(EmptyScanError) as exc:
        lodbuilder.build_archive([a], keep, joint="site", workers=1)
    assert str(exc.value) == "joint scan 'site': its input holds no points; nothing to build"
    with pytest.raises(InputError) as exc:
        lodbuilder.build_archive([files[0], files[1], files[0]], keep, joint="site", workers=1)
    assert str(exc.value) == (f"input {files[0]} is given twice (inputs 1 and 3) for the joint scan 'site'; "
                              "give each file once")
    assert keep.read_bytes() == before


def test_a_survey_on_one_las_grid_keeps_integer_coordinates(survey, tmp_path):
    """Tiles that share a LAS scale keep integer coordinates in the joint scan (they were stored as
    float64: 24 bytes a point, the 36-file survey's archive 159 MB against 90 MB), exactly; a tile
    on another grid makes them float64, with the same points."""
    files, scans = survey
    other = _las(tmp_path / "fine.laz", scans[2].points, 3)
    las = laspy.read(str(other))
    las.change_scaling(scales=[0.0005, 0.0005, 0.0005])
    las.write(str(other))
    grid = _read(_build_joint(files[:3], tmp_path / "g.h5"))
    mixed = _read(_build_joint([files[0], files[1], other], tmp_path / "m.h5"))
    with lodbuilder.open_archive(tmp_path / "g.h5") as a, lodbuilder.open_archive(tmp_path / "m.h5") as b:
        assert (a.scan().encoding, b.scan().encoding) == ("int32", "float64")
        assert a.scan().format_metadata["las_scales"] == [0.001, 0.001, 0.001]
    merged = np.vstack([s.points for s in scans[:3]])
    np.testing.assert_array_equal(grid["points"], merged[grid["order"]])
    np.testing.assert_array_equal(mixed["points"], merged[mixed["order"]])
