"""The order phase's schedule: of the tile orderings that are ready, the one with the longest chain
of orderings waiting for it starts first (its bottom level), at most one per worker at a time, so
that a task on the critical path that becomes ready late is not queued behind tasks submitted
earlier (the executor's queue is first in, first out)."""

from __future__ import annotations

import concurrent.futures as cf

import numpy as np
import pytest

from lodbuilder.build.tiled import plan as P
from lodbuilder.build.tiled.driver import _order_passes
from lodbuilder.build.tiled.pool import bottom_levels
from lodbuilder.build.tiled.store import as_store


def test_bottom_levels_of_a_chain_a_diamond_and_independent_tasks():
    assert bottom_levels({"a": [], "b": ["a"], "c": ["b"]}, {"a": 1.0, "b": 2.0, "c": 3.0}) == {
        "a": 6.0, "b": 5.0, "c": 3.0}
    diamond = {"a": [], "b": ["a"], "c": ["a"], "d": ["b", "c"]}
    assert bottom_levels(diamond, {"a": 1.0, "b": 2.0, "c": 3.0, "d": 1.0}) == {"a": 5.0, "b": 3.0, "c": 4.0, "d": 1.0}
    # independent tasks: their own costs (largest first); a dependency outside the tasks counts as done
    assert bottom_levels({"x": [], "y": ["elsewhere"]}, {"x": 2.0, "y": 7.0}) == {"x": 2.0, "y": 7.0}
    with pytest.raises(ValueError, match="the task dependencies have a cycle"):
        bottom_levels({"a": ["b"], "b": ["a"]}, {"a": 1.0, "b": 1.0})


class _Recorder(cf.Executor):
    """Finishes every task at once (as it is submitted) and records the tiles in order of submission."""

    def __init__(self) -> None:
        self.tiles: list[int] = []

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[override]
        self.tiles.append(args[1])
        fut: cf.Future = cf.Future()
        fut.set_result({"tile": args[1], "files": {}})
        return fut


def _tile(i: int, n: int) -> P.Tile:
    return P.Tile(i, ((i, i + 1), (0, 1), (0, 1)), np.array([i, 0, 0], float), np.array([i + 1, 1, 1], float), n)


@pytest.mark.parametrize(("slots", "expected"), [(1, [1, 2, 0]), (None, [1, 0, 2])])
def test_the_critical_path_starts_first(tmp_path, slots, expected):
    # tile 0 (50 points) waits for nothing and nothing waits for it; tile 1 (10 points) is a
    # neighbour of tile 2 (60 points, a larger colour), which waits for it: tile 1's chain is 70
    # points, so it starts before the larger tile 0 (which the largest-first order started first),
    # and with one worker tile 2 starts as soon as tile 1 is done, before tile 0
    by_size = [_tile(2, 60), _tile(0, 50), _tile(1, 10)]
    nbrs, colour = [[], [2], [1]], [0, 0, 1]
    pieces = {"core": [[], [], []], "halo": [[], [], []]}
    ex, work = _Recorder(), as_store(tmp_path / "w")
    work.claim()
    found = _order_passes(ex, work, "scan", by_size, nbrs, colour, 1, (), pieces, None, slots)
    assert found == 0
    assert ex.tiles == expected


def _survey_tiles(n: int, workers: int) -> list[P.Tile]:
    """The tiles a build of ``n`` points on ``workers`` workers plans for a flat survey of even
    density (a synthetic count histogram: one layer of cells, counts between 0.5 and 1.5 x the mean)."""
    grid = P.Grid.around(np.zeros(3), np.array([14_000.0, 14_000.0, 50.0]), cells=1 << 18)
    counts = np.zeros(grid.shape, np.int64)
    mean = n / (grid.shape[0] * grid.shape[1])
    counts[:, :, 0] = np.random.default_rng(0).poisson(mean * np.random.default_rng(1).uniform(0.5, 1.5, counts.shape[:2]))
    return P.split_tiles(counts.reshape(-1), grid, P.balanced_tile_points(int(counts.sum()), workers, 1 << 40))


@pytest.mark.parametrize("workers", [4, 8, 16])
def test_the_colour_chain_does_not_bound_the_order_phase(workers):
    """A tile ordering waits for its neighbours of smaller colours: the order phase lasts at least
    its longest chain of orderings (a tile's cost taken as its points). The tiles planned for W
    workers keep that chain under 4/5 of the phase's work per worker, so that the W workers, not
    the chain, set the phase's length (here 0.51 / 0.63 / 0.76 x at 4 / 8 / 16 workers; with the
    earlier 4 tiles per worker 1.0 / 1.01 / 1.26 x)."""
    tiles = _survey_tiles(21_560_000, workers)
    nbrs = P.tile_neighbours(tiles, 0.0)
    colour = P.colour_tiles(nbrs)
    deps = {t.index: [u for u in nbrs[t.index] if colour[u] < colour[t.index]] for t in tiles}
    chain = max(bottom_levels(deps, {t.index: float(t.n_points) for t in tiles}).values())
    assert chain <= 0.8 * sum(t.n_points for t in tiles) / workers
