"""The pieces of a tiled build's band, joined across tiles: how many connected pieces the scan's
band has and the rank at which each entered the merged order, stored as an in-memory build stores
them (``engine_stats``: ``pieces`` and ``piece_entries``) so that ``slice`` and ``evaluate`` say
how many pieces a level reaches (issue 20, item 5).

A piece of the band is a connected set of its marchable voxels (6-neighbours, see
:func:`lodbuilder._kernels.topology.point_pieces`). Two points whose marchable voxels touch are at
most ``2 r + h`` apart (``REACH``), so every step of a path through the band from one point to another
passes between points within that distance. Each tile labels the band of its core and of every
point of another tile within ``REACH`` of its box (on the whole scan's grid: the in-memory build's
voxels): every step that starts at one of its core points is in that band, so two of its local pieces
that the scan's band joins are joined through points of other tiles. The join (:func:`join_task`)
is a union over (tile, local piece), joined where a point that a tile borrowed from another tile
lies in the other tile's local piece: the global pieces are exactly the in-memory build's (on
the same grid, voxel size and band radius; an in-memory build that chooses its parameters itself
may also thin its band near close sheets, which a tiled build does not). The first rank of a
global piece is the least rank of any point of its local pieces.
"""

from __future__ import annotations

import concurrent.futures as cf
from typing import Any

import numpy as np

from .blocks import tile_records
from .pool import collect, submit
from .ranks import gather_ranks
from .store import as_store
from .sums import done, mark
from .timing import timed_task

#: a point a tile shares with another tile (borrowed, or its own near its box), with its local piece
LINK = np.dtype([("g", "<i8"), ("piece", "<i8")])
#: points whose marchable voxels touch are at most 2 r + h apart; one more voxel for rounding
REACH_R, REACH_H = 2.0, 2.0
#: the first ranks kept in the record (as :data:`lodbuilder.sampling.fastfps.PIECE_ENTRIES_MAX`)
ENTRIES_MAX = 10_000


def reach(voxel_size: float, band_radius: float) -> float:
    """The largest distance between two points whose band voxels can touch (with a voxel to spare)."""
    return REACH_R * band_radius + REACH_H * voxel_size


def _links(name: str) -> str:
    return f"{name}.links.bin"


def _firsts(name: str) -> str:
    return f"{name}.first.i8"


def _near_box(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, d: float) -> np.ndarray:
    """Which points lie within ``d`` of the box ``[lo, hi]`` (as a box grown by d)."""
    return np.all((xyz >= lo - d) & (xyz <= hi + d), axis=1)


def _near_faces(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, interior: np.ndarray, d: float) -> np.ndarray:
    """Which points lie within ``d`` of a face of the box that it shares with other tiles
    (``interior``: lo/hi per axis), the only points of a tile that another tile borrows: a point
    within ``d`` of tile u's box is within ``d`` of the face of its own box on a side where the
    boxes separate, and that face is shared (u lies beyond it). The scan's outer faces do not
    count: an airborne tile's box is thin in z, and every point is near its top or bottom."""
    near = np.zeros(xyz.shape[0], bool)
    for a in range(3):
        if interior[0, a]:
            near |= xyz[:, a] <= lo[a] + d
        if interior[1, a]:
            near |= xyz[:, a] >= hi[a] - d
    return near


def _xyz(rec: np.ndarray) -> np.ndarray:
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=1)


def _band_pieces(xyz: np.ndarray, h: float, r: float, lattice: np.ndarray, max_memory: int | None
                 ) -> tuple[np.ndarray, int]:
    """The band piece of every point (and their count) on the grid of the whole scan's band (its
    voxel corners a whole number of voxels from ``lattice``, the whole scan's lowest point)."""
    from ...sampling.band import band_pieces

    return band_pieces(xyz, h, r, max_memory, lattice=lattice)


def tile_pieces(work: Any, t: int, own: np.ndarray, own_rank: np.ndarray, borrowed: np.ndarray,
                borrowed_rank: np.ndarray, spec: dict[str, Any]) -> dict[str, list[int]]:
    """Label the band pieces of tile ``t``'s own points ``own`` and of the points of other tiles
    ``borrowed`` (records, with their ranks in the merged order): those of them within
    :func:`reach` of its box are kept. ``spec``: the tile's box (``lo``, ``hi``), ``voxel_size``,
    ``band_radius``, ``lattice`` (the scan's lowest point: the grid's voxel corners fall a whole
    number of voxels from it) and ``max_memory``. Writes ``pieces.<t>.links.bin`` (LINK records,
    by input index: the borrowed points, and its own points within the reach of its box's faces,
    which other tiles borrow) and ``pieces.<t>.first.i8`` (the least rank in the merged order of
    each local piece); returns their entries for the task's marker."""
    w = as_store(work)
    lo, hi = np.asarray(spec["lo"], float), np.asarray(spec["hi"], float)
    h, r = float(spec["voxel_size"]), float(spec["band_radius"])
    d = reach(h, r)
    near = _near_box(_xyz(borrowed), lo, hi, d)
    ext = np.concatenate([own, borrowed[near]])
    rank = np.concatenate([own_rank, borrowed_rank[near]])
    xyz = _xyz(ext)
    piece, npiece = _band_pieces(xyz, h, r, np.asarray(spec["lattice"], float), spec.get("max_memory"))
    first = np.full(int(npiece), np.iinfo(np.int64).max, np.int64)
    np.minimum.at(first, piece, rank)
    shared = np.ones(ext.shape[0], bool)  # borrowed points, and own points other tiles may borrow
    shared[: own.shape[0]] = _near_faces(xyz[: own.shape[0]], lo, hi, np.asarray(spec["interior"], bool), d)
    links = np.empty(int(shared.sum()), LINK)
    links["g"], links["piece"] = ext["g"][shared], piece[shared]
    name = f"pieces.{t}"
    return {_links(name): w.put(_links(name), links), _firsts(name): w.put(_firsts(name), first)}


def borrowed_points(work: Any, halo: np.ndarray, halo_rank: np.ndarray, spec: dict[str, Any]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The points of other tiles :func:`tile_pieces` needs, with their ranks: the tile's halo when
    it is at least :func:`reach` wide (``spec["halo"]``), else its neighbours' cores
    (``spec["neighbours"]``: their pieces' names)."""
    if float(spec["halo"]) >= reach(float(spec["voxel_size"]), float(spec["band_radius"])):
        return halo, halo_rank
    others = tile_records(work, [n for names in spec["neighbours"] for n in names])
    return others, gather_ranks(work, others["g"])


@timed_task
def join_task(work: str, n_tiles: int) -> dict[str, Any]:
    """Join the tiles' local pieces (see the module): ``pieces`` (the count of the scan's band
    pieces) and ``piece_entries`` (the first rank of each, ascending, the first ENTRIES_MAX)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    firsts = [as_store(work).read_array(_firsts(f"pieces.{t}"), "<i8") for t in range(n_tiles)]
    offset = np.cumsum([0, *(f.shape[0] for f in firsts)])
    links = [as_store(work).read_array(_links(f"pieces.{t}"), LINK) for t in range(n_tiles)]
    g = np.concatenate([x["g"] for x in links])
    node = np.concatenate([x["piece"] + offset[t] for t, x in enumerate(links)])
    srt = np.argsort(g, kind="stable")
    g, node = g[srt], node[srt]
    same = np.flatnonzero(g[1:] == g[:-1])  # the same point seen by two tiles: one piece
    m = int(offset[-1])
    graph = coo_matrix((np.ones(same.size, np.int8), (node[same], node[same + 1])), shape=(m, m))
    count, label = connected_components(graph, directed=False)
    first = np.full(count, np.iinfo(np.int64).max, np.int64)
    np.minimum.at(first, label, np.concatenate(firsts))
    return {"pieces": int(count), "piece_entries": np.sort(first)[:ENTRIES_MAX].tolist()}


def start_join(ex: cf.Executor, work: Any, n_tiles: int) -> dict[cf.Future, int]:
    """Submit the join of the tiles' band pieces (written by their covering tasks, see
    :func:`tile_pieces`), to run beside the phases after the covering; none when a finished
    join recorded it."""
    return {} if done(work, "pieces") is not None else submit(ex, [(0, join_task, (work, n_tiles))])


def finish_join(ex: cf.Executor, work: Any, name: str, n_tiles: int, pending: dict[cf.Future, int]
                ) -> dict[str, Any]:
    """Wait for the join :func:`start_join` submitted (or submit it, when nothing was pending and
    no finished join is recorded); returns ``{"pieces", "piece_entries"}`` for the build record's
    ``engine_stats``."""
    joined = None if pending else done(work, "pieces")
    if joined is None:
        pending = pending or start_join(ex, work, n_tiles)
        (joined,) = collect(pending, lambda _: "the join of the pieces", name, 1, None, "pieces")
        mark(work, "pieces", joined)
    return {k: joined[k] for k in ("pieces", "piece_entries")}
