"""tools/bench_seams.py's measures against brute force (never its times)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import bench_seams  # noqa: E402


def _naive_cross_spacing(p, group, radius, upto):
    """For each level size k (1 .. upto): min distance between two of its first k points of
    different groups over radius[k], capped at 1 (inf / 1 where no such pair)."""
    out = np.empty(upto)
    for k in range(1, upto + 1):
        best = np.inf
        for i in range(k):
            for j in range(i):
                if group[i] != group[j]:
                    best = min(best, float(np.linalg.norm(p[i] - p[j])))
        out[k - 1] = min(best / radius[k], 1.0)
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cross_spacing_is_the_brute_force_minimum_over_each_level(seed):
    rng = np.random.default_rng(seed)
    n = 60
    p = rng.random((n, 3))
    group = rng.integers(0, 3, n)
    radius = np.concatenate([[np.inf], np.sort(rng.random(n - 1) * 0.6)[::-1]])
    e, partner = bench_seams.cross_pairs(p, group, radius, n - 1)
    got = bench_seams.cross_spacing(e, radius, n - 1)
    want = _naive_cross_spacing(p, group, radius, n - 1)
    assert np.array_equal(np.isinf(got), np.isinf(want))
    assert np.allclose(got, want)
    for k in np.flatnonzero(partner >= 0):  # each partner: an earlier point of another group at that distance
        assert partner[k] < k and group[partner[k]] != group[k]
        assert np.isclose(np.linalg.norm(p[k] - p[partner[k]]), e[k])
