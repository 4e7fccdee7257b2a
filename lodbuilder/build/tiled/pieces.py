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
that the scan's band joins are joined through points of other tiles. Its ordering has labelled the
band of its core already (:func:`.tasks.order_tile`: on the same grid, around the core and the head
points near it, all of them the scan's points, so a subset of the scan's band), so the covering task
labels only a strip: its own points within ``REACH`` of a shared face and the points it borrows,
and joins the two labellings where they hold one point (:func:`_strip_pieces`: at 21.56M points
in 197 tiles the strip is about a quarter of the points the whole labelling took). This misses no
step: a step from a core point farther than ``REACH`` from every shared face ends at a point of the
core (a point of another tile lies beyond a shared face), so it is in the ordering's band, and a
step from a core point of the strip is in one band or the other; two points whose balls of radius
r share a voxel are both in the ordering's band or both in the strip's, so each voxel's pieces are
joined through a point. A tile ordered in seam rounds has no labels: its whole band is labelled
here. The join is a union over
(tile, local piece), joined where a point that a tile borrowed from another tile lies in the other
tile's local piece. It runs in bands of input indices, as every later phase does (no task reads
every tile's shared points: at 21.56M points in 197 tiles one task held 520 MB of them for 1 s, the
build's longest serial step): each tile writes its shared points sorted by input index in frames
(:func:`.workdir.put_banded`); a band's task (:func:`join_band`) reads its slice of the links of
the tiles that touch the band and keeps the pairs of local pieces that hold one point; one short task (:func:`join_task`) joins
those pairs, O(pieces + pairs): the global pieces are exactly the in-memory build's (on
the same grid, voxel size and band radius; an in-memory build that chooses its parameters itself
may also thin its band near close sheets, which a tiled build does not). The first rank of a
global piece is the least rank of any point of its local pieces.
"""

from __future__ import annotations

import concurrent.futures as cf
from typing import Any

import numpy as np

from . import layout as WL
from .blocks import tile_records
from .pool import collect, submit
from .ranks import gather_ranks
from .store import Store, as_store
from .sums import done, get_json, mark
from .timing import timed_task
from .workdir import BLOCK, banded_slice, get_zipped, put_banded, put_zipped

#: a point a tile shares with another tile (borrowed, or its own near its box), with its local piece
LINK = np.dtype([("g", "<i8"), ("piece", "<i8")])
#: points whose marchable voxels touch are at most 2 r + h apart; one more voxel for rounding
REACH_R, REACH_H = 2.0, 2.0
#: the first ranks kept in the record (as :data:`lodbuilder.sampling.fastfps.PIECE_ENTRIES_MAX`)
ENTRIES_MAX = 10_000
#: two local pieces (tile, piece) that hold one point: joined
PAIR = np.dtype([("t0", "<i8"), ("p0", "<i8"), ("t1", "<i8"), ("p1", "<i8")])


def reach(voxel_size: float, band_radius: float) -> float:
    """The largest distance between two points whose band voxels can touch (with a voxel to spare)."""
    return REACH_R * band_radius + REACH_H * voxel_size


def _links(name: str) -> str:
    return f"{name}.links.bin"


def _firsts(name: str) -> str:
    return f"{name}.first.i8"


def _pairs(band: int) -> str:
    return f"pieces.join.{band}.bin"


def _band_marker(band: int) -> str:
    return f"joined.{band}"  # (not "pieces.*": a marker's first word names its moment, see layout.moment)


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
                borrowed_rank: np.ndarray, spec: dict[str, Any]) -> tuple[dict[str, list[int]], list[int]]:
    """Label the band pieces of tile ``t``'s own points ``own`` and of the points of other tiles
    ``borrowed`` (records, with their ranks in the merged order): those of them within
    :func:`reach` of its box are kept. ``spec``: the tile's box (``lo``, ``hi``), ``voxel_size``,
    ``band_radius``, ``lattice`` (the scan's lowest point: the grid's voxel corners fall a whole
    number of voxels from it) and ``max_memory``. Writes ``pieces.<t>.links.bin`` (LINK records,
    by input index: the borrowed points, and its own points within the reach of its box's faces,
    which other tiles borrow) and ``pieces.<t>.first.i8`` (the least rank in the merged order of
    each local piece); returns their entries for the task's marker, and the bands of BLOCK input
    indices its links touch (the join's tasks that read them: :func:`join_phase`)."""
    w = as_store(work)
    lo, hi = np.asarray(spec["lo"], float), np.asarray(spec["hi"], float)
    h, r = float(spec["voxel_size"]), float(spec["band_radius"])
    d = reach(h, r)
    near = _near_box(_xyz(borrowed), lo, hi, d)
    ext = np.concatenate([own, borrowed[near]])
    rank = np.concatenate([own_rank, borrowed_rank[near]])
    xyz = _xyz(ext)
    shared = np.ones(ext.shape[0], bool)  # borrowed points, and own points other tiles may borrow
    shared[: own.shape[0]] = _near_faces(xyz[: own.shape[0]], lo, hi, np.asarray(spec["interior"], bool), d)
    grid = (h, r, np.asarray(spec["lattice"], float), spec.get("max_memory"))
    labels = _ordering_labels(w, t, own.shape[0])
    if labels is None:  # (a tile ordered in seam rounds)
        piece, npiece = _band_pieces(xyz, *grid)
    else:
        piece, npiece = _strip_pieces(xyz, shared, labels, *grid)
    first = np.full(int(npiece), np.iinfo(np.int64).max, np.int64)
    np.minimum.at(first, piece, rank)
    links = np.empty(int(shared.sum()), LINK)
    links["g"], links["piece"] = ext["g"][shared], piece[shared]
    links = links[np.argsort(links["g"], kind="stable")]  # (by input index, in frames: see join_band)
    name = f"pieces.{t}"
    files = {_links(name): put_banded(w, _links(name), links, BLOCK, key="g"), _firsts(name): w.put(_firsts(name), first)}
    return files, np.unique(links["g"] // BLOCK).tolist()


def _ordering_labels(w: Store, t: int, n_own: int) -> np.ndarray | None:
    """Tile ``t``'s core points' pieces of its ordering's band (None where its ordering wrote none)."""
    name = WL.band_labels(t)
    if w.size(name) is None:
        return None
    labels = get_zipped(w, name, "<i4")
    if labels.shape[0] != n_own:
        raise RuntimeError(f"{name}: {labels.shape[0]} labels for {n_own} core points (the tile changed)")
    return labels


def _strip_pieces(xyz: np.ndarray, strip: np.ndarray, labels: np.ndarray, h: float, r: float,
                  lattice: np.ndarray, max_memory: int | None) -> tuple[np.ndarray, int]:
    """The pieces of the points ``xyz`` (the tile's own first, ``labels`` their pieces of its
    ordering's band; then the borrowed ones) from those labels and the band of the ``strip``
    points (own points near a shared face, and every borrowed one) joined where they hold one
    point: each point's piece (0 .. count - 1) and their count. See the module for why no step
    of the scan's band is missed."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    c = labels.shape[0]
    sel = np.flatnonzero(strip)  # (own points first: sel is increasing)
    s_piece, n_s = _band_pieces(xyz[sel], h, r, lattice, max_memory)
    n_a = int(labels.max()) + 1 if c else 0
    own = int(np.searchsorted(sel, c))
    a, b = labels[sel[:own]].astype(np.int64), n_a + s_piece[:own]
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n_a + n_s, n_a + n_s))
    n_comp, comp = connected_components(graph, directed=False)
    node = np.empty(xyz.shape[0], np.int64)
    node[:c] = labels
    node[sel] = n_a + s_piece
    return dense_labels(comp[node], int(n_comp))


def dense_labels(label: np.ndarray, n_labels: int) -> tuple[np.ndarray, int]:
    """``label`` (values in ``0 .. n_labels - 1``) renumbered ``0 .. k - 1`` in increasing order of
    the labels that occur, and ``k``: ``np.unique(label, return_inverse=True)`` in O(n + n_labels)
    without its sort (3.5 of the 21.56M survey's 36 cover_tile CPU-s in 197 tiles). Labels that no
    point holds (pieces of the ordering's band with no point here) are dropped."""
    held = np.zeros(n_labels, bool)
    held[label] = True
    new = np.cumsum(held, dtype=np.int64) - 1
    return new[label], int(new[-1] + 1) if n_labels else 0


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
def join_band(work: Store | str, band: int, g0: int, g1: int, tiles: list[int]) -> dict[str, Any]:
    """The pairs of local pieces (tile, piece) that hold one point with input index in
    ``[g0, g1)``: the shared points of the band of ``tiles`` (those whose links it holds: a slice of
    each one's links), sorted by input index; a point seen by several tiles joins their pieces in a
    chain. Writes ``pieces.join.<band>.bin`` (PAIR records, each pair once)."""
    w = as_store(work)
    parts = [banded_slice(w, _links(f"pieces.{t}"), LINK, g0, g1, key="g")[0] for t in tiles]
    rec = np.concatenate(parts) if parts else np.zeros(0, LINK)
    tile = np.repeat(np.asarray(tiles, np.int64), [p.shape[0] for p in parts])
    srt = np.argsort(rec["g"], kind="stable")
    g, piece, tile = rec["g"][srt], rec["piece"][srt], tile[srt]
    same = np.flatnonzero(g[1:] == g[:-1])
    pairs = np.stack([tile[same], piece[same], tile[same + 1], piece[same + 1]], axis=1)
    # each pair once (np.unique(axis=0) compares rows as bytes: 5 x slower than a lexsort here)
    pairs = pairs[np.lexsort(pairs.T[::-1])]
    pairs = pairs[np.r_[True, (pairs[1:] != pairs[:-1]).any(axis=1)]] if pairs.shape[0] else pairs
    out = np.empty(pairs.shape[0], PAIR)
    out["t0"], out["p0"], out["t1"], out["p1"] = pairs.T
    return {"band": band, "pairs": int(out.shape[0]), "files": {_pairs(band): put_zipped(w, _pairs(band), out)}}


@timed_task
def join_task(work: Store | str, n_tiles: int, n_bands: int) -> dict[str, Any]:
    """Join the tiles' local pieces (see the module) from the bands' pairs (:func:`join_band`):
    ``pieces`` (the count of the scan's band pieces) and ``piece_entries`` (the first rank of each,
    ascending, the first ENTRIES_MAX)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    w = as_store(work)
    firsts = [w.read_array(_firsts(f"pieces.{t}"), "<i8") for t in range(n_tiles)]
    offset = np.cumsum([0, *(f.shape[0] for f in firsts)])
    pairs = np.concatenate([get_zipped(w, _pairs(b), PAIR) for b in range(n_bands)] or [np.zeros(0, PAIR)])
    m = int(offset[-1])
    a, b = offset[pairs["t0"]] + pairs["p0"], offset[pairs["t1"]] + pairs["p1"]
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(m, m))
    count, label = connected_components(graph, directed=False)
    first = np.full(count, np.iinfo(np.int64).max, np.int64)
    np.minimum.at(first, label, np.concatenate(firsts) if firsts else np.zeros(0, np.int64))
    return {"pieces": int(count), "piece_entries": np.sort(first)[:ENTRIES_MAX].tolist()}


def join_phase(ex: cf.Executor, work: Any, name: str, n: int, n_tiles: int) -> dict[str, Any]:
    """The join of the tiles' band pieces (written by their covering tasks, see :func:`tile_pieces`):
    tasks over bands of BLOCK input indices, then the join of their pairs (or what a finished join
    recorded); returns ``{"pieces", "piece_entries"}`` for the build record's ``engine_stats``."""
    joined = done(work, "pieces")
    if joined is None:
        bands = [(g0, min(n, g0 + BLOCK)) for g0 in range(0, n, BLOCK)]
        # the tiles whose links each band reads (their covering tasks' markers say; all where one
        # does not: a marker of an older build)
        readers: list[list[int]] = [[] for _ in bands]
        for t in range(n_tiles):
            touched = (get_json(work, WL.marker(WL.cover_piece(t))) or {}).get("link_bands")
            for b in range(len(bands)) if touched is None else touched:
                readers[b].append(t)
        calls = [(b, join_band, (work, b, g0, g1, readers[b])) for b, (g0, g1) in enumerate(bands)
                 if done(work, _band_marker(b)) is None]
        collect(submit(ex, calls), lambda b: "the join of the pieces of points {} to {}".format(*bands[b]), name,
                len(bands), None, "pieces", lambda res: mark(work, _band_marker(res["band"]), res))
        (joined,) = collect(submit(ex, [(0, join_task, (work, n_tiles, len(bands)))]), lambda _: "the join of the pieces",
                            name, 1, None, "pieces")
        mark(work, "pieces", joined)
    return {k: joined[k] for k in ("pieces", "piece_entries")}
