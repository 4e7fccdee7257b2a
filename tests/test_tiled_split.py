"""How a read block's points go to the tiles (lodbuilder.build.tiled.blocks._split): every point to
its own tile's core, and to the halo of every other tile whose box grown by the halo width holds it,
in input order, against that definition evaluated point by point."""

from __future__ import annotations

import numpy as np
import pytest

from lodbuilder.build.tiled import layout as WL
from lodbuilder.build.tiled.blocks import _split


class _Collect:
    def __init__(self):
        self.got: dict[str, list[np.ndarray]] = {}

    def write(self, name, data):
        self.got.setdefault(name, []).append(np.frombuffer(data.tobytes(), WL.REC))


def _boxes(rng, k):
    """k x k tiles splitting [0, 10]^2 at uneven cuts (z: one slab)."""
    cuts = np.sort(np.concatenate([[0.0, 10.0], rng.uniform(1, 9, k - 1)]))
    lo = np.array([[cuts[i], cuts[j], 0.0] for i in range(k) for j in range(k)])
    hi = np.array([[cuts[i + 1], cuts[j + 1], 2.0] for i in range(k) for j in range(k)])
    return lo, hi


@pytest.mark.parametrize(("seed", "k", "widest"), [(0, 4, 1.5), (1, 4, 1.5), (2, 4, 1.5), (3, 7, 0.5), (4, 3, 6.0)])
def test_split_puts_each_point_in_its_core_and_every_halo_whose_grown_box_holds_it(seed, k, widest):
    rng = np.random.default_rng(seed)
    lo, hi = _boxes(rng, k)
    pts = rng.uniform([0, 0, 0], [10, 10, 2], (5000, 3))
    own = np.array([int(np.flatnonzero(np.all((p >= lo) & (p <= hi), axis=1))[0]) for p in pts])
    halo = float(rng.uniform(0.2, widest))
    out, n_core, n_halo = _Collect(), np.zeros(len(lo), np.int64), np.zeros(len(lo), np.int64)
    _split(out, 3, 1000, pts, own, lo, hi, halo, 0.0, n_core, n_halo)
    for t in range(len(lo)):
        want_core = np.flatnonzero(own == t)
        want_halo = [i for i in range(len(pts)) if own[i] != t
                     and np.all(pts[i] >= lo[t] - halo) and np.all(pts[i] <= hi[t] + halo)]
        core = np.concatenate(out.got.get(WL.core(t, 3), [np.zeros(0, WL.REC)]))
        got_halo = np.concatenate(out.got.get(WL.halo(t, 3), [np.zeros(0, WL.REC)]))
        np.testing.assert_array_equal(core["g"], want_core + 1000)
        np.testing.assert_array_equal(got_halo["g"], np.asarray(want_halo, np.int64) + 1000)
        np.testing.assert_array_equal(got_halo["x"], pts[want_halo, 0])
        assert n_core[t] == want_core.size and n_halo[t] == len(want_halo)
    assert sum(len(v) for k, v in out.got.items() if k.startswith("halo")) > 0


@pytest.mark.parametrize("seed", range(4))
def test_in_sorted_is_isin_and_searchsorted(seed):
    """The tile's head seeds found by binary search (lodbuilder.build.tiled.tasks.in_sorted), as
    np.isin and np.searchsorted give them."""
    from lodbuilder.build.tiled.tasks import in_sorted

    rng = np.random.default_rng(seed)
    ref = np.sort(rng.choice(10_000, int(rng.integers(0, 3000)), replace=False)).astype(np.int64)
    values = rng.choice(10_000, 500, replace=False).astype(np.int64)  # (any order, like a head's)
    found, pos = in_sorted(values, ref)
    np.testing.assert_array_equal(found, np.isin(values, ref))
    np.testing.assert_array_equal(pos, np.searchsorted(ref, values[np.isin(values, ref)]))


@pytest.mark.parametrize("monotone", [True, False])
def test_stream_is_the_core_points_in_order_of_key(monotone):
    """A tile's stream (lodbuilder.build.tiled.tasks._stream): its core points that are not seeds,
    by non-increasing key, ties in the tile's order, against that definition written out."""
    from types import SimpleNamespace

    from lodbuilder.build.tiled.tasks import _margins, _stream

    rng = np.random.default_rng(7)
    n_core, n = 400, 460  # (rows from n_core on: head points and timed seeds)
    order = rng.permutation(n)
    radius = np.sort(rng.uniform(0, 5, n))[::-1].round(1)  # (ties)
    radius[:3] = np.inf  # the seeds
    if not monotone:
        radius[50] = 7.0  # (a key out of order: one the tiled stream sorts)
    is_seed = np.zeros(n, bool)
    is_seed[order[:3]] = True
    o = SimpleNamespace(order=order, radius=radius, __len__=lambda: n)
    core = np.zeros(n_core, WL.REC)
    core["g"] = np.arange(n_core) * 3
    cpts = rng.uniform(0, 10, (n_core, 3))
    core["x"], core["y"], core["z"] = cpts.T
    lo, hi = np.zeros(3), np.full(3, 10.0)
    interior = np.array([[True, False, False], [False, True, False]])
    got = _stream(o, is_seed, core, cpts, np.zeros((1, 3)), lo, hi, interior)
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    sel = order[(order < n_core) & ~is_seed[order]]
    key = radius[rank[sel]]
    assert monotone == bool((key[1:] <= key[:-1]).all())
    srt = np.argsort(-key, kind="stable")
    np.testing.assert_array_equal(got["g"], core["g"][sel][srt])
    np.testing.assert_array_equal(got["key"], key[srt])
    np.testing.assert_array_equal(np.stack([got["x"], got["y"], got["z"]], 1), cpts[sel][srt])
    np.testing.assert_array_equal(got["m"], _margins(cpts[sel][srt], lo, hi, interior))
