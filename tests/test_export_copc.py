"""``lodbuilder export ARCHIVE -o OUT.copc.laz``: a COPC 1.0 file (read back with laspy's
CopcReader, copclib's reader and the npm ``copc`` reader) whose octree depths are farthest-point
levels, with every attribute, the CRS, scale and offset, and with --rank-radius exact the rank
and the insertion radius (--rank-radius level: tests/test_export_copc_sublevels.py)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lodbuilder.cli.main import main

laspy = pytest.importorskip("laspy")

ROOT = Path(__file__).resolve().parents[1]
COPCJS = ROOT / "tools" / "copcjs"


def copclib():
    return pytest.importorskip("copclib", reason="copclib is not installed (pip install 'lodbuilder[dev]')")


@pytest.fixture(scope="module")
def autzen(autzen_archive_full):
    return autzen_archive_full


@pytest.fixture(scope="module")
def autzen_copc(autzen, tmp_path_factory):
    """The default export: no rank or radius."""
    out = tmp_path_factory.mktemp("copc") / "autzen.copc.laz"
    assert main(["export", str(autzen), "-o", str(out), "-q"]) == 0
    return out


@pytest.fixture(scope="module")
def autzen_copc_rr(autzen, tmp_path_factory):
    """With --rank-radius exact: every point says where it is in the ordering."""
    out = tmp_path_factory.mktemp("copc") / "autzen_rr.copc.laz"
    assert main(["export", str(autzen), "-o", str(out), "-q", "--rank-radius", "exact"]) == 0
    return out


def read_radius_table(path):
    from lodbuilder.export.copc import read_radius_table

    return read_radius_table(path)


def float32_up(radius: np.ndarray) -> np.ndarray:
    """float32 at or above each radius (what the radius table holds): an upper bound stays one."""
    r32 = radius.astype(np.float32)
    low = r32.astype(np.float64) < radius
    r32[low] = np.nextafter(r32[low], np.float32(np.inf))
    assert np.all(r32.astype(np.float64) >= radius)
    return r32


def our_vlr(path) -> dict:
    with laspy.open(str(path)) as r:
        (vlr,) = [v for v in r.header.evlrs if v.user_id == "lodbuilder" and v.record_id == 1]
        return json.loads(vlr.record_data)


def nodes(path) -> list:
    """(depth, offset, byte_size, point_count) of every node of the COPC hierarchy."""
    with laspy.CopcReader.open(str(path)) as reader:
        from laspy.copc import load_octree_for_query

        found = load_octree_for_query(reader.source, reader.copc_info, reader.root_page,
                                      query_bounds=None, level_range=None)
        return [(n.key.level, n.offset, n.byte_size, n.point_count) for n in found]


def test_every_depth_query_returns_the_prefix_written(autzen, autzen_copc_rr):
    import lodbuilder

    doc = our_vlr(autzen_copc_rr)
    with lodbuilder.open_archive(autzen) as arc:
        radius = np.asarray(arc.scan().radius)
    assert doc["n_points"] == doc["n_points_scan"] == 110000
    levels = doc["levels"]
    assert len(levels) >= 2 and levels[-1]["points"] == 110000
    # the deepest depth holds at least 7/8 of the points, every other depth its band
    assert levels[-1]["points"] - levels[-2]["points"] >= 110000 * 7 // 8
    table = read_radius_table(autzen_copc_rr)
    with laspy.CopcReader.open(str(autzen_copc_rr)) as reader:
        assert reader.copc_info.spacing == pytest.approx(doc["spacing"])
        for lv in levels:
            d = lv["depth"]
            got = reader.query(level=range(0, d + 1))
            rank = np.sort(np.asarray(got["rank"], dtype=np.int64))
            # exactly the points of depths <= d: the farthest-point prefix (nothing promoted here)
            assert lv["promoted"] == 0
            np.testing.assert_array_equal(rank, np.arange(lv["fps_prefix"]))
            # its covering radius is the next insertion radius, within the depth's band
            k = lv["fps_prefix"]
            assert lv["rho"] == (float(radius[k]) if k < radius.size else 0.0)
            assert lv["rho"] <= doc["spacing"] / 2 ** (d + 1) or d == len(levels) - 1
            # and the points of depth d alone have radii in (s0 / 2^(d+1), s0 / 2^d]
            one = reader.query(level=d)
            r = table[np.asarray(one["rank"], dtype=np.int64)]
            top = doc["spacing"] / 2**d  # (the table rounds up to float32: a radius of exactly top reads above it)
            assert np.all(r > doc["spacing"] / 2 ** (d + 1)) or d == len(levels) - 1
            assert d == 0 or np.all(r <= float32_up(np.array([top]))[0])


def depth_of_rank(doc: dict, rank: np.ndarray) -> np.ndarray:
    """The depth of each rank by the EVLR's prefixes (no promoted points)."""
    prefixes = np.array([lv["fps_prefix"] for lv in doc["levels"]])
    return np.searchsorted(prefixes, rank, side="right")


def test_spatial_and_resolution_queries_equal_brute_force(autzen_copc_rr):
    """laspy's CopcReader chooses nodes from the info VLR's cube: every box and resolution
    query returns exactly the points a mask over the whole file gives."""
    from laspy.copc import Bounds

    doc = our_vlr(autzen_copc_rr)
    every = laspy.read(str(autzen_copc_rr))  # read as a plain LAZ file, front to back
    xyz = np.column_stack([np.asarray(every.x), np.asarray(every.y), np.asarray(every.z)])
    rank = np.asarray(every["rank"], dtype=np.int64)
    depth = depth_of_rank(doc, rank)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    rng = np.random.default_rng(3)
    with laspy.CopcReader.open(str(autzen_copc_rr)) as reader:
        assert reader.header.point_count == xyz.shape[0]
        for _ in range(12):
            a, b = lo + rng.random(3) * (hi - lo), lo + rng.random(3) * (hi - lo)
            box = Bounds(np.minimum(a, b), np.maximum(a, b))
            for levels in (None, range(0, 1), range(0, len(doc["levels"]))):
                got = reader.query(bounds=box, level=levels)
                mask = np.all((xyz >= box.mins - 1e-9) & (xyz <= box.maxs + 1e-9), axis=1)
                if levels is not None:
                    mask &= depth < levels.stop
                assert np.array_equal(np.sort(np.asarray(got["rank"])), np.sort(rank[mask]))
        for res in (100.0, doc["spacing"], doc["spacing"] / 2, doc["spacing"] / 8, 0.01):
            got = reader.query(resolution=res)
            level_max = max(1, int(np.ceil(np.log2(doc["spacing"] / res))) + 1)
            assert np.array_equal(np.sort(np.asarray(got["rank"])), np.sort(rank[depth < level_max]))


def test_copc_1_0_details(shared_data, autzen, autzen_copc):
    """GPS-time range in the info VLR, the CRS as a WKT VLR that CopcReader finds, no legacy
    extents VLR, the info VLR first at 375, the header's bounds around every point, a cube that
    contains them strictly, and copclib's ValidateSpatialBounds."""
    src = laspy.read(str(shared_data / "autzen_trim.laz"))
    raw = autzen_copc.read_bytes()
    assert raw[377:381] == b"copc" and raw[393:395] == b"\x01\x00"
    assert raw[104] & 0x3F in (6, 7, 8) and raw[104] & 0x80  # compressed point format 7
    with laspy.CopcReader.open(str(autzen_copc)) as reader:
        info = reader.copc_info
        assert (info.gps_min, info.gps_max) == (src.gps_time.min(), src.gps_time.max())
        crs = reader.header.parse_crs()
        assert crs is not None and crs.to_wkt() and "Lambert" in crs.to_wkt()
        records = list(reader.header.vlrs) + list(reader.header.evlrs or [])
        assert not [v for v in records if v.user_id == "copc" and v.record_id == 10000]
        assert [type(v).__name__ for v in reader.header.vlrs][0] == "CopcInfoVlr"
        assert reader.header.global_encoding.wkt
        every = reader.query()
        xyz = np.column_stack([np.asarray(every.x), np.asarray(every.y), np.asarray(every.z)])
        mins, maxs = reader.header.mins, reader.header.maxs
        assert np.all(xyz >= mins) and np.all(xyz <= maxs)
        np.testing.assert_allclose(mins, xyz.min(axis=0) - 0.01)  # padded by one step
        cube_lo, cube_hi = info.center - info.halfsize, info.center + info.halfsize
        assert np.all(xyz > cube_lo) and np.all(xyz < cube_hi)
        np.testing.assert_allclose(cube_lo, mins)
    check_copclib(autzen_copc)


def check_copclib(path) -> None:
    reader = copclib().FileReader(str(path))
    try:
        assert reader.ValidateSpatialBounds()
        assert sum(n.point_count for n in reader.GetAllNodes()) == reader.copc_config.las_header.point_count
    finally:
        reader.Close()


def test_points_on_the_faces_of_the_bounding_box(tmp_path, monkeypatch):
    """A flat grid whose points lie on every face of its bounding box (the case where copclib's
    ValidateSpatialBounds failed with an unpadded cube) is valid, and every point is found."""
    from lodbuilder.export import copc
    from lodbuilder.export.copc import write_copc

    monkeypatch.setattr(copc, "ROOT_POINTS", 1000)  # several depths from 40,401 points
    g = np.linspace(0.0, 100.0, 201)
    xx, yy = np.meshgrid(g, g)
    pts = np.column_stack([xx.ravel(), yy.ravel(), (xx.ravel() > 50) * 5.0])
    rng = np.random.default_rng(1)
    pts = pts[rng.permutation(pts.shape[0])]
    radius = 200.0 / np.sqrt(np.arange(1, pts.shape[0] + 1))
    radius[0] = np.inf
    out = write_copc(tmp_path / "g.copc.laz", pts, {}, radius, 0.0,
                     metadata={"las_scales": [0.5, 0.5, 0.5], "las_offsets": [0.0, 0.0, 0.0]})
    assert out.depths >= 2
    check_copclib(tmp_path / "g.copc.laz")
    with laspy.CopcReader.open(str(tmp_path / "g.copc.laz")) as reader:
        got = reader.query()
        assert len(got) == pts.shape[0]
        xyz = np.column_stack([np.asarray(got.x), np.asarray(got.y), np.asarray(got.z)])
        assert sorted(map(tuple, xyz.tolist())) == sorted(map(tuple, pts.tolist()))


def test_points_inside_a_node_go_by_gps_time(autzen_copc):
    """Inside each node the points follow GPS time (what LAZ compresses well), not the
    farthest-point order."""
    gps = np.asarray(laspy.read(str(autzen_copc)).gps_time)  # the file front to back
    start = 0
    for _, _, _, count in sorted(nodes(autzen_copc), key=lambda n: n[1]):  # nodes in file order
        assert np.all(np.diff(gps[start:start + count]) >= 0)
        start += count
    assert start == gps.size == 110000


def copcjs() -> Path:
    """tools/copcjs with the npm 'copc' reader installed (npm install there), or skip."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: the npm copc reader cannot run")
    if not (COPCJS / "node_modules" / "copc").is_dir():
        npm = shutil.which("npm")
        if npm is None:
            pytest.skip("npm is not installed: cannot install the npm copc reader")
        r = subprocess.run([npm, "install", "--no-audit", "--no-fund"], cwd=COPCJS,
                           capture_output=True, text=True, timeout=300)
        if r.returncode != 0:
            pytest.skip(f"npm install in tools/copcjs failed (offline?): {r.stderr.strip()[-200:]}")
    return COPCJS / "decode.js"


def decode_with_copcjs(path) -> dict:
    r = subprocess.run(["node", str(copcjs()), str(path)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.mark.parametrize("which", ["autzen_copc", "autzen_copc_rr"])
def test_the_npm_copc_reader_decodes_every_node(which, request):
    path = request.getfixturevalue(which)
    out = decode_with_copcjs(path)
    las = laspy.read(str(path))
    assert out["pointFormat"] == 7 and out["pointCount"] == len(las) == 110000
    assert out["info"]["gpsTimeRange"] == [float(las.gps_time.min()), float(las.gps_time.max())]
    assert out["wkt"] and "Lambert" in out["wkt"]
    assert len(out["nodes"]) == len(nodes(path))
    for node in out["nodes"].values():
        assert node["decoded"] == node["declared"] > 0
    assert sum(n["decoded"] for n in out["nodes"].values()) == 110000
    sums = np.sum([n["sums"] for n in out["nodes"].values()], axis=0)
    np.testing.assert_allclose(sums, [np.sum(las.x), np.sum(las.y), np.sum(las.z)], rtol=1e-12)


def test_depths_are_written_breadth_first_in_one_byte_range(autzen_copc):
    ns = nodes(autzen_copc)
    depths = sorted({d for d, *_ in ns})
    for d in depths[:-1]:
        upto = [(o, s) for dd, o, s, _ in ns if dd <= d]
        deeper = [o for dd, o, _, _ in ns if dd > d]
        start, end = min(o for o, _ in upto), max(o + s for o, s in upto)
        assert end - start == sum(s for _, s in upto)  # contiguous
        assert end <= min(deeper)  # before every deeper node


def test_copc_keeps_dimensions_crs_scale_offset(shared_data, autzen, autzen_copc_rr):
    import lodbuilder

    autzen_copc = autzen_copc_rr

    src = laspy.read(str(shared_data / "autzen_trim.laz"))
    with lodbuilder.open_archive(autzen) as arc:
        view = arc.scan()
        source_index = np.asarray(view.source_index)
        wkt = view.crs
    out = laspy.read(str(autzen_copc))  # a COPC file is a LAZ file
    assert out.header.version == "1.4" and out.header.point_format.id == 7  # format 3's 1.4 twin
    np.testing.assert_array_equal(out.header.scales, src.header.scales)
    np.testing.assert_array_equal(out.header.offsets, src.header.offsets)
    assert out.header.global_encoding.wkt
    (wkt_vlr,) = [v for v in out.header.vlrs if type(v).__name__ == "WktCoordinateSystemVlr"]
    assert not [v for v in out.header.evlrs if type(v).__name__ == "WktCoordinateSystemVlr"]
    assert wkt and wkt_vlr.string.rstrip("\0") == wkt
    # every point, by rank: the same integer coordinates and every field of the source
    rank = np.asarray(out["rank"], dtype=np.int64)
    src_i = source_index[rank]
    for dim in ("X", "Y", "Z", "intensity", "return_number", "number_of_returns",
                "classification", "user_data", "point_source_id", "gps_time",
                "red", "green", "blue", "scan_direction_flag", "edge_of_flight_line"):
        np.testing.assert_array_equal(np.asarray(out[dim]), np.asarray(src[dim])[src_i], dim)
    np.testing.assert_array_equal(np.asarray(out["scan_angle_rank"]), np.asarray(src.scan_angle_rank)[src_i])
    # format 7's own scan_angle field (0.006-degree units) for viewers; it was left 0 before
    angle = np.rint(np.asarray(src.scan_angle_rank, dtype=np.float64)[src_i] / 0.006)
    assert np.count_nonzero(angle) > 100000
    np.testing.assert_array_equal(np.asarray(out["scan_angle"]), angle)
    assert sorted(rank.tolist()) == list(range(110000))
    assert "radius" not in out.point_format.dimension_names  # by rank, in our EVLR
    with lodbuilder.open_archive(autzen) as arc:
        np.testing.assert_array_equal(read_radius_table(autzen_copc)[rank],
                                      float32_up(np.asarray(arc.scan().radius))[rank])
    np.testing.assert_array_equal(
        out.header.number_of_points_by_return[:5], np.bincount(src.return_number, minlength=6)[1:6]
    )
    # copclib reads it back and finds every point inside its node's box and the header bounds
    check_copclib(autzen_copc)


def test_copc_round_trips_through_lodbuilder(autzen, autzen_copc_rr, tmp_path):
    """Reading the COPC file back gives the level's points and attributes, and building an
    archive from it gives the same ordering (rank and radius came along)."""
    import lodbuilder
    from lodbuilder.io import read_scans

    (scan,) = read_scans(autzen_copc_rr)
    with lodbuilder.open_archive(autzen) as arc:
        level = arc.scan().level(size=110000)
        wkt = arc.scan().crs
    rank = np.asarray(scan.attributes["rank"], dtype=np.int64)
    np.testing.assert_allclose(scan.points, level.points[rank], rtol=0, atol=1e-9)
    for name in ("intensity", "classification", "gps_time", "red"):
        np.testing.assert_array_equal(scan.attributes[name], level.attributes[name][rank], name)
    np.testing.assert_array_equal(read_radius_table(autzen_copc_rr)[rank], float32_up(level.radius[rank]))
    assert scan.metadata.get("crs_wkt") == wkt


def test_export_of_a_level_and_a_coloured_scan(tmp_path, capsys):
    import lodbuilder
    from lodbuilder.datasets import demo_scan

    arc = tmp_path / "demo.h5"
    lodbuilder.build_archive(demo_scan(30000, seed=2), arc, name="demo", importance="curvature")
    out = tmp_path / "demo.copc.laz"
    assert main(["export", str(arc), "--size", "20000", "-o", str(out), "--rank-radius", "exact"]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"wrote 20,000 of 30,000 points of scan 'demo' to {out} (")
    # 20,000 points: the root's band (10,000) reaches past K / 8, so one depth holds them all

    assert f"  changed: {out}: red: 8-bit values scaled x 257 into the 16-bit LAS field\n" in text
    doc = our_vlr(out)
    assert f"  depths 0..{doc['levels'][-1]['depth']} hold 20,000 points, covering radius " in text
    with lodbuilder.open_archive(arc) as a:
        view = a.scan()
        radius = np.asarray(view.radius)
        rgb = view.attributes(20000, ["red", "green", "blue"])
        curvature = np.asarray(view.importance("curvature"))
    assert doc["levels"][-1] == doc["levels"][-1] | {"points": 20000, "fps_prefix": 20000}
    assert doc["levels"][-1]["rho"] == float(radius[20000])  # the level's own bound
    las = laspy.read(str(out))
    rank = np.asarray(las["rank"], dtype=np.int64)
    assert las.header.point_format.id == 7
    np.testing.assert_array_equal(np.asarray(las.red), rgb["red"][rank].astype(np.uint16) * 257)
    np.testing.assert_array_equal(np.asarray(las["importance_curvature"]), curvature[rank].astype(np.float32))
    with laspy.CopcReader.open(str(out)) as reader:
        for lv in doc["levels"]:
            got = np.sort(np.asarray(reader.query(level=range(lv["depth"] + 1))["rank"]))
            assert got.size == lv["points"]
            np.testing.assert_array_equal(got[: lv["fps_prefix"]], np.arange(lv["fps_prefix"]))


def test_orphan_voxels_move_the_first_point_up():
    """A point whose parent voxel has no point of the depth above moves up to the first missing
    depth, so a reader walking down from the root reaches every node."""
    from lodbuilder.export.copc import assign_depths

    pts = np.array(
        [
            [0.10, 0.10, 0.10],  # depth 0: the root
            [0.20, 0.20, 0.20],  # depth 1, voxel (0, 0, 0)
            [0.90, 0.90, 0.90],  # band 2, but voxel (1, 1, 1) of depth 1 is empty: moves to 1
            [0.95, 0.95, 0.95],  # band 2: its parent now exists, stays
            [0.60, 0.10, 0.10],  # band 3, parents at depths 1 and 2 missing: moves to 1
            [0.62, 0.12, 0.12],  # band 3: moves to 2 (depth 1 voxel now exists, depth 2 does not)
            [0.63, 0.13, 0.13],  # band 3: stays
        ]
    )
    band = np.array([0, 1, 2, 2, 3, 3, 3])
    depth, codes = assign_depths(pts, band, np.zeros(3), 1.0)
    np.testing.assert_array_equal(depth, [0, 1, 1, 2, 1, 2, 3])
    check_tree(pts, depth, codes)


def check_tree(pts, depth, codes):
    from lodbuilder.export.copc import _code, _voxels

    keys = {(int(d), int(c)) for d, c in zip(depth, codes, strict=True)}
    for d, c in keys:
        if d:
            parent = _code(np.array([c >> 42, (c >> 21) & 0x1FFFFF, c & 0x1FFFFF]) >> 1)
            assert (d - 1, int(parent)) in keys, (d, c)
    for d in np.unique(depth):
        sel = depth == d
        np.testing.assert_array_equal(codes[sel], _code(_voxels(pts[sel], np.zeros(3), 1.0, int(d))))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 400))
def test_depths_keep_the_octree_connected_and_the_prefixes(seed, n):
    from lodbuilder.export.copc import assign_depths

    rng = np.random.default_rng(seed)
    pts = rng.random((n, 3))
    band = np.sort(rng.integers(0, 6, n))
    band[0] = 0
    depth, codes = assign_depths(pts, band, np.zeros(3), 1.0)
    assert np.all(depth <= band) and depth[0] == 0
    check_tree(pts, depth, codes)
    for d in range(6):  # depths <= d hold the prefix of band <= d and the points moved up
        assert np.all(depth[band <= d] <= d)
    moved = np.flatnonzero(depth < band)
    for i in moved:  # a moved point is the first of its band in its voxel at its new depth
        same = (band == band[i]) & (codes == codes[i]) & (depth == depth[i])
        assert np.flatnonzero(same)[0] == i


def test_promoted_points_end_to_end(tmp_path, monkeypatch):
    """A level whose octree needs moved points: the depth queries return what the EVLR says."""
    from lodbuilder.export import copc
    from lodbuilder.export.copc import write_copc

    monkeypatch.setattr(copc, "ROOT_POINTS", 15)  # several depths from 3,000 points
    rng = np.random.default_rng(5)
    pts = rng.random((3000, 3)) * [100, 100, 1]
    pts[1:300, :2] *= 0.2  # the coarse points in one corner, the fine ones everywhere
    radius = 50 / np.sqrt(np.arange(1, 3001))  # radii unrelated to where the points are
    radius[0] = np.inf
    out = write_copc(tmp_path / "p.copc.laz", pts, {}, radius, 0.0, rank_radius="exact")
    assert out.promoted > 0 and out.depths >= 4
    with laspy.CopcReader.open(str(tmp_path / "p.copc.laz")) as reader:
        for lv in out.levels:
            got = np.sort(np.asarray(reader.query(level=range(lv["depth"] + 1))["rank"]))
            assert got.size == lv["points"] == lv["fps_prefix"] + lv["promoted"]
            np.testing.assert_array_equal(got[: lv["fps_prefix"]], np.arange(lv["fps_prefix"]))
        assert reader.header.point_count == 3000


def test_the_deepest_depth_holds_seven_eighths(tmp_path, monkeypatch):
    """Radii of a surface (1 / sqrt(rank)): the coarse depths hold at most 1/8 of the points
    (with the K / 4 rule, 40,000 points took 6 depths and left 80 % in the deepest)."""
    from lodbuilder.export import copc
    from lodbuilder.export.copc import write_copc

    monkeypatch.setattr(copc, "ROOT_POINTS", 30)
    rng = np.random.default_rng(2)
    pts = rng.random((40000, 3)) * [100, 100, 1]
    radius = 1.0 / np.sqrt(np.arange(1, 40001))
    radius[0] = np.inf
    out = write_copc(tmp_path / "s.copc.laz", pts, {}, radius, 0.0)
    assert out.depths == 5
    assert out.levels[-1]["points"] - out.levels[-2]["points"] >= 40000 * 7 // 8


def test_radius_table_round_trips(tmp_path):
    """The radius by rank: float32 at or above each radius, NaN for ranks a filter removed,
    decoded by read_radius_table; a file without one is refused with its fix."""
    from lodbuilder.errors import InputError
    from lodbuilder.export.copc import radius_table, write_copc

    rng = np.random.default_rng(4)
    rank = np.sort(rng.choice(5000, 3000, replace=False))  # a filtered level: ranks with gaps
    full = np.concatenate([[np.inf], 30.0 / np.sqrt(np.arange(2, 5001))]) * (1 + 1e-9)
    pts = rng.random((3000, 3)) * 100
    out = write_copc(tmp_path / "f.copc.laz", pts, {}, full[rank], 0.0, rank_radius="exact",
                     rank=rank)
    table = read_radius_table(out.path)
    assert table.dtype == np.float32 and table.size == rank[-1] + 1
    np.testing.assert_array_equal(table[rank], float32_up(full[rank]))
    assert np.isnan(np.delete(table, rank)).all()
    np.testing.assert_array_equal(table, radius_table(rank, full[rank])[0])
    las = laspy.read(str(out.path))
    assert sorted(np.asarray(las["rank"]).tolist()) == rank.tolist()
    assert our_vlr(out.path)["radius_by_rank"]["record_id"] == 2
    plain = write_copc(tmp_path / "p.copc.laz", pts, {}, full[rank], 0.0)
    with pytest.raises(InputError, match=f"^{re.escape(str(plain.path))} has no radius table; "
                       "export it with --rank-radius exact$"):
        read_radius_table(plain.path)


def test_copc_size_against_the_source_laz(shared_data, autzen_copc, autzen_copc_rr):
    """autzen: 1.12 x its source LAZ without rank and radius, 1.69 x with them (2.77 x when the
    radius was float64 extra bytes)."""
    source = (shared_data / "autzen_trim.laz").stat().st_size
    assert autzen_copc.stat().st_size <= 1.15 * source
    assert autzen_copc_rr.stat().st_size <= 1.75 * source


def test_copc_errors(autzen, tmp_path, capsys, monkeypatch):
    from lodbuilder.errors import InputError, MissingDependencyError
    from lodbuilder.export.copc import write_copc

    arc = str(autzen)
    cases = [
        (["-o", str(tmp_path / "x.copc.laz"), "--max-points", "10"],
         "--max-points applies to a web page (-o OUT.html) only"),
        (["-o", str(tmp_path / "x.copc.laz"), "--up", "y"],
         "--up applies to a web page (-o OUT.html) only"),
        (["-o", str(tmp_path / "x.html"), "--rank-radius"],
         "--rank-radius applies to a COPC file (-o OUT.copc.laz) only"),
        (["-o", str(tmp_path / "x.laz")],
         f"-o {tmp_path / 'x.laz'}: name it OUT.copc.laz (COPC), OUT.html (web page) or DIR/tileset.json (3D Tiles); for "
         ".ply, .las, .laz, .csv, .npy... use lodbuilder slice"),
    ]
    for args, message in cases:
        assert main(["export", arc] + args) == 2
        assert capsys.readouterr().err == f"lodbuilder export: error: {message}\n"
    # slice does not write a plain LAZ under a COPC name (the io layer's rule: see test_io_writers)
    out = tmp_path / "s.copc.laz"
    assert main(["slice", arc, "--size", "10", "-o", str(out)]) == 2
    assert capsys.readouterr().err == (
        f"lodbuilder slice: error: {out}: cannot write a COPC file (only plain LAS/LAZ); use "
        f"lodbuilder export ARCHIVE -o {out} (in Python: lodbuilder.export.copc.export_copc)\n"
    )
    with pytest.raises(InputError, match=r"^attribute 'rank' would clash with the rank the COPC"):
        write_copc(tmp_path / "y.copc.laz", np.zeros((2, 3)), {"rank": np.zeros(2)}, np.ones(2), 0,
                   rank_radius="exact")
    # copclib is not needed to write (laspy and lazrs write COPC here); lazrs is
    monkeypatch.setitem(sys.modules, "copclib", None)
    monkeypatch.setitem(sys.modules, "lazrs", None)
    with pytest.raises(MissingDependencyError, match=r"^COPC export needs lazrs, which is not installed; install it with: pip install 'lodbuilder\[las\]'$"):
        write_copc(tmp_path / "y.copc.laz", np.zeros((2, 3)), {}, np.ones(2), 0)
    assert main(["export", arc, "-o", str(tmp_path / "z.copc.laz")]) == 2
    assert "COPC export needs lazrs" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_export_does_not_import_copclib_for_a_web_page(autzen, tmp_path):
    code = (
        "import sys; from lodbuilder.cli.main import main; "
        f"rc = main(['export', {str(autzen)!r}, '--size', '100', '-o', {str(tmp_path / 'a.html')!r}, '-q']); "
        "bad = [m for m in ('copclib', 'pyvista', 'numba', 'dask') if m in sys.modules]; "
        "sys.exit(rc or (3 if bad else 0))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_export_from_an_archive_over_http(tmp_path):
    """export reads the archive through open_archive, so an https:// (here http://127.0.0.1)
    archive gives the same files as the local one."""
    pytest.importorskip("fsspec")
    from rangeserver import RangeServer  # (tests/rangeserver.py)

    import lodbuilder
    from lodbuilder.datasets import demo_scan

    root = tmp_path / "served"
    root.mkdir()
    lodbuilder.build_archive(demo_scan(4000, seed=4), root / "d.h5", name="d")
    with RangeServer(root) as srv:
        for suffix in (".copc.laz", ".html"):
            outs = []
            for src in (str(root / "d.h5"), srv.url("d.h5")):
                out = tmp_path / f"{len(outs)}{suffix}"
                assert main(["export", src, "--size", "3000", "-o", str(out), "-q"]) == 0
                outs.append(out)
            if suffix == ".html":
                assert outs[0].read_bytes() == outs[1].read_bytes()
            else:
                a, b = (laspy.read(str(o)) for o in outs)
                assert np.array_equal(a.points.array, b.points.array)
