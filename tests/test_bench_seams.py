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


def test_reference_spread_compares_orders_at_the_case_levels(tmp_path, monkeypatch):
    import lodbuilder
    from lodbuilder.io import write_points

    pts = np.random.default_rng(4).random((3000, 3)) * [1, 1, 0.01]
    f = write_points(tmp_path / "p.npy", pts)
    ref = {"order": lodbuilder.fastfps(pts).order}
    case = {"head_points": 40, "sweep": [[20, 1.0, 0.0], [40, 1.0, 0.0], [90, 1.0, 0.0], [200, 1.0, 0.0]]}
    out = bench_seams.reference_spread(f, ref, case, 2)
    assert out["levels"] == 3 and len(out["orders"]) == 2
    assert len({o["start"] for o in out["orders"]}) == 2
    # an order that is the reference's gives 1 at every level; one that is not, something else
    monkeypatch.setattr(lodbuilder, "fastfps", lambda p, seeds: type("R", (), {"order": ref["order"]}))
    same = bench_seams.reference_spread(f, ref, case, 1)
    assert same["worst"] == 1.0 and same["orders"][0]["best"] == 1.0
    assert out["worst"] != 1.0 or min(o["best"] for o in out["orders"]) != 1.0


def test_bench_survey_seams_measures_archives_as_bench_seams_does(tmp_path, capsys):
    import json

    import bench_survey_seams

    import lodbuilder
    from lodbuilder.io import write_points

    xy = np.random.default_rng(8).random((5000, 2))
    pts = np.column_stack([xy, 0.05 * np.sin(6 * xy[:, 0]) * np.cos(5 * xy[:, 1])])  # (a wavy sheet)
    f = write_points(tmp_path / "p.npy", pts)
    for name, kw in (("one", {}), ("rounds", {"seam_rounds": True})):
        lodbuilder.build_archive(f, tmp_path / f"{name}.h5", _tile_points=600, name=name, **kw)
    assert bench_survey_seams.main([str(tmp_path / "one.h5"), str(tmp_path / "rounds.h5"), "--sample", "1000"]) == 0
    doc = json.loads(capsys.readouterr().out)
    one, rounds = doc["archives"]
    assert one["tiles"] >= 8 and one["rounds"] is None and rounds["rounds"]["q"] == 1.05
    assert one["cover_over_first_worst"] == one["cover_over_first_mean"] == 1.0
    assert [c[0] for c in one["covering"]] == [c[0] for c in rounds["covering"]]
    # the spacing is bench_seams' measure over the levels from the head to 3 %, brute force here
    with lodbuilder.open_archive(tmp_path / "rounds.h5") as arc:
        v = arc.scan()
        p, radius, tiled = v.points(), v.radius[:], v.build["tiled"]
    h, top = tiled["head_points"], max(int(0.03 * len(p)), tiled["head_points"] + 2)
    group = bench_seams.tile_of(p, tiled["tile_boxes"])
    group[:h] = -1
    naive = _naive_cross_spacing(p[:top], group[:top], radius, top)
    assert rounds["cross_spacing_min"] == round(float(naive[h - 1:top].min()), 4)
