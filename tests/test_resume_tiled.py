"""Radius rounds in the tiled build (lodbuilder.build.tiled.rounds, private): the guarantees hold
(brute force) and points of different tiles keep their distance where one pass crowds them."""

from __future__ import annotations

import numpy as np
from naive import prefix_covering_radii
from scipy.spatial import cKDTree
from test_tiled import _build, _tile_of, wavy


def _cross_spacing(d, upto):
    """The smallest distance of each level's newest point to an earlier point of another tile (the
    head one more) over the level's radius, for the levels from the head's size to ``upto``."""
    tiled = d["build"]["tiled"]
    p = d["points"]
    tile = _tile_of(p, tiled["tile_boxes"])
    tile[: tiled["head_points"]] = -1
    tree = cKDTree(p)
    out = []
    for k in range(tiled["head_points"], upto):
        r = d["radius"][k + 1]
        near = [i for i in tree.query_ball_point(p[k], r) if i < k and tile[i] != tile[k]]
        e = min((np.linalg.norm(p[i] - p[k]) for i in near), default=r)
        out.append(e / r)
    return np.array(out)


def test_rounds_keep_the_guarantees_and_the_tiles_apart(tmp_path, monkeypatch):
    from lodbuilder.build.tiled import rounds

    rng = np.random.default_rng(7)
    pts = wavy(10_000, rng)
    n = len(pts)
    one, _ = _build(tmp_path, pts, tile_points=1200, name="one", seam_spacing=0)
    monkeypatch.setattr(rounds, "TILE_ROUNDS", (8, 1.25))
    d, _ = _build(tmp_path, pts, tile_points=1200, name="rounds", seam_spacing=0, seam_rounds=True)
    tiled = d["build"]["tiled"]
    assert tiled["tiles"] >= 12
    rows = [r for r in d["build"]["tasks"]["rows"] if r[0].startswith(("order_", "round_"))]
    assert {r[0] for r in rows} == {"round_steps", "round_finish"} and tiled["rounds"]["owners"] == 1
    # every input point exactly once; every stored radius a true covering radius (brute force)
    assert np.array_equal(np.sort(d["order"]), np.arange(n))
    cr = prefix_covering_radii(pts, d["order"])
    assert np.all(cr[1:n] <= d["radius"][1:n] * (1 + 1e-12))
    # the levels down to the last round's radius: one pass crowds tiles, the rounds keep them apart
    r_last = tiled["head_radius"] / 1.25**8
    upto = int(np.searchsorted(-d["radius"], -r_last))
    assert upto > tiled["head_points"] + 50
    assert _cross_spacing(one, upto).min() < 0.3  # (0.21)
    assert _cross_spacing(d, upto).min() >= 0.5  # (0.80)
