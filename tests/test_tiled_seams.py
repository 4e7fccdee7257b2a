"""The seams of the tiled build (issue 19, item 4): the merge's seam repair against its naive
reference, and the guarantees across tiles against brute force on inputs cut into many tiny tiles."""

from __future__ import annotations

import numpy as np
import pytest
from naive import naive_euclidean_fps, naive_seam_merge, prefix_covering_radii
from scipy.spatial import cKDTree
from test_tiled import _build, _tile_of, wavy

import lodbuilder
from lodbuilder.build.tiled import layout as WL


def _streams(rng, n_tiles=3, per_tile=120):
    """Tiles side by side along x (faces at x = 1, 2, ...), each ordered by exact FPS seeded with
    the head points inside it: rows (g, key, x, y, z, margin) by decreasing key, and the head."""
    pts = np.c_[rng.random(n_tiles * per_tile) * n_tiles, rng.random(n_tiles * per_tile),
                0.05 * rng.random(n_tiles * per_tile)]
    head = np.sort(rng.choice(len(pts), 6, replace=False))
    streams = []
    for t in range(n_tiles):
        idx = np.flatnonzero((pts[:, 0] >= t) & (pts[:, 0] < t + 1))
        seeds = [i for i, g in enumerate(idx) if g in head]
        order, radius, _ = naive_euclidean_fps(pts[idx], seeds)
        keep = [(j, r) for j, r in zip(order, radius, strict=True) if idx[j] not in head]
        rows = np.empty((len(keep), 6))
        for k, (j, r) in enumerate(keep):
            x = pts[idx[j]]
            m = x[0] - t if t > 0 else np.inf  # distance to the shared faces
            if t < n_tiles - 1:
                m = min(m, t + 1 - x[0])
            rows[k] = (idx[j], r, x[0], x[1], x[2], m)
        streams.append(rows)
    return pts, head, streams


def _store(tmp_path, pts, head, streams):
    from lodbuilder.build.tiled.store import as_store
    from lodbuilder.build.tiled.workdir import put_stream

    w = as_store(tmp_path)
    h = np.empty(len(head), WL.HEAD)
    h["g"], h["x"], h["y"], h["z"], h["r"], h["parent"] = head, *pts[head].T, 1.0, -1
    w.put(WL.HEAD_FILE, h)
    for t, rows in enumerate(streams):
        s = np.empty(len(rows), WL.STREAM)
        for c, name in enumerate(WL.STREAM.names):
            s[name] = rows[:, c]
        put_stream(w, WL.stream(t), s, 7)  # (frames of 7 rows at most: the bands' runs cut them)
        w.put(WL.seam(t), s[s["m"] < s["key"]])
    return w


def _stats(streams):
    """The tiles' order markers as the merge reads them: key histograms and seam rows."""
    return [{"key_hist": WL.key_hist(s[:, 1]), "n_seam": int((s[:, 5] < s[:, 1]).sum())} for s in streams]


def _boxes(n_tiles):
    """The boxes of _streams' tiles, side by side along x."""
    return [(np.array([t, 0.0, 0.0]), np.array([t + 1, 1.0, 0.05])) for t in range(n_tiles)]


@pytest.mark.parametrize(("seed", "alpha", "step", "band_rows"),
                         [(0, 0.25, 0.0, 40), (1, 0.5, 0.0, 2), (2, 1.0, 0.0, 40), (3, 0.5, 0.04, 40), (4, 0.25, 0.0, 8)])
def test_merge_matches_its_naive_reference(tmp_path, monkeypatch, seed, alpha, step, band_rows):
    """The merge (the seam repair over the tiles' seam points, then bands of keys side by side; tile
    buffers of 7 rows, an output buffer of 5 and bands of about ``band_rows`` rows: every refill and
    flush path, bins larger than a band) gives the naive merge of the whole streams: tiles ordered
    without seeing each other, their seam points demoted; without the repair, the tiles' keys merged
    as they are. With keys rounded to steps of ``step``, ties across tiles and a bin of zero keys."""
    from concurrent.futures import ThreadPoolExecutor

    from lodbuilder.build.tiled import merge as M
    from lodbuilder.build.tiled.sums import get_json, mark
    from lodbuilder.build.tiled.workdir import segment

    rng = np.random.default_rng(seed)
    pts, head, streams = _streams(rng)
    if step:
        for s in streams:
            s[:, 1] = np.where(np.isfinite(s[:, 1]), np.floor(s[:, 1] / step) * step, np.inf)
    monkeypatch.setattr(M, "BUF", 7)
    monkeypatch.setattr(M.W, "BLOCK", 5)
    monkeypatch.setattr(M, "LINK_ROWS", 1)  # (a group of seam links a tile)
    stats = [{**st, "files": {WL.stream(t): [0, 0]}} for t, st in enumerate(_stats(streams))]
    boxes = _boxes(len(streams))
    for a in (alpha, 0.0):
        (tmp_path / f"a{a}").mkdir()
        w = _store(tmp_path / f"a{a}", pts, head, streams)
        with ThreadPoolExecutor(2) as ex:
            res = M.merge_phase(ex, w, "s", len(pts), stats, a, np.zeros(3), 1e-6, band_rows=band_rows,
                                boxes=None if seed % 2 else boxes)
        d = w.read_array(WL.DEFERRED, WL.DEFER)
        mark(w, "merge", res)  # (the order's pieces are listed there; the streams and deferred points pruned)
        order = segment(w, M.order_files(w), "<i8", 0, len(pts))
        g, k = naive_seam_merge(streams, pts[head], a)
        np.testing.assert_array_equal(order[: len(head)], head)
        np.testing.assert_array_equal(order[len(head):], g)
        assert np.array_equal(np.sort(order), np.arange(len(pts)))
        was = {int(r[0]): r[1] for s in streams for r in s}
        late = [(gi, ki) for gi, ki in zip(g.tolist(), k.tolist(), strict=True) if ki < was[gi]]
        assert [(int(x), float(y)) for x, y in zip(d["g"], d["key"], strict=True)] == late
        assert (res["deferred"] > 0) == (a > 0), res  # the case demotes (the test sees that path)
        assert len(res["order"]) > 4  # (several bands)
        # each band reads its slices of the deferred points, by their acceptance keys and by their
        # tiles' keys: together every row once, in order
        seams = get_json(w, WL.marker(WL.SEAMS_PIECE))
        bands = M.plan_bands([st["key_hist"] for st in stats], seams["key_hist"], band_rows, seams["drop_hist"])
        for at in (2, 3):
            cuts = [x for band in bands for x in band[at]]
            assert cuts[0] == 0 and cuts[-1] == len(d) and cuts == sorted(cuts)
            assert all(cuts[i] == cuts[i + 1] for i in range(1, len(cuts) - 1, 2))
        if band_rows == 2:  # (bins of several keys larger than a band)
            b = WL.hist_bins(np.concatenate([s[:, 1] for s in streams]))
            assert max(len(np.unique(np.concatenate([s[:, 1] for s in streams])[b == x])) for x in b
                       if (b == x).sum() > band_rows) > 1
        if step:
            assert np.sum(np.concatenate([s[:, 1] for s in streams]) == 0) > 40  # (a bin of zero keys)


def _brute_links(streams, head_xyz, alpha):
    """The linked seam points by brute force: (tile, row of its seam points) of every seam point
    within ``alpha`` times the smaller key of another tile's seam point, or within ``alpha`` times
    its own (finite, positive) key of a head point."""
    seam = [s[s[:, 5] < s[:, 1]] for s in streams]
    rows = [(t, r, s[r]) for t, s in enumerate(seam) for r in range(len(s))]
    out = set()
    slack = 1 + 1e-9
    for t, r, p in rows:
        if not (np.isfinite(p[1]) and p[1] > 0):
            continue
        if np.min(np.linalg.norm(head_xyz - p[2:5], axis=1)) <= alpha * p[1] * slack:
            out.add((t, r))
        for u, v, q in rows:
            if u != t and np.linalg.norm(p[2:5] - q[2:5]) <= alpha * min(p[1], q[1]) * slack:
                out |= {(t, r), (u, v)}
    return seam, out


@pytest.mark.parametrize(("seed", "alpha", "step"), [(5, 0.25, 0.0), (6, 0.5, 0.0), (7, 1.0, 0.0), (8, 0.5, 0.03)])
def test_the_repair_of_the_linked_seam_points_is_the_repair_of_them_all(tmp_path, seed, alpha, step):
    """The seam links (one group a tile, each reading the tiles within its reach) find exactly the
    seam points that meet another tile's or a head point (brute force), fewer than all the seam
    points; and the repair of those alone defers the same points, at the same keys, in the same
    order as the repair of every seam point (with keys rounded to steps of ``step``: ties)."""
    from lodbuilder.build.tiled import merge as M

    rng = np.random.default_rng(seed)
    pts, head, streams = _streams(rng, n_tiles=4, per_tile=150)
    if step:
        for s in streams:
            s[:, 1] = np.where(np.isfinite(s[:, 1]), np.floor(s[:, 1] / step) * step, np.inf)
    w = _store(tmp_path, pts, head, streams)
    groups = M.link_groups(_stats(streams), _boxes(len(streams)), alpha, rows=1)
    assert [g[0] for g in groups] == [[0], [1], [2], [3]]
    found = set()
    for j, (mine, reads) in enumerate(groups):
        M.seam_links(str(tmp_path), j, mine, reads, alpha, np.zeros(3), 1e-6)
        found |= {(int(t), int(r)) for t, r in w.read_array(WL.links(j), WL.LINK)[["t", "row"]].tolist()}
    seam, want = _brute_links(streams, pts[head], alpha)
    assert found == want
    assert 0 < len(found) < sum(len(s) for s in seam)
    M.seam_repair(str(tmp_path), len(groups), alpha, np.zeros(3), 1e-6)
    d = w.read_array(WL.DEFERRED, WL.DEFER)
    every = [np.rec.fromarrays(s.T, dtype=WL.STREAM) for s in seam]
    g, key = M.seam_merge(every, w.read_array(WL.HEAD_FILE, WL.HEAD), alpha, np.zeros(3), 1e-6)
    was = {int(r[0]): r[1] for s in seam for r in s}
    late = [(int(x), float(k)) for x, k in zip(g, key, strict=True) if k < was[int(x)]]
    assert len(late) > 0
    assert [(int(x), float(k)) for x, k in zip(d["g"], d["key"], strict=True)] == late


def test_a_bins_ceiling_is_above_its_keys_by_less_than_its_width():
    """layout.hist_ceiling: above every key of the bin, by at most a 64th of an octave (0 for the
    bin of zero keys, inf for that of the infinite ones)."""
    k = 10.0 ** np.random.default_rng(2).uniform(-12, 12, 20_000)
    c = np.array([WL.hist_ceiling(int(b)) for b in WL.hist_bins(k)])
    assert np.all(k < c) and np.all(c <= k * (1 + 1 / 64) * (1 + 1e-12))
    assert WL.hist_ceiling(WL.BIN_ZERO) == 0.0 and WL.hist_ceiling(WL.BIN_INF) == np.inf


def test_the_seam_links_read_only_the_tiles_within_reach():
    """A group reads the tiles whose box comes within alpha times its tiles' largest finite key
    (the infinite keys' bin left out) of one of its tiles: tiles of width 1 in a row, keys up to
    1.9 and alpha 0.25 reach about 0.48: across a gap of 0.4, not across 0.6 or 1.4."""
    from lodbuilder.build.tiled import merge as M

    stats = [{"key_hist": WL.key_hist(np.array([1.9, 0.5, np.inf])), "n_seam": 10}] * 4
    boxes = [(np.array([x, 0.0, 0.0]), np.array([x + 1, 1.0, 1.0])) for x in (0.0, 1.0, 2.4, 4.0)]
    assert M.link_groups(stats, boxes, 0.25, rows=10) == [([0], [1]), ([1], [0, 2]), ([2], [1]), ([3], [])]
    assert M.link_groups(stats, boxes, 0.25, rows=20) == [([0, 1], [2]), ([2, 3], [1])]
    assert M.link_groups(stats, None, 0.25, rows=40) == [([0, 1, 2, 3], [])]
    assert M.link_groups(stats, boxes, 0.0) == []


def test_a_point_demoted_twice_ties_by_its_latest_demotion(tmp_path):
    """B (tile 1) is demoted by A to key 1, then by C to 0.5; E (tile 1) was demoted to 0.5 between
    B's two demotions, so at the tied key 0.5 E comes first, as in the naive merge (ties by order
    of demotion: the latest, not B's first)."""
    from lodbuilder.build.tiled import merge as M

    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.5, 0, 0], [2.0, 0, 0], [9.0, 9, 9]])  # A, B, C, E, a head point
    #                 g    key  x    y  z  margin (0: every row a seam point)
    tile0 = np.array([[0, 10.0, *pts[0], 0.0], [2, 5.0, *pts[2], 0.0]])
    tile1 = np.array([[1, 9.0, *pts[1], 0.0], [3, 4.0, *pts[3], 0.0]])
    head = np.array([4])
    w = _store(tmp_path, pts, head, [tile0, tile1])
    g, key = M.seam_merge([w.read_array(WL.seam(t), WL.STREAM) for t in (0, 1)], w.read_array(WL.HEAD_FILE, WL.HEAD),
                          1.0, np.zeros(3), 1e-6)
    ng, nk = naive_seam_merge([tile0, tile1], pts[head], 1.0)
    assert g.tolist() == ng.tolist() == [0, 2, 3, 1]
    assert key.tolist() == nk.tolist() == [10.0, 5.0, 0.5, 0.5]


def _chains(tkeys, thead, nxt):
    """The seam grid's cells: key -> the sorted points of its chain."""
    out = {}
    for s in np.flatnonzero(tkeys != -1):
        j, got = thead[s], []
        while j >= 0:
            got.append(int(j))
            j = nxt[j]
        out[int(tkeys[s])] = sorted(got)
    return out


def test_the_seam_grid_spreads_its_cells_and_rebuilds_as_it_inserts():
    """The seam repair's hash grid (``_kernels.tiled``): the cells of a row along any axis take
    distinct slots (a hash that left out the key's high bits put a row along x in one slot: 18-115
    probes an insertion on a survey's seam points), and its rebuild in slot order indexes every
    point in its cell as inserting the points one by one does."""
    from lodbuilder._kernels import tiled as K

    n = 4096
    mask = K.table_size(n) - 1
    for axis in range(3):
        cells = np.zeros((n, 3), np.int64)
        cells[:, axis] = np.arange(n)
        slots = {int(K._hash(K.key3(*map(int, c)), mask)) for c in cells}
        assert len(slots) > 0.7 * n, (axis, len(slots))  # (a random hash: 1 - e^-1/2 = 0.79 of n)
    rng = np.random.default_rng(5)
    xyz = rng.random((3000, 3)) * [50.0, 20.0, 2.0]
    lo = np.zeros(3)
    size = K.table_size(len(xyz))
    tables = []
    for rebuild in (False, True):
        tkeys, thead, nxt = np.full(size, -1, np.int64), np.full(size, -1, np.int64), np.full(len(xyz), -1, np.int64)
        if rebuild:
            tkeys[:5] = 7  # (stale keys: a rebuild starts from an empty table)
            K.grid_rebuild(tkeys, thead, nxt, xyz, lo, 0.7, size - 1, len(xyz))
        else:
            for j in range(len(xyz)):
                K.grid_insert(tkeys, thead, nxt, xyz, lo, 0.7, size - 1, j)
        tables.append(_chains(tkeys, thead, nxt))
    assert tables[0] == tables[1]
    assert sum(len(v) for v in tables[1].values()) == len(xyz) and len(tables[1]) > 500


def test_a_work_directory_with_the_old_histograms_is_refused(tmp_path):
    """Order markers from before the fine bins (``hist``, eight bins an octave, not ``key_hist``)
    would cut the streams at the wrong rows: the merge refuses them with the fix (--force)."""
    from concurrent.futures import ThreadPoolExecutor

    from lodbuilder.build.tiled import merge as M
    from lodbuilder.errors import BuildError

    pts, head, streams = _streams(np.random.default_rng(0))
    w = _store(tmp_path, pts, head, streams)
    stats = [{"hist": [b.tolist() for b in np.unique(WL.key_bins(s[:, 1]), return_counts=True)],
              "files": {WL.stream(t): [0, 0]}} for t, s in enumerate(streams)]
    with ThreadPoolExecutor(1) as ex, pytest.raises(BuildError, match=r"^scan 's': its work directory was left by "
                                                                      r"an older lodbuilder; run the build again with --force$"):
        M.merge_phase(ex, w, "s", len(pts), stats, 0.25, np.zeros(3), 1e-6)


def test_a_band_of_the_merge_may_take_part_of_a_key_bin():
    """The merge's bands take whole fine bins (``layout.hist_bins``: 64 an octave, eight inside each
    key bin that frames the streams), so a key bin holding more rows than a band is several bands
    (at 21.56M points the fullest key bin held 2.0M rows: one band task of 0.5 s, growing with the
    survey)."""
    from lodbuilder.build.tiled import merge as M

    rng = np.random.default_rng(1)
    x = np.concatenate([10.0 ** rng.uniform(-12, 12, 5000), [1.0, 0.5, 0.75, np.nextafter(1.0, 0.0)]])
    assert np.array_equal(WL.hist_bins(x) // 8, WL.key_bins(x))  # (nested: a frame never holds part of a fine bin)
    srt = np.sort(x)
    assert np.all(np.diff(WL.hist_bins(srt)) >= 0) and np.all(np.diff(WL.key_bins(srt)) >= 0)
    assert WL.hist_bins(np.array([np.inf]))[0] == WL.BIN_INF and WL.hist_bins(np.array([0.0]))[0] == WL.BIN_ZERO
    # two tiles' streams whose 12,000 keys all fall in one key bin, [1, 1.09): six fine bins
    streams = [np.sort(rng.uniform(1.0, 1.09, n))[::-1] for n in (7000, 5000)]
    assert len(np.unique(WL.key_bins(np.concatenate(streams)))) == 1
    hists = [WL.key_hist(k) for k in streams]
    bands = M.plan_bands(hists, [[], []], 2500)
    assert len(bands) >= 5
    for t, k in enumerate(streams):  # every row of each stream in exactly one band, in order
        runs = [(a, z) for rows, *_ in bands for tt, a, z in rows if tt == t]
        assert runs[0][0] == 0 and runs[-1][1] == len(k) and all(p[1] == q[0] for p, q in zip(runs, runs[1:], strict=False))
        for rows, (lo, hi), *_ in bands:  # the rows of a band are those whose keys fall in its bins
            for tt, a, z in rows:
                if tt == t:
                    assert lo <= WL.hist_bins(k[a:z]).min() and WL.hist_bins(k[a:z]).max() <= hi


def test_the_merge_buffers_stay_within_their_bytes():
    """The tiles' buffers of the merge take at most BUF_BYTES together (256 tiles at 65,536 rows
    each took 805 MB of a worker's 435 MB share), whatever the number of tiles."""
    from lodbuilder.build.tiled import merge as M

    assert M.buffer_rows(4) == M.BUF
    for n_tiles in (256, 1_000):
        assert M.buffer_rows(n_tiles) * n_tiles * WL.STREAM.itemsize <= M.BUF_BYTES
    assert M.buffer_rows(100_000) == 1024


def _cross_spacing(p, tile, radius, start):
    """The smallest distance between points of different tiles of each level of size k >= start,
    over the level's stored radius: the worst level."""
    tree = cKDTree(p)
    worst, run = np.inf, np.inf
    for k in range(1, len(p)):
        near = [i for i in tree.query_ball_point(p[k], radius[k + 1] if k + 1 < len(p) else radius[k])
                if i < k and tile[i] != tile[k]]
        if near:
            run = min(run, float(np.linalg.norm(p[near] - p[k], axis=1).min()))
        if k + 1 >= start and k + 1 < len(p):
            worst = min(worst, run / radius[k + 1])
    return worst


@pytest.mark.parametrize(("surface", "alpha"), [("wavy", None), ("patchy", 0.5)])
def test_seams_keep_points_of_different_tiles_apart(tmp_path, surface, alpha):
    """Many tiny tiles: every stored radius is a true covering radius of its prefix (brute force),
    every point is stored once, and points of different tiles (the head counting as one more) are
    at least alpha / (1 + alpha) x the level's radius apart at every level (0.2 at the default)."""
    rng = np.random.default_rng(11)
    pts = wavy(6000, rng)
    if surface == "patchy":  # uneven density: a sparse strip and a dense patch
        pts = np.concatenate([pts[pts[:, 0] > 0.3], pts[(pts[:, 0] <= 0.3) & (rng.random(len(pts)) < 0.15)]])
        pts = np.concatenate([pts, wavy(3000, rng) * [0.2, 0.2, 1.0] + [0.5, 0.5, 0.0]])
    d, _ = _build(tmp_path, pts, tile_points=400, **({} if alpha is None else {"seam_spacing": alpha}))
    tiled = d["build"]["tiled"]
    n = len(pts)
    assert tiled["tiles"] >= 16
    assert np.array_equal(np.sort(d["order"]), np.arange(n)) and d["n_ordered"] == n
    cr = prefix_covering_radii(pts, d["order"])
    assert np.all(cr[1:n] <= d["radius"][1:n] * (1 + 1e-12))
    p = pts[d["order"]]
    tile = _tile_of(p, tiled["tile_boxes"])
    tile[: tiled["head_points"]] = -1
    a = tiled["seam_alpha"]
    assert _cross_spacing(p, tile, d["radius"], tiled["head_points"]) >= a / (1 + a)
    # the repair merged the linked seam points alone (see merge.seam_links), and deferred some
    assert 0 < tiled["seam_deferrals"] <= tiled["seam_links"] < tiled["seam_points"], tiled


def test_seams_cover_like_the_in_memory_build(tmp_path):
    """At equal sizes from the head to 3 % of the points, the tiled order covers within 1.1 x of
    the in-memory order on a sheet cut into 16 tiles (1.05 today; a seam zone merged as one
    Euclidean greedy ordering, tried and dropped, gave 1.19)."""
    rng = np.random.default_rng(5)
    pts = wavy(40_000, rng)
    d, _ = _build(tmp_path, pts, tile_points=2600)
    h = d["build"]["tiled"]["head_points"]
    ref = lodbuilder.fastfps(pts).order
    worst = 0.0
    for k in np.unique(np.geomspace(h, 0.03 * len(pts), 10).astype(int)):
        a = cKDTree(pts[d["order"][:k]]).query(pts)[0].max()
        b = cKDTree(pts[ref[:k]]).query(pts)[0].max()
        worst = max(worst, a / b)
    assert worst <= 1.1, worst
