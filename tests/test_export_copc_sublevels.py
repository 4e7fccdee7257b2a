"""``export --rank-radius [level]``: one uint8 extra byte ``sublevel`` a point and a table of
(depth, sublevel) -> (prefix, points, rho). A reader that keeps the points of depths < D and
those of depth D with sublevel <= s holds exactly the archive's level of ``prefix`` points, and
its covering radius is the archive's. The same file is read by laspy's CopcReader, copclib
and the npm ``copc`` reader."""

from __future__ import annotations

import re

import numpy as np
import pytest
from test_export_copc import check_copclib, decode_with_copcjs, our_vlr

from lodbuilder.cli.main import main

laspy = pytest.importorskip("laspy")


@pytest.fixture(scope="module")
def autzen(autzen_archive_full):
    return autzen_archive_full


@pytest.fixture(scope="module")
def autzen_copc_level(autzen, tmp_path_factory):
    """``--rank-radius`` with no mode: the level mode."""
    out = tmp_path_factory.mktemp("copc") / "autzen_level.copc.laz"
    assert main(["export", str(autzen), "-o", str(out), "-q", "--rank-radius"]) == 0
    return out


def by_depth(path) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per depth, the (M, 3) integer coordinates and the sublevel of its points (CopcReader)."""
    out = []
    with laspy.CopcReader.open(str(path)) as reader:
        for d in range(len(our_vlr(path)["levels"])):
            got = reader.query(level=d)
            xyz = np.column_stack([np.asarray(got.X), np.asarray(got.Y), np.asarray(got.Z)])
            out.append((xyz.astype(np.int64), np.asarray(got["sublevel"])))
    return out


def kept(depths, d: int, s: int) -> np.ndarray:
    """What a reader keeps for the bound (d, s): depths < d and sublevels <= s of depth d."""
    parts = [xyz for xyz, _ in depths[:d]] + [depths[d][0][depths[d][1] <= s]]
    return np.concatenate(parts)


def rows(a: np.ndarray) -> np.ndarray:
    """Rows sorted lexicographically (a multiset of points, comparable with ==)."""
    return a[np.lexsort(a.T[::-1])]


def test_sublevels_are_the_archives_levels(autzen, autzen_copc_level):
    """Every (depth, sublevel) bound keeps exactly the archive's level of the table's prefix
    (its points, quantised to the file's grid), and the table's rho is the archive's rho."""
    import lodbuilder
    from lodbuilder.export.copc import SUBLEVELS, read_sublevels

    table = read_sublevels(autzen_copc_level)
    doc = our_vlr(autzen_copc_level)
    depths = by_depth(autzen_copc_level)
    with laspy.open(str(autzen_copc_level)) as r:
        scales, offsets = r.header.scales, r.header.offsets
    with lodbuilder.open_archive(autzen) as arc:
        view = arc.scan()
        radius = np.asarray(view.radius)
        every = np.rint((view.points(110000) - offsets) / scales).astype(np.int64)
        assert [view.level(size=int(p)).rho for p in table["prefix"][[0, 300, -1]]] == \
            table["rho"][[0, 300, -1]].tolist()
    assert doc["sublevels"]["record_id"] == 3 and doc["extra_bytes"] == {"sublevel": doc["extra_bytes"]["sublevel"]}
    # SUBLEVELS equal-count runs a depth, ending at the depth's own prefix
    assert table.size == SUBLEVELS * len(doc["levels"]) == 512
    for lv in doc["levels"]:
        mine = table[table["depth"] == lv["depth"]]
        np.testing.assert_array_equal(mine["sublevel"], np.arange(SUBLEVELS))
        assert mine["prefix"][-1] == lv["fps_prefix"] and mine["rho"][-1] == (lv["rho"] or 0.0)
        start = 0 if lv["depth"] == 0 else doc["levels"][lv["depth"] - 1]["fps_prefix"]
        assert np.ptp(np.diff(np.concatenate([[start], mine["prefix"]]))) <= 1  # equal counts
    assert np.all(np.diff(table["prefix"].astype(np.int64)) > 0)
    assert np.all(table["points"] == table["prefix"])  # autzen: nothing promoted
    np.testing.assert_array_equal(
        table["rho"], [radius[p] if p < radius.size else 0.0 for p in table["prefix"]])
    for i in list(range(0, 256, 15)) + list(range(256, 512, 37)) + [255, 511]:
        d, s, p = int(table["depth"][i]), int(table["sublevel"][i]), int(table["prefix"][i])
        got = kept(depths, d, s)
        assert got.shape[0] == p
        np.testing.assert_array_equal(rows(got), rows(every[:p]), f"depth {d} sublevel {s}")


def test_sublevels_with_promoted_points(tmp_path, monkeypatch):
    """Points moved up to keep the octree connected carry sublevel 0: a bound (D, s) keeps the
    prefix and the moved points of depths <= D, as many as the table's ``points``."""
    from lodbuilder.export import copc
    from lodbuilder.export.copc import read_sublevels, write_copc

    monkeypatch.setattr(copc, "ROOT_POINTS", 15)  # several depths from 3,000 points
    rng = np.random.default_rng(5)
    pts = np.round(rng.random((3000, 3)) * [100, 100, 1], 2)
    pts[1:300, :2] = np.round(pts[1:300, :2] * 0.2, 2)  # coarse points in one corner
    radius = 50 / np.sqrt(np.arange(1, 3001))
    radius[0] = np.inf
    meta = {"las_scales": [0.01, 0.01, 0.01], "las_offsets": [0.0, 0.0, 0.0]}
    lv = write_copc(tmp_path / "l.copc.laz", pts, {}, radius, 0.0, rank_radius="level", metadata=meta)
    ex = write_copc(tmp_path / "e.copc.laz", pts, {}, radius, 0.0, rank_radius="exact", metadata=meta)
    assert lv.promoted == ex.promoted > 0 and lv.levels == ex.levels
    rank_of = {}  # integer coordinates -> (rank, depth), from the exact file
    with laspy.CopcReader.open(str(tmp_path / "e.copc.laz")) as reader:
        for d in range(ex.depths):
            got = reader.query(level=d)
            for key, r in zip(zip(got.X, got.Y, got.Z, strict=True), got["rank"], strict=True):
                rank_of[tuple(int(v) for v in key)] = (int(r), d)
    assert len(rank_of) == 3000
    table = read_sublevels(tmp_path / "l.copc.laz")
    depths = by_depth(tmp_path / "l.copc.laz")
    band = copc.depth_bands(radius, lv.spacing, lv.depths - 1)
    for d, s, p, n, rho in table.tolist():
        got = [rank_of[tuple(row)] for row in kept(depths, d, s).tolist()]
        ranks = np.array([r for r, _ in got])
        extra = [(r, e) for r, e in got if r >= p]
        assert len(got) == n and np.array_equal(np.sort(ranks)[:p], np.arange(p))
        assert all(e <= d and e < band[r] for r, e in extra)  # only points moved up to depths <= d
        assert rho == (radius[p] if p < 3000 else 0.0)
    check_copclib(tmp_path / "l.copc.laz")


def test_level_files_are_read_by_copclib_and_the_npm_reader(autzen_copc_level):
    check_copclib(autzen_copc_level)
    las = laspy.read(str(autzen_copc_level))
    assert las["sublevel"].dtype == np.uint8 and "rank" not in las.point_format.dimension_names
    out = decode_with_copcjs(autzen_copc_level)
    assert out["pointCount"] == 110000
    assert all(n["decoded"] == n["declared"] > 0 for n in out["nodes"].values())
    assert sum(n["decoded"] for n in out["nodes"].values()) == 110000


def test_level_size_against_the_source_laz(shared_data, autzen_copc_level):
    """The target: <= 1.5 x the source LAZ with the levels stored (1.31 x measured)."""
    source = (shared_data / "autzen_trim.laz").stat().st_size
    assert autzen_copc_level.stat().st_size <= 1.5 * source


def test_rank_radius_modes_are_checked(autzen, tmp_path, capsys):
    from lodbuilder.errors import InputError
    from lodbuilder.export.copc import read_sublevels, write_copc

    out = tmp_path / "x.copc.laz"
    for bad in ("bogus", "Level"):
        assert main(["export", str(autzen), "-o", str(out), "--rank-radius", bad]) == 2
        assert capsys.readouterr().err == (
            "lodbuilder export: error: --rank-radius takes level (the default: 256 sub-levels a "
            f"depth, one byte a point) or exact (each point's rank), got '{bad}'\n")
    for bad in (True, "rank", 1):
        with pytest.raises(InputError, match="^" + re.escape(
                "rank_radius must be 'level' (one byte a point: 256 sub-levels a depth, each with "
                "its covering radius) or 'exact' (each point's rank and the radius by rank), "
                f"got {bad!r}") + "$"):
            write_copc(out, np.zeros((2, 3)), {}, np.ones(2), 0, rank_radius=bad)
    with pytest.raises(InputError, match=r"^attribute 'sublevel' would clash with the sublevel the "
                       r"COPC file records; rename it$"):
        write_copc(out, np.zeros((2, 3)), {"sublevel": np.zeros(2)}, np.ones(2), 0,
                   rank_radius="level")
    plain = write_copc(out, np.random.default_rng(0).random((50, 3)), {}, np.ones(50), 0)
    with pytest.raises(InputError, match=f"^{re.escape(str(out))} has no sub-level table; "
                       "export it with --rank-radius level$"):
        read_sublevels(plain.path)
    (tmp_path / "x.copc.laz").unlink()
    assert list(tmp_path.iterdir()) == []
