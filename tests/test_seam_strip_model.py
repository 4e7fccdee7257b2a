"""tools/seam_strip_model.py (the seam model behind docs/benchmarks.md's strip figures): its
orderings checked against brute force, and the properties each merge claims."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

from seam_strip_model import fps, main, merge_defer, merge_strip, reorder, sheet, tile_orders  # noqa: E402


def _dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point a to the nearest of b."""
    return np.sqrt(((p[a][:, None, :] - p[b][None, :, :]) ** 2).sum(-1)).min(axis=1)


def test_fps_keys_are_the_distances_to_the_prefix():
    p = sheet(600, "uniform")
    order, key = fps(p, np.full(600, np.inf), np.zeros((0, 3)), np.zeros(0), 0.0, 600)
    assert sorted(order.tolist()) == list(range(600))
    assert np.all(np.diff(key[1:]) <= 0)
    for j in range(1, 600, 37):
        assert key[j] == _dist(p, order[j : j + 1], order[:j])[0]


def test_a_timed_seed_joins_at_its_key():
    p = sheet(400, "uniform")
    seed, seed_key = np.array([[0.5, 0.5, 0.0]]), 0.2  # (on the sheet, not one of its points)
    order, key = fps(p, np.full(400, np.inf), seed, np.array([seed_key]), 0.0, 400)
    first_after = int(np.argmax(key < seed_key))  # the seed lowers every distance from there on
    assert 0 < first_after and np.all(key[first_after:] <= seed_key)
    nearer_the_seed = 0
    for j in range(first_after, 400):
        d = _dist(p, order[j : j + 1], order[:j])[0]
        to_seed = float(np.sqrt(((p[order[j]] - seed[0]) ** 2).sum()))
        assert key[j] == min(d, to_seed)
        nearer_the_seed += to_seed < d
    assert nearer_the_seed > 0  # (the check above tells a seed that never joined)


def _tiles(n=3000, tiles=2, head_points=12):
    p = sheet(n, "uniform")
    ref, _ = fps(p, np.full(n, np.inf), np.zeros((0, 3)), np.zeros(0), 0.0, head_points)
    head = ref[:head_points]
    res, tile, face = tile_orders(p, tiles, head, 0.0)
    return p, head, res, tile, face


def test_every_merge_orders_every_point_once():
    p, head, res, tile, face = _tiles()
    rest = np.setdiff1d(np.arange(p.shape[0]), head)
    assert sorted(np.concatenate([g for g, _ in res.values()]).tolist()) == rest.tolist()
    for order in (merge_defer(p, res, tile, face, head, 0.25, 0.05)[0], merge_strip(p, res, face, head, 0.1, 0.05)):
        assert sorted(order.tolist()) == rest.tolist()


def test_the_repair_keeps_seam_points_of_different_tiles_alpha_times_their_key_apart():
    p, head, res, tile, face = _tiles()
    alpha = 0.5
    order, key = merge_defer(p, res, tile, face, head, alpha, 0.05)
    assert np.all(np.diff(key) <= 0)
    tkey = {int(i): float(k) for g, k in res.values() for i, k in zip(g, k, strict=True)}
    seam = np.array([face[i] < tkey[int(i)] for i in order])
    assert np.any(key < np.array([tkey[int(i)] for i in order]))  # some point waited
    group = np.concatenate([np.full(head.shape[0], -1), tile[order]])
    pts = np.concatenate([head, order])
    checked = np.concatenate([np.ones(head.shape[0], bool), seam])  # the head and the seam points
    for j in np.flatnonzero(seam):
        m = head.shape[0] + j
        earlier = pts[:m][checked[:m] & (group[:m] != group[m])]
        assert _dist(p, pts[m : m + 1], earlier)[0] >= alpha * key[j]


def test_reordered_points_are_accepted_at_their_distance_to_the_prefix():
    p, head, res, tile, face = _tiles(n=1500)
    keys = {int(i): float(k) for g, key in res.values() for i, k in zip(g, key, strict=True)}
    again = np.flatnonzero(face < 0.08)
    again = again[~np.isin(again, head)]
    out = reorder(p, keys, again, head, 0.05)
    order = np.fromiter(out, np.int64, len(out))
    k = np.fromiter(out.values(), float, len(out))
    assert np.all(np.diff(k) <= 0)
    assert sorted(order.tolist()) == sorted(keys)
    pos = {int(i): j for j, i in enumerate(order)}
    for i in again[::7]:
        j = pos[int(i)]
        prefix = np.concatenate([head, order[:j]])
        assert np.isclose(out[int(i)], _dist(p, np.array([i]), prefix)[0])


def test_main_writes_its_json(tmp_path):
    out = tmp_path / "m.json"
    assert main(["--points", "3000", "--head", "12", "--widths", "1", "--corner", "1", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "seam_strip_model" and doc["inputs_synthetic"] is True
    assert set(doc["variants"]) == {"none", "defer 0.25", "strip 1.0", "strip 1.0, corners 1.0"}
    for v in doc["variants"].values():
        assert len(v["covering"]) == len(doc["sizes"]) and v["covering_worst"] >= v["covering_median"]
