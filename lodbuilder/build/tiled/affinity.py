"""Radius rounds in parallel (:mod:`.rounds`), each tile's state pinned to one worker process.

The rounds keep every tile's ordering state (:class:`lodbuilder.sampling.resumable.FastFPSState`)
from round to round. Here each tile has an *owner*, one worker process that starts its state on
the first round, orders it on in every round and writes its stream at the end; the state never
leaves that process. Tile t's round p runs once its own round p - 1 and its neighbours' round p
(a lower colour) or p - 1 (a higher colour) are done, as in :func:`.rounds.order_rounds` (one
task, every state in one process, round by round and colour by colour); each round returns the
points it ordered that lie in a neighbour's halo box (input id and key, 16 bytes a point), and
the parent hands them to the neighbours' rounds that wait for them, so both give the same orders
bit for bit (:func:`run_rounds`).

Owners: with a process pool, ``parallel`` new single-process pools (the build's pool waits
meanwhile); with a Dask client, its workers, each task pinned to one by address; otherwise (the
calling process) one owner, this process. Tiles go to owners largest first, each to the owner with
the fewest points of the tile's colour so far (then of all colours): a colour's step waits for its
slowest owner. (Owners holding spatial groups of tiles, whose batches also ran the rounds that
waited only on the batch, were tried and dropped: on 2 workers they saved no order CPU and made
the order wall of 64 tiles longer; docs/benchmarks.md, "Owners holding spatial groups of tiles".)

Memory: a state holds about :data:`STATE_BYTES_PER_POINT` bytes per point of its tile with its halo
(201-252 measured on 1M-point builds in 16-66 tiles while a tile is in the grid phase, band
included; 135-158 in the Euclidean tail: docs/benchmarks.md, "Seams"), and an owner holds the
states of all its tiles at once. The rounds are used only when every owner's states plus one
whole tile ordering (``TILE_BYTES_PER_POINT`` per point of its largest tile, the working memory
of a step and of the stream) fit the worker budget; otherwise the tiles are ordered in one pass as
without rounds, and the build record says why (``tiled.rounds``).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from ...progress import ProgressCallback, TaskCounts, report_tasks
from . import layout as WL
from . import plan as P
from . import rounds as R
from .pool import bottom_levels, result
from .store import Store
from .tasks import HEAD

#: bytes of a tile's rounds state per point of the tile with its halo (see the module)
STATE_BYTES_PER_POINT = 260


def assign(points: dict[int, int], colour: list[int], n_owners: int) -> dict[int, int]:
    """Each tile's owner (0 .. ``n_owners`` - 1): largest first, to the owner with the fewest
    points of the tile's colour, then of all."""
    per_colour = np.zeros((n_owners, max(colour, default=0) + 1), np.int64)
    total = np.zeros(n_owners, np.int64)
    out = {}
    for t in sorted(points, key=lambda t: (-points[t], t)):
        o = min(range(n_owners), key=lambda i: (per_colour[i, colour[t]], total[i], i))
        out[t] = o
        per_colour[o, colour[t]] += points[t]
        total[o] += points[t]
    return out


def owner_bytes(points: dict[int, int], owner: dict[int, int], n_owners: int) -> list[int]:
    """What each owner needs (see the module): its states and one tile ordering of its largest."""
    need = [0] * n_owners
    big = [0] * n_owners
    for t, n in points.items():
        need[owner[t]] += STATE_BYTES_PER_POINT * n
        big[owner[t]] = max(big[owner[t]], n)
    return [a + P.TILE_BYTES_PER_POINT * b for a, b in zip(need, big, strict=True)]


def n_owners(ex: cf.Executor, parallel: int) -> int:
    """How many owners ``ex`` gives (see :func:`owners`)."""
    if isinstance(ex, cf.ProcessPoolExecutor):
        return max(parallel, 1)
    client = getattr(ex, "_client", None)
    if client is not None:
        return max(len(client.scheduler_info().get("workers", {})), 1)
    return 1


@contextlib.contextmanager
def owners(ex: cf.Executor, parallel: int, key: str) -> Iterator[list[Callable[..., Any]]]:
    """The owners' submit functions (see the module); on leaving, every owner's process is gone or
    holds no state of ``key``."""
    if isinstance(ex, cf.ProcessPoolExecutor):
        from ..executors import die_with_parent, mp_context

        pools = [cf.ProcessPoolExecutor(1, mp_context=mp_context(True), initializer=die_with_parent)
                 for _ in range(max(parallel, 1))]
        try:
            yield [p.submit for p in pools]
        finally:
            for p in pools:  # (waits for the steps still running: nothing writes after the build failed)
                p.shutdown(wait=True, cancel_futures=True)
        return
    client = getattr(ex, "_client", None)
    if client is not None:
        addrs = sorted(client.scheduler_info().get("workers", {}))
        try:
            yield [client.get_executor(workers=[a], allow_other_workers=False, pure=False).submit for a in addrs]
        finally:
            with contextlib.suppress(Exception):
                client.run(R.round_drop, key, workers=addrs)
        return
    try:
        yield [ex.submit]
    finally:
        R.round_drop(key)


def _result(fut: Any, name: str, tiles: list[int], n_tiles: int, when: str, what: str = "ordering") -> Any:
    """A task's result; its failure fails the build naming the tile (that of the exception, else
    every tile of the task: a worker that died)."""
    exc = fut.exception()
    t = getattr(exc, "lodbuilder_tile", None)
    which = f"tile {t + 1}" if isinstance(t, int) else \
        f"tile{'s' if len(tiles) > 1 else ''} {', '.join(str(u + 1) for u in tiles)}"
    return result(fut, name, f"{what} of {which} of {n_tiles}{when}")


def run_rounds(ex: cf.Executor, work: Store, name: str, docs: dict[int, dict[str, Any]], nbrs: list[list[int]],
               colour: list[int], owner: dict[int, int], parallel: int, rounds: int, q: float,
               progress: ProgressCallback = None) -> dict[str, Any]:
    """Order the tiles ``docs`` (as :func:`.rounds.order_rounds`'s, with ``args``) in rounds on
    their owners (``owner``: tile -> owner); returns the tiles' results as ``order_rounds`` does,
    each owner's largest sum of its states' bytes (``owner_state_bytes``) and the largest state.

    Tile t's round p waits for its own round p - 1 and for its neighbours' round p (those of a
    lower colour) or p - 1 (a higher colour), and gets their points of those rounds: what
    ``order_rounds`` gives it, so the orders are the same. Each owner runs the rounds of its tiles
    as they become ready (those on the longest chain of rounds waiting for them first), in
    batches of one round's ready rounds, at most :data:`IN_FLIGHT` batches queued at a time.
    ``progress`` hears the tile rounds done and the tiles' points ordered (stage ``tiles``)."""
    key = uuid.uuid4().hex
    sched = R.radii(work.read_array(WL.HEAD_FILE, HEAD), rounds, q)
    n_owners = max(owner.values(), default=0) + 1
    sc = _Schedule(sched, docs, nbrs, colour, owner, n_owners)
    ordered = dict.fromkeys(docs, 0)
    total, points = len(docs) * len(sched), sum(int(d["n_points"]) for d in docs.values())

    def tell() -> None:
        report_tasks(progress, "tiles", TaskCounts(total - len(sc.todo) - sum(len(b) for _, b in running.values()),
                                                   total, sum(ordered.values()), points, len(running),
                                                   unit="tile round"))

    with owners(ex, parallel, key) as submit:
        running: dict[Any, tuple[int, list[tuple[int, int]]]] = {}
        tell()
        try:
            while sc.todo or running:
                for o in range(n_owners):
                    if sum(1 for v in running.values() if v[0] == o) < IN_FLIGHT and (batch := sc.take(o)):
                        calls = [(t, docs[t] if p == 1 else None, sc.news(p, t)) for p, t in batch]
                        rho = sched[batch[0][0] - 1]
                        running[submit[o](R.round_steps, work, key, calls, rho, R.round_step)] = (o, batch)
                if not running:
                    raise RuntimeError("the rounds' schedule is stuck")  # (cannot happen: the colours order it)
                fin, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
                for fut in fin:
                    o, batch = running.pop(fut)
                    p = batch[0][0]
                    res = _result(fut, name, [t for _, t in batch], len(docs), f" in round {p} of {len(sched)}")
                    sc.record(p, res["tiles"])
                    ordered.update((r["tile"], r["ordered"]) for r in res["tiles"])
                    tell()
        except BaseException:
            for f in running:
                f.cancel()
            raise
        halo = next(iter(docs.values()))["args"][2]
        mine = {o: [t for t in sorted(docs) if owner[t] == o] for o in range(n_owners)}
        futs = {o: submit[o](R.round_finish, work, key, ts, halo) for o, ts in mine.items() if ts}
        out = [r for o, f in futs.items() for r in _result(f, name, mine[o], len(docs), " after its rounds", "writing")["tiles"]]
    return {"tiles": sorted(out, key=lambda r: r["tile"]), "owner_state_bytes": sc.peak,
            "state_bytes": max(sc.state.values(), default=0), "rounds": rounds, "q": q}


#: batches of rounds queued on an owner at a time (one running, one waiting: the owner does not
#: wait for the parent between them)
IN_FLIGHT = 2


class _Schedule:
    """The rounds of every tile still to run, what each returned, and the owners' state bytes."""

    def __init__(self, sched: list[float | None], docs: dict[int, Any], nbrs: list[list[int]], colour: list[int],
                 owner: dict[int, int], n_owners: int) -> None:
        self.nbrs, self.colour, self.owner = nbrs, colour, owner
        self.todo = {(p, t) for p in range(1, len(sched) + 1) for t in docs}
        self.state = dict.fromkeys(docs, 0)
        self.peak = [0] * n_owners
        self.news_of: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        deps = {x: self.deps(*x) for x in self.todo}
        self.level = bottom_levels(deps, {(p, t): float(docs[t]["n_points"]) for p, t in self.todo})
        self.waiting = {x: len(d) for x, d in deps.items()}
        self.users: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for x, d in deps.items():
            for y in d:
                self.users.setdefault(y, []).append(x)
        self.ready: list[set[tuple[int, int]]] = [set() for _ in range(n_owners)]
        for x, n in self.waiting.items():
            if n == 0:
                self.ready[owner[x[1]]].add(x)

    def deps(self, p: int, t: int) -> list[tuple[int, int]]:
        d = [(p, u) if self.colour[u] < self.colour[t] else (p - 1, u) for u in self.nbrs[t]]
        return [x for x in [*d, (p - 1, t)] if x[0] >= 1]

    def take(self, o: int) -> list[tuple[int, int]]:
        """The ready rounds of owner ``o``'s tiles of one round (the most urgent's), taken off the
        list: by colour, then the most urgent first."""
        if not self.ready[o]:
            return []
        p = min(self.ready[o], key=lambda x: (-self.level[x], x))[0]
        inb = {x for x in self.ready[o] if x[0] == p}
        batch = sorted(inb, key=lambda x: (self.colour[x[1]], -self.level[x], x))
        self.ready[o].difference_update(batch)
        self.todo.difference_update(batch)
        return batch

    def news(self, p: int, t: int) -> list[tuple[np.ndarray, np.ndarray] | None]:
        """The points in t's halo box that its neighbours ordered since t's last round (see
        run_rounds)."""
        return [self.news_of.get((p if self.colour[u] < self.colour[t] else p - 1, u)) for u in self.nbrs[t]]

    def record(self, p: int, results: list[dict[str, Any]]) -> None:
        for res in results:
            t = res["tile"]
            self.news_of[p, t] = (res["g"], res["keys"])
            self.state[t] = res["state_bytes"]
            for x in self.users.get((p, t), []):
                self.waiting[x] -= 1
                if self.waiting[x] == 0 and x in self.todo:
                    self.ready[self.owner[x[1]]].add(x)
        for o in range(len(self.peak)):
            self.peak[o] = max(self.peak[o], sum(b for t, b in self.state.items() if self.owner[t] == o))
