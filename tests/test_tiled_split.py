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


@pytest.mark.parametrize("seed", range(3))
def test_split_puts_each_point_in_its_core_and_every_halo_whose_grown_box_holds_it(seed):
    rng = np.random.default_rng(seed)
    lo, hi = _boxes(rng, 4)
    pts = rng.uniform([0, 0, 0], [10, 10, 2], (5000, 3))
    own = np.array([int(np.flatnonzero(np.all((p >= lo) & (p <= hi), axis=1))[0]) for p in pts])
    halo = float(rng.uniform(0.2, 1.5))
    out, n_core, n_halo = _Collect(), np.zeros(len(lo), np.int64), np.zeros(len(lo), np.int64)
    _split(out, 3, 1000, pts, own, lo, hi, halo, n_core, n_halo)
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
