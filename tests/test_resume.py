"""The resumable ordering (lodbuilder.sampling.resumable): stop at a radius, bring in sources, go on."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from naive import naive_euclidean_fps, prefix_covering_radii
from surfaces import folded_sheet, jittered_plane

from lodbuilder import fastfps
from lodbuilder.errors import InputError
from lodbuilder.sampling.resumable import resume_fastfps, start_fastfps


def _two_plates(n, rng):
    """Two plates far apart: two pieces of the band (the second dormant at first)."""
    a = jittered_plane(n // 2, rng)
    b = jittered_plane(n - n // 2, rng) + [3.0, 0.0, 0.0]
    return np.concatenate([a, b])


def _same(a, b):
    assert np.array_equal(a.order, b.order)
    assert np.array_equal(a.radius, b.radius)
    assert np.array_equal(a.parent, b.parent)


@pytest.mark.parametrize("shape", ["plane", "plates", "fold"])
def test_stopping_and_going_on_orders_as_one_call(shape, rng):
    pts = {"plane": lambda: jittered_plane(4000, rng), "plates": lambda: _two_plates(4000, rng),
           "fold": lambda: folded_sheet(0.025, 0.08)[0]}[shape]()
    one = fastfps(pts)
    state = start_fastfps(pts)
    g, n = one.stats["grid_points"], len(pts)
    assert g >= 9
    for k in (g // 3, 2 * g // 3, g + (n - g) // 5, g + (n - g) // 2):  # in the grid phase, then in the tail
        part = resume_fastfps(state, rho=float(one.radius[k]))
        ref = fastfps(pts, rho=float(one.radius[k]))
        _same(part, ref)
        assert part.stop_radius >= ref.stop_radius  # (a bound: stale values of dormant pieces kept)
        assert 0 < part.stop_radius <= part.radius[-1]
        assert state.phase == ("grid" if k < g else "tail")
    assert state.phase == "tail"
    _same(resume_fastfps(state), one)
    assert state.k == len(pts)


def test_sources_join_as_timed_seeds_declared_with_their_keys(rng):
    # the points of a strip are timed seeds with key 0 ("not yet"); after the first stop some of
    # them get keys below the stop: the ordering is the one-shot ordering with those keys
    pts = jittered_plane(3000, rng)
    strip = np.flatnonzero(pts[:, 0] < 0.2)
    state = start_fastfps(pts, seeds=[0], timed_seeds=(strip, np.zeros(strip.size)))
    first = resume_fastfps(state, rho=0.1)
    chosen = strip[::3]
    keys = rng.random(chosen.size) * 0.9 * first.stop_radius
    resume_fastfps(state, sources=(chosen, keys), rho=0.03)
    later = strip[1::3]
    keys2 = rng.random(later.size) * 0.02
    out = resume_fastfps(state, sources=(later, keys2))
    final = np.zeros(strip.size)
    final[::3], final[1::3] = keys, keys2
    _same(out, fastfps(pts, seeds=[0], timed_seeds=(strip, final)))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(20, 150), seed=st.integers(0, 2**31 - 1))
def test_sources_in_the_tail_match_the_naive_reference(n, seed):
    # one voxel for the cloud: everything in the Euclidean tail; sources brought in after a stop
    r = np.random.default_rng(seed)
    pts = r.random((n, 3))
    idx = r.choice(np.arange(1, n), size=n // 4, replace=False)
    state = start_fastfps(pts, seeds=[0], voxel_size=4.0, timed_seeds=(idx, np.zeros(idx.size)))
    first = resume_fastfps(state, rho=0.4)
    keys = r.random(idx.size) * 0.9 * min(first.stop_radius, 0.4)
    out = resume_fastfps(state, sources=(idx, keys))
    order, radius, parent = naive_euclidean_fps(pts, [0], timed=(idx, keys))
    assert np.array_equal(out.order, order)
    assert (out.radius >= radius).all()  # + the rounding bound of grid-unit arithmetic (precision.py)
    np.testing.assert_allclose(out.radius, radius, rtol=1e-9, atol=2 * out.stats["rounding_bound"])
    assert np.array_equal(out.parent, parent)


@pytest.mark.parametrize(("bulk", "voxel_size"), [(False, None), (False, 0.01), (True, 0.01)])
def test_sources_brought_in_at_once_keep_every_radius_a_covering_radius(rng, bulk, voxel_size):
    # sources without keys join at once (radius: the largest remaining distance), marched one by
    # one or together (bulk); every stored radius still bounds the true Euclidean covering radius
    # of the prefix (brute force). Voxel size 0.01: the hand-over at 0.075, the sources join in
    # the grid phase; the library's: in the tail
    pts = jittered_plane(1500, rng)
    left = np.flatnonzero(pts[:, 0] < 0.35)
    state = start_fastfps(pts, timed_seeds=(left, np.zeros(left.size)), voxel_size=voxel_size)
    joined = []
    for rho, part in ((0.3, left[::7]), (0.15, left[3::5]), (0.1, left[1::4])):
        before = resume_fastfps(state, rho=rho)
        assert state.phase == ("grid" if voxel_size else "tail")
        out = resume_fastfps(state, sources=part, rho=rho * 0.85, bulk=bulk)
        new = out.order[len(before): len(before) + np.isin(part, before.order, invert=True).sum()]
        assert set(new) <= set(part)  # they come first, at the stop radius
        assert (out.radius[len(before): len(before) + new.size] <= before.stop_radius).all()
        joined.append(new)
    if voxel_size:
        assert (state.grid[26][4] > 0) == bulk  # (the sources marched in bulk)
    out = resume_fastfps(state)
    assert np.array_equal(np.sort(out.order), np.arange(len(pts)))
    # the points to cover: all but the timed seeds (those stand for another ordering's points);
    # the prefix: every point ordered, sources included
    others = np.setdiff1d(np.arange(len(pts)), left)
    cr = prefix_covering_radii(pts, out.order, targets=others)
    assert (cr[1:len(out)] <= out.radius[1:] * (1 + 1e-9)).all()
    assert (out.radius[np.isin(out.order, np.concatenate(joined))] > 0).all()


def test_a_source_must_be_declared_at_the_start(rng):
    pts = jittered_plane(500, rng)
    state = start_fastfps(pts, seeds=[0], timed_seeds=([5, 6], [0.0, 0.0]))
    resume_fastfps(state, rho=0.2)
    with pytest.raises(InputError, match=r"^sources\[1\] was not a timed seed at the start; pass every point "
                       r"that may become a source in timed_seeds \(key 0: not yet\)$"):
        resume_fastfps(state, sources=[5, 7])
    with pytest.raises(InputError, match=r"^sources needs one non-negative key per index \(2 indices, 1 keys\); "
                       r"pass \(indices, keys\) of equal length$"):
        resume_fastfps(state, sources=([5, 6], [0.1]))
    out = resume_fastfps(state, sources=[0, 6])  # the seed 0 has joined: skipped
    assert out.order[0] == 0 and 6 in out.order
    pos = int(np.flatnonzero(out.order == 6)[0])
    assert out.radius[pos] <= out.radius[pos - 1] and out.parent[pos] == -1  # joined at once, no parent


def test_timed_seeds_that_never_join_do_not_trip_the_precision_check(rng):
    # most points are declared "not yet" (key 0) and never brought in: they come last with radius
    # 0, and the precision check (radii rounding could take away) looks at the measured radii only
    pts = rng.random((200, 3))
    later = np.arange(50, 200)
    state = start_fastfps(pts, seeds=[0], voxel_size=4.0, timed_seeds=(later, np.zeros(later.size)))
    out = resume_fastfps(state)
    assert np.array_equal(np.sort(out.order), np.arange(200))
    assert (out.radius[50:] == 0).all() and set(out.order[50:]) == set(later)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31 - 1), calls=st.integers(1, 4))
def test_bringing_in_sources_matches_the_naive_reference(seed, calls):
    # sources that joined already, seeds among them, keys above and below the
    # largest remaining distance: the pending timed seeds and their keys as the naive array gives them
    from naive import naive_bring_in

    from lodbuilder.sampling.resumable import _bring_in, _now

    rng = np.random.default_rng(seed)
    pts = jittered_plane(1500, rng)
    timed = np.flatnonzero(pts[:, 0] < 0.3)
    state = start_fastfps(pts, seeds=[int(np.flatnonzero(pts[:, 0] >= 0.3)[0])],
                          timed_seeds=(timed, np.zeros(timed.size)))
    first = resume_fastfps(state, rho=0.2)
    for _ in range(calls):
        idx = rng.choice(timed, size=int(rng.integers(1, 40)), replace=False)
        if rng.random() < 0.5:
            idx = np.concatenate([idx, state.perm[state.seeds_c][:1]])  # (a seed: skipped)
        keys = rng.random(idx.size) * 1.5 * first.stop_radius
        tseed, tkey = naive_bring_in(state.tseed_c.copy(), state.tkey_g.copy(), int(state.tpos[0]), state.seeds_c,
                                     state.inv[idx], keys / state.h, _now(state))
        assert _now(state) == _scan_now(state)
        _bring_in(state, (idx, keys))
        assert np.array_equal(state.tseed_c, tseed)
        assert np.array_equal(state.tkey_g, tkey)
        pend = state.tseed_c[int(state.tpos[0]):]
        assert np.array_equal(state.tslot[pend], np.arange(int(state.tpos[0]), state.tseed_c.size))
        resume_fastfps(state, rho=float(rng.random() * first.stop_radius))
        assert _now(state) == _scan_now(state)
    resume_fastfps(state)
    assert _now(state) == _scan_now(state) == 0.0


def _scan_now(state):
    """_now the slow way: every point's value scanned, as fastfps's stop radius is."""
    from lodbuilder.sampling.fastfps import _stop_radius

    if state.phase == "grid":
        return _stop_radius(state.grid[5], state.grid[7], state.tseed_c)
    return _stop_radius(state.tail["ud"][:, 3], state.tail["rank"], state.tseed_c)
