"""The covering pass of a tiled build (``_kernels.tiled.cover_pass``: an insertion phase, then a
tail phase once the covering radius is below ``TAIL`` cells) against a brute-force reference."""

from __future__ import annotations

import numpy as np
import pytest
from naive import naive_band_radii, naive_cover_pass

from lodbuilder._kernels import tiled as K


def _survey(seed: int, n: int, dups: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of two sheets and a cluster (``dups`` exact duplicates), in a farthest-point-like
    rank order with random ranks mixed in; the first 70 % of the x range is the core."""
    rng = np.random.default_rng(seed)
    a = np.column_stack([rng.uniform(0, 10, n // 2), rng.uniform(0, 6, n // 2), rng.normal(0, 0.05, n // 2)])
    b = np.column_stack([rng.uniform(0, 10, n // 3), rng.uniform(0, 6, n // 3), 1.5 + rng.normal(0, 0.05, n // 3)])
    c = rng.normal([4, 3, 0.5], 0.05, (n - a.shape[0] - b.shape[0], 3))
    xyz = np.concatenate([a, b, c])
    xyz[rng.choice(xyz.shape[0], dups, replace=False)] = xyz[0]
    # a greedy (farthest point) order over a coarse sample, then the rest at random: ties and late
    # far points both occur
    order = rng.permutation(xyz.shape[0])
    rank = np.sort(rng.choice(10 * xyz.shape[0], xyz.shape[0], replace=False))
    core = xyz[order, 0] < 7.0
    return np.ascontiguousarray(xyz[order]), rank.astype(np.int64), np.ascontiguousarray(core)


def _fps_like(xyz: np.ndarray, seed: int) -> np.ndarray:
    """An order of ``xyz`` that is farthest-point-first over a random half, the rest appended."""
    rng = np.random.default_rng(seed)
    idx = rng.permutation(xyz.shape[0])
    half, rest = idx[: len(idx) // 2], idx[len(idx) // 2:]
    d = np.full(half.size, np.inf)
    out = []
    cur = 0
    for _ in range(half.size):
        out.append(half[cur])
        d = np.minimum(d, np.linalg.norm(xyz[half] - xyz[half[cur]], axis=1))
        cur = int(np.argmax(d))
        if d[cur] == 0.0:
            break
    seen = set(out)
    return np.array(out + [i for i in half if i not in seen] + list(rest))


def _run(xyz: np.ndarray, rank: np.ndarray, core: np.ndarray, cell: float):
    n, nc = xyz.shape[0], int(core.sum())
    ev_rank, ev_val = np.empty(n + 1, np.int64), np.empty(n + 1)
    pt_rank, pt_parent, pt_space = np.empty(nc, np.int64), np.empty(nc, np.int64), np.empty(nc)
    ne, npt = K.cover_pass(xyz, rank, core, cell, ev_rank, ev_val, pt_rank, pt_parent, pt_space)
    return ev_rank[:ne], ev_val[:ne], pt_rank[:npt], pt_parent[:npt], pt_space[:npt]


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("cell", [0.05, 0.4, 3.0])
@pytest.mark.parametrize("greedy", [False, True])
def test_the_covering_pass_is_the_brute_force_one(seed: int, cell: float, greedy: bool) -> None:
    xyz, rank, core = _survey(seed, 900, dups=12)
    if greedy:
        o = _fps_like(xyz, seed)
        xyz, core = np.ascontiguousarray(xyz[o]), np.ascontiguousarray(core[o])
    got = _run(xyz, rank, core, cell)
    want = naive_cover_pass(xyz, rank, core)
    for name, g, w in zip(["ev_rank", "ev_val", "pt_rank", "pt_parent", "pt_space"], got, want, strict=True):
        assert np.array_equal(g, w), name


def test_both_phases_run_and_the_tail_starts_below_its_radius() -> None:
    """At a coarse cell the tail starts early (most points are its), at a fine one late: both
    phases are exercised by the test above."""
    xyz, rank, core = _survey(0, 900, dups=12)
    o = _fps_like(xyz, 0)
    xyz, core = np.ascontiguousarray(xyz[o]), np.ascontiguousarray(core[o])
    n, nc = xyz.shape[0], int(core.sum())
    starts = []
    for cell in (0.05, 3.0):
        bufs = [np.empty(n + 1, np.int64), np.empty(n + 1), np.empty(nc, np.int64), np.empty(nc, np.int64), np.empty(nc)]
        ne, npt, i0, last, d0, p0 = K.cover_head(xyz, rank, core, cell, K.TAIL * cell, *bufs)
        assert last <= K.TAIL * cell or i0 == n
        assert np.all(d0[core[i0:]] <= K.TAIL * cell)
        starts.append(i0)
    assert starts[1] < n // 10 < starts[0] < n


def test_stable_argsort_is_numpys() -> None:
    rng = np.random.default_rng(3)
    for top in (1, 2000, 1 << 40):
        key = rng.integers(0, top, 5000).astype(np.int64)
        assert np.array_equal(K.stable_argsort(key), np.argsort(key, kind="stable"))


@pytest.mark.parametrize("tiles", [1, 3, 17])
@pytest.mark.parametrize("share", [0.0, 0.01, 0.5])
def test_merge_events_is_the_largest_radius_over_the_tiles(tiles: int, share: float) -> None:
    rng = np.random.default_rng(tiles * 100 + int(share * 100))
    k0, k1 = 100, 2_100
    cur = np.where(rng.random(tiles) < 0.3, np.inf, rng.uniform(5, 15, tiles))
    events = []
    for _ in range(tiles):
        m = rng.binomial(k1 - k0, share / tiles)
        ranks = np.sort(rng.choice(np.arange(k0, k1), m, replace=False))
        events.append((ranks, np.sort(rng.uniform(0, 10, m))[::-1] + rng.uniform(0, 0.5, m)))  # some rise
    rank = np.concatenate([r for r, _ in events]).astype(np.int64)
    value = np.concatenate([v for _, v in events])
    tile = np.repeat(np.arange(tiles, dtype=np.int64), [r.shape[0] for r, _ in events])
    by_rank = np.argsort(rank, kind="stable")
    got, after = np.empty(k1 - k0), cur.copy()
    K.merge_events(rank[by_rank], tile[by_rank], np.ascontiguousarray(value[by_rank]), after, k0, k1, got)
    assert np.array_equal(got, naive_band_radii(cur, events, k0, k1))
    last = [v[-1] if v.shape[0] else c for (_, v), c in zip(events, cur, strict=True)]
    assert np.array_equal(after, last)
