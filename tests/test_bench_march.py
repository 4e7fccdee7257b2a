"""tools/bench_march.py: the same fronts marched one by one and in batches, on a small sheet."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import bench_march  # noqa: E402


def test_the_march_benchmark_compares_batched_and_one_by_one_marches():
    from lodbuilder._kernels.march import BATCH_SOURCES

    rng = np.random.default_rng(3)
    n = 20_000
    pts = np.c_[rng.uniform(0, 1, n), rng.uniform(0, 1, n), 0.001 * rng.standard_normal(n)]
    out = bench_march.measure(pts, [3, BATCH_SOURCES, 60], repeat=2)
    assert out["n_points"] == n and out["voxels"] > 0
    rows = {r["fronts"]: r for r in out["rows"]}
    assert [r["batched"] for r in out["rows"]] == [False, True, True]
    for r in out["rows"]:
        assert len(r["one_by_one_us_per_pop"]) == len(r["batched_us_per_pop"]) == 2
        assert r["median_one_by_one"] > 0 and r["median_batched"] > 0
    # below BATCH_SOURCES fronts both ways are the same march (values equal); batched ones move a little
    assert rows[3]["value_ratio_min"] == rows[3]["value_ratio_max"] == 1.0
    assert rows[60]["value_ratio_max"] > 1.0 and 0.95 < rows[60]["value_ratio_min"] <= 1.0
    assert abs(rows[60]["value_ratio_mean"] - 1) < 0.005
