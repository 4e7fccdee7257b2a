"""Radius rounds in parallel (:mod:`.rounds`), each tile's state pinned to one worker process.

The rounds keep every tile's ordering state (:class:`lodbuilder.sampling.resumable.FastFPSState`)
from round to round. Here each tile has an *owner*, one worker process that starts its state on
the first round, orders it on in every round and writes its stream at the end; the state never
leaves that process. The parent runs round by round, colour by colour: the tiles of one colour
(no two of them neighbours) run at once on their owners, and each returns the points it ordered in
that round that lie in a neighbour's halo box (input id and key, 16 bytes a point); the parent
hands them to the neighbours' next steps, in the order in which :func:`.rounds.order_rounds` (one
task, every state in one process) would see them, so both give the same orders bit for bit.

Owners: with a process pool, ``parallel`` new single-process pools (the build's pool waits
meanwhile); with a Dask client, its workers, each task pinned to one by address; otherwise (the
calling process) one owner, this process. Tiles go to owners largest first, each to the owner with
the fewest points of the tile's colour so far (then of all colours): a colour's step waits for its
slowest owner.

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
import functools
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from . import layout as WL
from . import plan as P
from . import rounds as R
from .pool import result
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

        pools = [cf.ProcessPoolExecutor(1, mp_context=mp_context(), initializer=die_with_parent)
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
            yield [functools.partial(client.submit, workers=[a], allow_other_workers=False, pure=False) for a in addrs]
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
               colour: list[int], owner: dict[int, int], parallel: int, rounds: int, q: float
               ) -> dict[str, Any]:
    """Order the tiles ``docs`` (as :func:`.rounds.order_rounds`'s, with ``args``) in rounds on
    their owners (``owner``: tile -> owner); returns the tiles' results as ``order_rounds`` does,
    each owner's largest sum of its states' bytes (``owner_state_bytes``) and the largest state."""
    key = uuid.uuid4().hex
    sched = R.radii(work.read_array(WL.HEAD_FILE, HEAD), rounds, q)
    colours = sorted({colour[t] for t in docs})
    chunks: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {t: [] for t in docs}
    seen: dict[tuple[int, int], int] = {}
    state = dict.fromkeys(docs, 0)
    peak = [0] * (max(owner.values(), default=0) + 1)
    n_tiles = len(docs)

    def news(t: int) -> list[tuple[np.ndarray, np.ndarray] | None]:
        out: list[tuple[np.ndarray, np.ndarray] | None] = []
        for u in nbrs[t]:
            if not chunks[u]:
                out.append(None)  # (not started yet)
                continue
            part = chunks[u][seen.get((t, u), 0):]
            seen[t, u] = len(chunks[u])
            out.append((np.concatenate([c[0] for c in part]), np.concatenate([c[1] for c in part])) if part
                       else (np.empty(0, np.int64), np.empty(0)))
        return out

    with owners(ex, parallel, key) as submit:
        for p, rho in enumerate(sched, 1):
            for c in colours:
                mine = {o: [t for t in sorted(docs) if colour[t] == c and owner[t] == o] for o in range(len(peak))}
                futs = {o: submit[o](R.round_steps, work, key, [(t, docs[t] if p == 1 else None, news(t)) for t in ts],
                                     rho, R.round_step) for o, ts in mine.items() if ts}
                for o, f in futs.items():
                    for res in _result(f, name, mine[o], n_tiles, f" in round {p} of {len(sched)}")["tiles"]:
                        chunks[res["tile"]].append((res["g"], res["keys"]))
                        state[res["tile"]] = res["state_bytes"]
                for o in range(len(peak)):
                    peak[o] = max(peak[o], sum(b for t, b in state.items() if owner[t] == o))
        halo = next(iter(docs.values()))["args"][2]
        mine = {o: [t for t in sorted(docs) if owner[t] == o] for o in range(len(peak))}
        futs = {o: submit[o](R.round_finish, work, key, ts, halo) for o, ts in mine.items() if ts}
        out = [r for o, f in futs.items() for r in _result(f, name, mine[o], n_tiles, " after its rounds", "writing")["tiles"]]
    return {"tiles": out, "owner_state_bytes": peak, "state_bytes": max(state.values(), default=0),
            "rounds": rounds, "q": q}
