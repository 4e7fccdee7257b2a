"""A tiled build knows the pieces of its band as an in-memory build does (issue 20, item 5): the
tiles' local pieces joined across tiles give the same pieces as the band of the whole scan, and
the rank at which each entered the merged order, so that slice and evaluate say how many pieces a
level of a tiled archive reaches."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from clirun import run as run_cli

import lodbuilder

REPO = Path(__file__).resolve().parents[1]


def _fragmented(seed: int, pieces: int, points: int) -> np.ndarray:
    spec = importlib.util.spec_from_file_location("make_fragmented", REPO / "tools" / "make_fragmented.py")
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(mod)
    return mod.fragmented_scene(seed, pieces, points)


def _band_labels(pts: np.ndarray, h: float, r: float) -> np.ndarray:
    """The piece of every point in the band of the whole scan (the in-memory build's band)."""
    from lodbuilder._kernels.topology import point_pieces
    from lodbuilder.sampling.band import build_band

    band = build_band(pts, h, r)
    piece, _ = point_pieces(band.nbr, band.cs, band.near, band.vcost)
    out = np.empty(pts.shape[0], np.int64)
    out[band.perm] = piece
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiled_pieces")
    pts = _fragmented(2, 100, 20_000)
    np.save(d / "fr.npy", pts)
    out = {}
    for tiles in (3000, 600):  # 8 and 57 tiles
        arc = d / f"t{tiles}.h5"
        res = lodbuilder.build_archive(d / "fr.npy", arc, _tile_points=tiles)
        assert res.scans[0].method == "tiled"
        with lodbuilder.open_archive(arc) as a:
            s = a.scan()
            out[tiles] = (arc, s.build, np.asarray(s.source_index[:]))
    return d, pts, out


@pytest.mark.parametrize("tiles", [3000, 600])
def test_tiled_pieces_are_the_whole_band_s(scene, tiles):
    d, pts, built = scene
    _, build, order = built[tiles]
    assert build["tiled"]["tiles"] >= (8 if tiles == 3000 else 40)
    h, r = build["voxel_size"], build["band_radius"]
    labels = _band_labels(pts, h, r)
    stats = build["engine_stats"]
    assert stats["pieces"] == int(np.unique(labels).size) > 50
    # the first rank of every piece in the tiled order, by brute force
    _, first = np.unique(labels[order], return_index=True)
    assert stats["piece_entries"] == sorted(first.tolist())


def test_pieces_joined_across_a_gap_between_tiles(tmp_path):
    """Columns of points in pairs 3.5 apart (one piece each: the band of radius 2.5 spans the gap)
    and 8 apart between pairs, each column a tile of its own: the tiles' boundaries fall in the
    gaps, so only the points a tile borrows from beyond its box join a pair."""
    pts = _columns()
    np.save(tmp_path / "c.npy", pts)
    lodbuilder.build_archive(tmp_path / "c.npy", tmp_path / "c.h5", _tile_points=100, voxel_size=1.0, band_radius=2.5)
    with lodbuilder.open_archive(tmp_path / "c.h5") as a:
        build = a.scan().build
    assert build["tiled"]["tiles"] >= 20
    assert np.unique(_band_labels(pts, 1.0, 2.5)).size == build["engine_stats"]["pieces"] == 10


def test_tiled_and_in_memory_builds_count_the_same_pieces(scene, tmp_path):
    d, pts, built = scene
    _, build, _ = built[600]
    ref = tmp_path / "m.h5"
    lodbuilder.build_archive(d / "fr.npy", ref, voxel_size=build["voxel_size"], band_radius=build["band_radius"])
    with lodbuilder.open_archive(ref) as a:
        mem = a.scan().build["engine_stats"]
    tiled = build["engine_stats"]
    assert mem["pieces"] == tiled["pieces"]
    # every piece entered by the same level in both (orders differ in between)
    assert max(mem["piece_entries"]) < 500 and max(tiled["piece_entries"]) < 500


def test_slice_and_evaluate_say_the_pieces_of_a_tiled_level(scene, capsys, tmp_path):
    d, pts, built = scene
    arc, build, order = built[3000]
    entries, total = build["engine_stats"]["piece_entries"], build["engine_stats"]["pieces"]
    reached = sum(e < 40 for e in entries)
    rc, out, err = run_cli(capsys, "slice", arc, "--size", 40, "-o", tmp_path / "x.ply")
    assert rc == 0, err
    assert out.strip().endswith(f"; reaches {reached} of the scan's {total} pieces)")
    rc, out, err = run_cli(capsys, "evaluate", arc, "--sizes", "1", "40")
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[1].rstrip().endswith("pieces")
    assert lines[2].rstrip().endswith(f"1/{total}") and lines[3].rstrip().endswith(f"{reached}/{total}")


def test_a_tile_shares_only_its_points_near_faces_other_tiles_touch(tmp_path, monkeypatch):
    """The join holds the points near the tiles' shared faces, not every point: a sheet's tiles
    are thin in z, and all their points lie near the box's top and bottom (the 100M-point survey's
    join held every point: 5 GB on one worker)."""
    rng = np.random.default_rng(3)
    xy = rng.random((160_000, 2))
    pts = np.c_[xy, 0.01 * np.sin(6 * xy[:, 0])]
    np.save(tmp_path / "s.npy", pts)

    def stop(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr("lodbuilder.build.tiled.bands.write_phase", stop)  # (the pieces phase is done)
    with pytest.raises(KeyboardInterrupt):
        lodbuilder.build_archive(tmp_path / "s.npy", tmp_path / "s.h5", _tile_points=40_000)
    (work,) = (tmp_path / ".s.h5.parts").glob("*.work")
    links = sum(f.stat().st_size for f in work.glob("pieces.*.links.bin")) // 16
    n_tiles = len(list(work.glob("pieces.*.links.bin")))
    assert n_tiles >= 4
    # each tile's points near its shared faces, and those it borrows: a seam band, not the sheet
    assert 0 < links < 0.6 * pts.shape[0]
    monkeypatch.undo()
    lodbuilder.build_archive(tmp_path / "s.npy", tmp_path / "s.h5", _tile_points=40_000)  # resumed
    with lodbuilder.open_archive(tmp_path / "s.h5") as a:
        build = a.scan().build
    assert build["engine_stats"]["pieces"] == np.unique(_band_labels(pts, build["voxel_size"], build["band_radius"])).size


def _columns() -> np.ndarray:
    """Columns of points in pairs 3.5 apart and 8 apart between pairs (10 band pieces at h 1, r 2.5)."""
    y = np.arange(0, 50, 0.5)
    x = np.cumsum([0.0] + [3.5 if i % 2 == 0 else 8.0 for i in range(19)])
    return np.vstack([np.c_[np.full(y.size, xi), y, np.zeros(y.size)] for xi in x])


def _local_pieces(work, pts, h, r, edges, halo, rank, ordered=False):
    """Every tile's local pieces (tiles: the cells of ``edges`` in x and y), from its own points
    and the other tiles' points within ``halo`` of its box, written to ``work``; the tile count and
    for each tile the points it labels whole and the bands its links touch. ``ordered``: each tile's ordering has labelled its core
    first, in the band of its points and a few of the others' (as head points) on the scan's grid."""
    from lodbuilder.build.tiled import layout as WL
    from lodbuilder.build.tiled.pieces import borrowed_points, tile_pieces
    from lodbuilder.build.tiled.store import as_store
    from lodbuilder.build.tiled.workdir import REC, put_zipped
    from lodbuilder.sampling.band import band_pieces

    rec = np.empty(pts.shape[0], REC)
    rec["g"] = np.arange(pts.shape[0])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ij = [np.clip(np.searchsorted(edges[a], pts[:, a], "right") - 1, 0, len(edges[a]) - 2) for a in range(2)]
    t = 0
    touched = []
    for i in range(len(edges[0]) - 1):
        for j in range(len(edges[1]) - 1):
            box_lo = np.array([edges[0][i], edges[1][j], lo[2]])
            box_hi = np.array([edges[0][i + 1], edges[1][j + 1], hi[2]])
            own = (ij[0] == i) & (ij[1] == j)
            near = ~own & np.all((pts >= box_lo - halo) & (pts <= box_hi + halo), axis=1)
            interior = [[i > 0, j > 0, False], [i < len(edges[0]) - 2, j < len(edges[1]) - 2, False]]
            spec = {"lo": box_lo.tolist(), "hi": box_hi.tolist(), "interior": interior, "voxel_size": h, "band_radius": r,
                    "lattice": lo.tolist(), "max_memory": None, "halo": halo, "neighbours": []}
            if ordered:  # (the head: every 50th point of the scan, those in the box grown by the halo)
                head = ~own & (np.arange(pts.shape[0]) % 50 == 0) & near
                core = np.flatnonzero(own)
                ext = np.concatenate([core, np.flatnonzero(head)])
                put_zipped(as_store(work), WL.band_labels(t),
                           band_pieces(pts[ext], h, r, lattice=lo)[0][: core.size].astype("<i4"))
            borrowed, b_rank = borrowed_points(work, rec[near], rank[near], spec)
            touched.append((int(own.sum() + near.sum()), tile_pieces(work, t, rec[own], rank[own], borrowed, b_rank, spec)[1]))
            t += 1
    return t, touched


@pytest.mark.parametrize(("bands", "ordered"), [(1, False), (7, False), ("marked", False), (7, True), ("marked", True)])
@pytest.mark.parametrize("scene_name", ["fragmented 2x2", "fragmented 4x4", "columns"])
def test_pieces_from_a_halo_wider_than_the_reach_are_the_whole_band(tmp_path, monkeypatch, scene_name, bands, ordered):
    """The covering tasks take the points of other tiles from their halo when it is at least the
    pieces' reach wide (a survey's halo is: 41 vs 29.5 on the 4 x 4 survey): each tile's local
    pieces from its own points and its halo, joined, are the whole scan's band pieces, and each
    piece's first rank is the least rank of its points (ranks: a random permutation). The
    columns' tiles are cut in the middle of every gap: only the halo joins a pair. The join runs
    in one band of input indices or in 7 (the band's size patched; each task sees a slice of
    every tile's shared points), or in 7 where the covering tasks' markers say which tiles' links
    each band holds (a band's task reads only those). ``ordered``: the tiles' orderings labelled
    their cores (with head points from beyond them), and a covering task labels only the strip
    near its shared faces and joins the two: the same pieces from fewer points labelled."""
    from lodbuilder.build.executors import InlineExecutor
    from lodbuilder.build.tiled import layout as WL
    from lodbuilder.build.tiled import pieces
    from lodbuilder.build.tiled.pieces import join_phase, reach
    from lodbuilder.build.tiled.sums import put_json
    from lodbuilder.sampling.band import choose_parameters

    if scene_name == "columns":
        pts = _columns()
        h, r = 1.0, 2.5
        xs = np.unique(pts[:, 0])
        edges = [np.r_[xs[0], (xs[1:] + xs[:-1]) / 2, xs[-1]], np.array([pts[:, 1].min(), pts[:, 1].max()])]
    else:
        pts = _fragmented(3, 60, 12_000)
        h, r = choose_parameters(pts, None, None)
        cuts = int(scene_name[-1])
        edges = [np.linspace(pts[:, a].min(), pts[:, a].max(), cuts + 1) for a in range(2)]
    labels = _band_labels(pts, h, r)
    rank = np.random.default_rng(0).permutation(pts.shape[0])
    monkeypatch.setattr(pieces, "BLOCK", -(-pts.shape[0] // (7 if bands == "marked" else bands)))
    labelled = []
    band_pieces = pieces._band_pieces
    monkeypatch.setattr(pieces, "_band_pieces", lambda xyz, *a: labelled.append(len(xyz)) or band_pieces(xyz, *a))
    n_tiles, touched = _local_pieces(tmp_path, pts, h, r, edges, reach(h, r), rank, ordered)
    # the covering tasks labelled every point and those they borrow, or (ordered) a strip only
    whole = sum(n for n, _ in touched)  # (each tile's own points and those it borrows)
    if ordered:  # (the columns' tiles lie within the reach of their faces: all strip)
        assert sum(labelled) <= (0.7 if scene_name == "fragmented 2x2" else 1.0) * whole
    else:
        assert sum(labelled) == whole
    reads = []
    if bands == "marked":
        for t in range(n_tiles):
            put_json(tmp_path, WL.marker(WL.cover_piece(t)), {"link_bands": touched[t][1]})
        join_band = pieces.join_band
        monkeypatch.setattr(pieces, "join_band", lambda *a: reads.append(a[-1]) or join_band(*a))
    joined = join_phase(InlineExecutor(), str(tmp_path), "scan", pts.shape[0], n_tiles)
    assert len(list(tmp_path.glob("pieces.join.*.bin"))) == (7 if bands == "marked" else bands)
    if bands == "marked":  # (every tile's links in the bands it touches, and only there)
        assert sorted(t for tiles in reads for t in tiles) == sorted(t for t in range(n_tiles) for _ in touched[t][1])
        assert sum(map(len, reads)) < 7 * n_tiles
    assert joined["pieces"] == np.unique(labels).size >= 10
    first = np.full(labels.max() + 1, pts.shape[0])
    np.minimum.at(first, labels, rank)
    assert joined["piece_entries"] == sorted(first.tolist())


@pytest.mark.parametrize("seed", range(4))
def test_dense_labels_renumber_as_unique_does(seed):
    """The strip's labels renumbered without a sort: what np.unique(..., return_inverse=True) gives
    (the labels that occur, in increasing order), labels no point holds dropped."""
    from lodbuilder.build.tiled.pieces import dense_labels

    rng = np.random.default_rng(seed)
    n_labels = int(rng.integers(1, 50))
    label = rng.choice(rng.choice(n_labels, size=max(1, n_labels // 3), replace=False), size=int(rng.integers(0, 200)))
    got, k = dense_labels(label, n_labels)
    held, want = np.unique(label, return_inverse=True)
    assert k == held.shape[0]
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, want)


def test_dense_labels_of_no_points():
    from lodbuilder.build.tiled.pieces import dense_labels

    got, k = dense_labels(np.zeros(0, np.int64), 0)
    assert k == 0 and got.shape == (0,)
    got, k = dense_labels(np.zeros(0, np.int64), 5)
    assert k == 0 and got.shape == (0,)
