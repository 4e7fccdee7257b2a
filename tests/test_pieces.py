"""Pieces of the band enter at their Euclidean distance (issue 20, finding 16 of reliability-3):
only the seeds have radius inf, and every prefix of an ordering of a fragmented scene covers the
whole scene within its stored radius (brute force, every prefix)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import lodbuilder
from lodbuilder.sampling.fastfps import fastfps

REPO = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("make_fragmented", REPO / "tools" / "make_fragmented.py")
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(mod)
    return mod


fragmented_scene = _tool().fragmented_scene


def prefix_covering(pts: np.ndarray, order: np.ndarray) -> np.ndarray:
    """cover[k] = the largest distance from any point to the first k points of ``order`` (k >= 1),
    for every prefix, by brute force (O(N K))."""
    d = np.full(pts.shape[0], np.inf)
    out = np.empty(order.shape[0] + 1)
    out[0] = np.inf
    for k, q in enumerate(order):
        np.minimum(d, np.sqrt(((pts - pts[q]) ** 2).sum(axis=1)), out=d)
        out[k + 1] = d.max()
    return out


def test_generator_is_deterministic_and_fragmented():
    a, b = fragmented_scene(5, 60, 4000), fragmented_scene(5, 60, 4000)
    assert a.shape == (4000, 3) and np.array_equal(a, b)
    assert not np.array_equal(a, fragmented_scene(6, 60, 4000))
    assert fastfps(a, size=2).stats["pieces"] >= 30


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), objects=st.integers(50, 160), n=st.integers(1500, 3500))
def test_every_prefix_covers_a_fragmented_scene(seed, objects, n):
    pts = fragmented_scene(seed, objects, n)
    o = fastfps(pts)
    assert o.stats["pieces"] > 1
    assert np.isinf(o.radius).sum() == 1  # the seed only: every other piece enters at a distance
    cover = prefix_covering(pts, o.order)
    k = np.arange(1, len(o))
    assert (cover[k] <= o.radius[k]).all(), int(k[np.argmax(cover[k] - o.radius[k])])
    # a partial ordering's stop radius bounds the covering of its whole prefix
    size = max(2, n // 50)
    p = fastfps(pts, size=size)
    assert cover[size] <= p.stop_radius


def test_a_piece_enters_at_its_euclidean_distance():
    """Two patches 10 m apart: the far patch's first point enters when the radius falls to its
    exact Euclidean distance to the points before it (not with radius inf, before everything)."""
    rng = np.random.default_rng(3)
    a = np.c_[rng.random((2000, 2)) * 20, np.zeros(2000)]
    b = np.c_[rng.random((300, 2)) * 3 + [30, 0], np.zeros(300)]
    pts = np.vstack([a, b])
    o = fastfps(pts, seeds=[0])
    assert o.stats["pieces"] == 2 and np.isinf(o.radius).sum() == 1
    pos = np.flatnonzero(o.order >= 2000)[0]
    first = pts[o.order[pos]]
    dist = np.sqrt(((pts[o.order[:pos]] - first) ** 2).sum(axis=1))
    assert o.radius[pos] == pytest.approx(dist.min(), rel=1e-12)
    assert o.parent[pos] == np.argmin(dist)
    assert o.radius[pos - 1] >= o.radius[pos] >= o.radius[pos + 1]


@pytest.mark.parametrize("joint", [False, True])
def test_tiled_and_joint_builds_of_a_fragmented_scene(tmp_path, joint):
    """The tiled path (tiny tiles) and a joint build of two halves: no radius inf past the first
    point, and the checked prefixes cover the scene within their stored radius."""
    from lodbuilder.io import write_points

    pts = fragmented_scene(11, 120, 6000)
    if joint:
        left = pts[:, 0] < np.median(pts[:, 0])
        files = [write_points(tmp_path / "a.npy", pts[left]), write_points(tmp_path / "b.npy", pts[~left])]
        lodbuilder.build_archive(files, tmp_path / "j.h5", joint="scene", workers=1)
        arc_path = tmp_path / "j.h5"
    else:
        f = write_points(tmp_path / "s.npy", pts)
        lodbuilder.build_archive(f, tmp_path / "t.h5", workers=1, _tile_points=1500)
        arc_path = tmp_path / "t.h5"
    with lodbuilder.open_archive(arc_path) as arc:
        scan = arc.scan()
        radius = np.asarray(scan.radius)
        stored = scan.points()
        if not joint:
            assert scan.build.get("method") == "tiled"
    assert np.isinf(radius).sum() == 1
    cover = prefix_covering(stored, np.arange(stored.shape[0]))
    k = np.arange(1, stored.shape[0])
    assert (cover[k] <= radius[k] * (1 + 1e-12)).all(), int(k[np.argmax(cover[k] - radius[k])])


@pytest.mark.parametrize("how", [{"size": 120}, {"rho": 6.0}], ids=["size", "rho"])
def test_partial_builds_of_a_fragmented_scene_never_understate(tmp_path, how):
    """A partial build (by size, by rho) of a fragmented scene: every stored radius of the ordered
    prefix and the stop radius of the whole prefix bound its true covering radius (brute force),
    and a level by rho at the stop radius is the whole ordered prefix (finding 3 of reliability-3:
    the stop was 0)."""
    from lodbuilder.io import write_points

    pts = fragmented_scene(13, 150, 5000)
    f = write_points(tmp_path / "s.npy", pts)
    lodbuilder.build_archive(f, tmp_path / "p.h5", workers=1, **how)
    with lodbuilder.open_archive(tmp_path / "p.h5") as arc:
        scan = arc.scan()
        m, stop = scan.n_ordered, scan.stop_radius
        radius = np.asarray(scan.radius)[:m]
        order = np.asarray(scan.source_index[:m])
        at_stop = scan.level(rho=stop).size
    assert 1 < m < len(pts) and stop > 0 and at_stop == m
    if "rho" in how:
        assert stop <= how["rho"] < radius[-1]
    cover = prefix_covering(pts, order)
    k = np.arange(1, m)
    assert (cover[k] <= radius[k]).all(), int(k[np.argmax(cover[k] - radius[k])])
    assert cover[m] <= stop


@pytest.mark.parametrize("npiece", [1, 3, 50, 400])
def test_first_entries_match_a_sort(npiece):
    """The ranks at which pieces first enter an ordering (build records): one pass, the same as
    the positions of the first occurrences found by a stable sort."""
    from lodbuilder._kernels.pieces import first_entries

    rng = np.random.default_rng(npiece)
    m = 500
    piece = rng.integers(0, npiece, m).astype(np.int32)
    for k in (0, 1, 37, m):
        order = rng.permutation(m)[:k].astype(np.int32)
        _, where = np.unique(piece[order], return_index=True)
        got = first_entries(piece, order, np.int64(npiece))
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, np.sort(where))
