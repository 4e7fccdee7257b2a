"""Radius rounds in parallel (lodbuilder.build.tiled.affinity): each tile's state stays on one
worker process, and the orders are those of the one-task rounds (rounds.order_rounds) bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from naive import prefix_covering_radii
from rounds_fault import failing_step
from test_tiled import wavy

import lodbuilder
from lodbuilder.build.tiled import affinity, rounds
from lodbuilder.errors import BuildError, MemoryBudgetError
from lodbuilder.io import write_points

ROUNDS = (6, 1.25)


def _one_task(ex, work, name, docs, nbrs, colour, owner, parallel, n_rounds, q, progress=None):
    """The reference: every tile ordered in one task of this process, every state in it."""
    args = next(iter(docs.values()))["args"]
    res = rounds.order_rounds(work, docs, nbrs, colour, *args, n_rounds, q)
    return {**res, "owner_state_bytes": [0]}


@pytest.fixture
def pts():
    p = wavy(6000, np.random.default_rng(3))
    return np.concatenate([p, p[::50]])  # (with exact copies of points: the engine's duplicates)


def _build(tmp_path, pts, name, **kw):
    """A tiled build of ``pts`` (saved as a file: workers) on 2 workers; the archive's arrays."""
    src = tmp_path / "pts.npy"
    if not src.exists():
        write_points(src, pts)
    out = tmp_path / f"{name}.h5"
    out.unlink(missing_ok=True)
    lodbuilder.build_archive(src, out, _tile_points=700, seam_spacing=0, workers=2, name=name, **kw)
    with lodbuilder.open_archive(out) as arc:
        v = arc.scan(name)
        return {"order": v.source_index[:], "radius": v.radius[:], "build": v.build}


def test_parallel_rounds_give_the_one_task_orders(tmp_path, monkeypatch, pts):
    monkeypatch.setattr(rounds, "TILE_ROUNDS", ROUNDS)
    d = _build(tmp_path, pts, "par", seam_rounds=True)
    tiled = d["build"]["tiled"]
    assert tiled["tiles"] >= 8
    assert tiled["rounds"]["owners"] == 2
    assert len(tiled["rounds"]["owner_state_bytes"]) == 2 and min(tiled["rounds"]["owner_state_bytes"]) > 0
    # tasks of a round of one or more tiles of one owner, in two processes (a tile's state is only
    # on its owner: a step elsewhere would fail, not start it again)
    assert sorted(set(tiled["rounds"]["owner"])) == [0, 1]
    steps = [r for r in d["build"]["tasks"]["rows"] if r[0] == "round_steps"]
    assert 2 * (ROUNDS[0] + 1) <= len(steps) <= tiled["tiles"] * (ROUNDS[0] + 1)
    assert len({r[7] for r in steps}) == 2
    # every input point exactly once; every stored radius a true covering radius (brute force)
    n = len(pts)
    assert np.array_equal(np.sort(d["order"]), np.arange(n))
    cr = prefix_covering_radii(pts, d["order"])
    assert np.all(cr[1:n] <= d["radius"][1:n] * (1 + 1e-12))
    # the one-task rounds (every state in one process) give the same order and radii
    monkeypatch.setattr(affinity, "run_rounds", _one_task)
    ref = _build(tmp_path, pts, "par", seam_rounds=True)
    assert [r[0] for r in ref["build"]["tasks"]["rows"] if r[0].startswith(("order_", "round_"))] == ["order_rounds"]
    np.testing.assert_array_equal(d["order"], ref["order"])
    np.testing.assert_array_equal(d["radius"], ref["radius"])
    # and they differ from one pass (the rounds did something)
    one = _build(tmp_path, pts, "par")
    assert one["build"]["tiled"]["rounds"] is None
    assert not np.array_equal(one["order"], d["order"])


def test_rounds_that_do_not_fit_the_worker_budget_are_refused(tmp_path, monkeypatch, pts):
    """Seam rounds asked for and workers too small for the tiles' states: a one-line refusal with
    the budget that would do, and the archive the build adds to is left as it was. Where the points
    alone are too many, before any work (no work directory); else once the tiles are known."""
    src, arc = tmp_path / "pts.npy", tmp_path / "keep.h5"
    write_points(src, pts)
    lodbuilder.build_archive(src, arc, name="keep")
    before = arc.read_bytes()
    parts = tmp_path / ".keep.h5.parts"
    monkeypatch.setattr(rounds, "TILE_ROUNDS", ROUNDS)
    monkeypatch.setattr(affinity, "STATE_BYTES_PER_POINT", 10**6)  # (an owner: half the points' states at least)
    least = f"{10**6 * -(-len(pts) // 2) / 2**30:.2f}".replace(".", r"\.")
    with pytest.raises(MemoryBudgetError, match=rf"^seam rounds need at least {least} GiB in each of 2 worker\(s\) for "
                       r"the tiles' ordering states, over the 0\.89 GiB each has of max_memory=3\.00 GiB; give "
                       r"max_memory of at least 8 GiB, or build without seam rounds$"):
        lodbuilder.build_archive(src, arc, _tile_points=700, workers=2, name="big", seam_rounds=True,
                                 max_memory="3GiB")
    assert arc.read_bytes() == before and not list(parts.glob("*.work"))
    monkeypatch.setattr(affinity, "STATE_BYTES_PER_POINT", 260)
    monkeypatch.setattr(affinity, "owner_bytes", lambda points, owner, n: [2**31] * n)  # (the tiles' halos)
    with pytest.raises(MemoryBudgetError, match=r"^seam rounds need about 2\.00 GiB in each of 2 worker\(s\) for "
                       r"the tiles' ordering states, over the 0\.89 GiB each has of max_memory=3\.00 GiB; give "
                       r"max_memory of at least 6 GiB, or build without seam rounds$"):
        lodbuilder.build_archive(src, arc, _tile_points=700, workers=2, name="big", seam_rounds=True,
                                 max_memory="3GiB")
    assert arc.read_bytes() == before


def test_a_failing_tile_fails_the_build_naming_it(tmp_path, monkeypatch, pts):
    monkeypatch.setattr(rounds, "TILE_ROUNDS", ROUNDS)
    step = rounds.round_step
    monkeypatch.setattr(rounds, "round_step", failing_step)  # (a module the workers import alone)
    with pytest.raises(BuildError, match=r"ordering of tile 4 of \d+ in round 1 of 7 failed: RuntimeError: "
                                         r"boom in the rounds"):
        _build(tmp_path, pts, "fail", seam_rounds=True)
    assert not (tmp_path / "fail.h5").exists()
    # the work is kept, with no tile ordering marked done; the resumed build redoes the rounds and
    # gives the order of a build that did not fail
    (work,) = (tmp_path / ".fail.h5.parts").glob("*.work")
    assert (work / "distribute.json").exists() and list(work.glob("order*.json")) == []
    monkeypatch.setattr(rounds, "round_step", step)
    resumed = _build(tmp_path, pts, "fail", seam_rounds=True)
    assert resumed["build"]["tiled"]["rounds"]["rounds"] == ROUNDS[0]
    clean = _build(tmp_path, pts, "clean", seam_rounds=True)
    np.testing.assert_array_equal(resumed["order"], clean["order"])
    np.testing.assert_array_equal(resumed["radius"], clean["radius"])


def test_owners_balance_each_colour():
    points = {0: 100, 1: 90, 2: 80, 3: 70, 4: 10}
    colour = [0, 0, 1, 1, 0]
    owner = affinity.assign(points, colour, 2)
    assert owner[0] != owner[1] and owner[2] != owner[3]
    assert affinity.owner_bytes(points, owner, 2)[owner[0]] == (
        affinity.STATE_BYTES_PER_POINT * sum(n for t, n in points.items() if owner[t] == owner[0])
        + 800 * 100)


def test_dask_workers_own_the_tiles_as_the_pool_does(tmp_path, monkeypatch, pts):
    pytest.importorskip("dask.distributed")
    monkeypatch.setattr(rounds, "TILE_ROUNDS", ROUNDS)
    pool = _build(tmp_path, pts, "pool", seam_rounds=True)
    src = tmp_path / "pts.npy"
    out = tmp_path / "dask.h5"
    lodbuilder.build_archive(src, out, _tile_points=700, seam_spacing=0, dask_local=2, name="dask", seam_rounds=True)
    with lodbuilder.open_archive(out) as arc:
        v = arc.scan("dask")
        order, radius, build = v.source_index[:], v.radius[:], v.build
    assert build["tiled"]["rounds"]["owners"] == 2
    assert len({r[7] for r in build["tasks"]["rows"] if r[0] == "round_steps"}) == 2
    np.testing.assert_array_equal(order, pool["order"])
    np.testing.assert_array_equal(radius, pool["radius"])


def test_resume_news_gives_the_points_of_each_round():
    from lodbuilder.sampling.resumable import resume_fastfps, resume_news, start_fastfps

    p = wavy(3000, np.random.default_rng(5))
    p = np.concatenate([p, p[::10]])  # (3001 is a copy of 10: a seed and its copy, the copies of points)
    seeds = np.array([0, 10, 3001])
    a, b = start_fastfps(p, seeds=seeds), start_fastfps(p, seeds=seeds)
    since, idx, rad = 0, [], []
    for rho in (0.1, 0.05, 0.02):
        o = resume_fastfps(a, rho=rho)
        i, r, since = resume_news(b, since, rho=rho)
        idx.append(i)
        rad.append(r)
    assert len(o) > 500
    np.testing.assert_array_equal(np.concatenate(idx), o.order[3:])
    np.testing.assert_array_equal(np.concatenate(rad), o.radius[3:])


def test_a_batch_holds_one_rounds_ready_rounds():
    # a strip of 4 tiles, colours 0 1 0 1; owner 0 holds tiles 0 and 1, owner 1 tiles 2 and 3
    nbrs = [[1], [0, 2], [1, 3], [2]]
    colour = [0, 1, 0, 1]
    docs = {t: {"n_points": 10} for t in range(4)}
    sc = affinity._Schedule([1.0, None], docs, nbrs, colour, {0: 0, 1: 0, 2: 1, 3: 1}, 2)
    # tiles 1 and 3 wait for their neighbours of colour 0 in the same round
    assert sc.take(0) == [(1, 0)]
    assert sc.take(1) == [(1, 2)]
    assert sc.take(0) == [] and sc.take(1) == []
    sc.record(1, [{"tile": 2, "g": np.arange(1), "keys": np.ones(1), "state_bytes": 1}])
    assert sc.take(1) == [(1, 3)] and sc.take(0) == []  # (tile 1 still waits for tile 0)
    assert sc.news(1, 3)[0][0].tolist() == [0]  # tile 2's points of round 1, through the parent
    sc.record(1, [{"tile": 0, "g": np.arange(1), "keys": np.ones(1), "state_bytes": 1}])
    assert sc.take(0) == [(1, 1)]
    # one owner: the ready rounds of a round in one batch, a colour at a time
    sc = affinity._Schedule([1.0, None], docs, nbrs, colour, dict.fromkeys(range(4), 0), 1)
    assert sc.take(0) == [(1, 0), (1, 2)]
