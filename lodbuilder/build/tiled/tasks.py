"""The tasks of a tiled build that run on workers (a local process, a pool worker or a Dask worker).

Each task reads its inputs from the work store and writes its outputs there as whole objects (each
appears only when complete, so a killed task leaves nothing half-written and a finished one is
reused when the build is resumed). The store is a directory the workers share with the parent
(always true for a local pool or a LocalCluster) or an object store (:mod:`.store`), which a
cluster with no shared file system uses.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import layout as WL
from .blocks import tile_records
from .store import Store, as_store
from .timing import timed_task
from .workdir import BLOCK, REC, put_banded, put_stream, put_zipped

if TYPE_CHECKING:
    from ...sampling.ordering import Ordering

STREAM, HEAD, FACE, EVENT, POINT = WL.STREAM, WL.HEAD, WL.FACE, WL.EVENT, WL.POINT
MAX_CELLS = 1 << 24  # cells (blocks x 8) of the covering pass's grid


@timed_task
def parameters_task(work: Store | str, n: int, voxel_size: float | None, band_radius: float | None) -> dict[str, Any]:
    """The point spacing of the scan (from the sample of the read phase, ``sample.npy``) and the
    voxel size and band radius every tile shares."""
    from ...sampling.band import VOXEL_PER_SPACING, choose_parameters, median_spacing

    sample = as_store(work).load_npy(WL.SAMPLE)
    if sample.shape[0] < 2:
        s = 1.0
    else:
        s = median_spacing(sample) * math.sqrt(sample.shape[0] / max(n, 1))
        s = s if s > 0 else float(np.ptp(sample, axis=0).max() or 1.0) / math.sqrt(max(n, 1))
    h, r = choose_parameters(sample, voxel_size if voxel_size is not None else VOXEL_PER_SPACING * s, band_radius)
    return {"spacing": s, "voxel_size": h, "band_radius": r}


@timed_task
def coarse_task(work: Store | str, size: int, max_memory: int | None, voxel_min: float = 0.0) -> dict[str, Any]:
    """Order the decimated copy down to ``size`` points: the coarse global level (the head).

    ``voxel_min``: the ordering's grid is at least this coarse (the driver asks for a fraction of
    the copy's estimated radius at one point in 200, see :data:`.driver.HEAD_RADIUS_VOXELS`): the
    grid phase needs radii down to 11-14 of the copy's spacings only (the deeper head is the
    Euclidean tail's), and a grid of the copy's own spacing has several times the voxels (the
    task's CPU is mostly the band and its marching). Where the
    copy's automatic grid is that coarse already, it is used as it is (its thin-sheet plan too).
    Any grid keeps the head's radii upper bounds of the copy's covering radius."""
    from ...sampling.band import choose_parameters
    from ...sampling.fastfps import fastfps

    w = as_store(work)
    rec = w.read_array(WL.DECIMATED, REC)
    dec = rec["g"]
    pts = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
    k = min(size + 1, dec.shape[0])
    coarser = voxel_min > 0.0 and choose_parameters(pts, None, None)[0] < voxel_min
    o = fastfps(pts, size=k, max_memory=max_memory, voxel_size=float(voxel_min) if coarser else None)
    h = min(size, len(o))
    head = np.empty(h, HEAD)
    head["g"] = dec[o.order[:h]]
    hp = pts[o.order[:h]]
    head["x"], head["y"], head["z"] = hp[:, 0], hp[:, 1], hp[:, 2]
    head["r"] = o.radius[:h]
    head["parent"] = o.parent[:h]
    r_next = float(o.radius[h]) if len(o) > h else 0.0
    files = {WL.HEAD_FILE: w.put(WL.HEAD_FILE, head)}
    return {"n_decimated": int(dec.shape[0]), "head": h, "r_cut": r_next, "voxel_size": o.voxel_size,
            "band_radius": o.band_radius, "files": files}


def in_sorted(values: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which of ``values`` are in ``ref`` (sorted ascending), and their positions there: the
    mask ``np.isin(values, ref)`` and ``searchsorted(ref, values[mask])``, by binary search
    (np.isin hashes all of ``ref``: about 0.25 CPU-s for a tile of 250,000 points, where this takes 1 ms)."""
    if ref.shape[0] == 0:
        return np.zeros(values.shape[0], bool), np.empty(0, np.intp)
    pos = np.minimum(np.searchsorted(ref, values), ref.shape[0] - 1)
    found = ref[pos] == values
    return found, pos[found]


def _margins(pts: np.ndarray, lo: np.ndarray, hi: np.ndarray, interior: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest face its tile shares with another tile."""
    m = np.full(pts.shape[0], np.inf)
    for a in range(3):
        if interior[0, a]:
            m = np.minimum(m, pts[:, a] - lo[a])
        if interior[1, a]:
            m = np.minimum(m, hi[a] - pts[:, a])
    return np.maximum(m, 0.0)


def _timed(store: Store, halo_rec: np.ndarray, faces: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """The halo points that neighbouring tiles have ordered: (row in ``halo_rec``, key)."""
    if not faces or halo_rec.shape[0] == 0:
        return np.empty(0, np.int64), np.empty(0)
    known = np.concatenate([store.read_array(Path(f).name, FACE) for f in faces])
    if known.shape[0] == 0:
        return np.empty(0, np.int64), np.empty(0)
    known = known[np.argsort(known["g"], kind="stable")]
    pos = np.minimum(np.searchsorted(known["g"], halo_rec["g"]), known.shape[0] - 1)
    rows = np.flatnonzero(known["g"][pos] == halo_rec["g"])
    return rows, known["key"][pos[rows]]


def _seeded(w: Store, tile: dict[str, Any], core: np.ndarray, cpts: np.ndarray, head: np.ndarray,
            hpts: np.ndarray, in_ext: np.ndarray, faces: tuple[str, ...]
            ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
    """The points a tile orders, its seeds (rows) and its timed seeds (rows, keys; None: none)."""
    head_in_core, pos_in_core = in_sorted(head["g"], core["g"])  # (core is in input order)
    extra = in_ext & ~head_in_core
    parts = [cpts, hpts[extra]] if extra.any() else [cpts]
    seeds = np.concatenate([pos_in_core, cpts.shape[0] + np.arange(int(extra.sum()))]).astype(np.int64)
    timed = None
    if faces:
        hrec = tile_records(w, tile["halo"])
        rows, keys = _timed(w, hrec, list(faces))
        if rows.size:
            first = cpts.shape[0] + int(extra.sum())
            parts.append(np.stack([hrec["x"][rows], hrec["y"][rows], hrec["z"][rows]], axis=1))
            timed = (first + np.arange(rows.size), keys)
    pts = np.concatenate(parts) if len(parts) > 1 else cpts
    return pts, seeds, timed


def _keys(o: Ordering, at: np.ndarray, p: np.ndarray, hpts: np.ndarray) -> np.ndarray:
    """The keys of the ordered points at positions ``at`` of the order (at ``p``): insertion
    radius, else distance to the head."""
    from scipy.spatial import cKDTree

    key = o.radius[at]  # (a copy: fancy indexing)
    unreached = ~np.isfinite(key)
    if unreached.any():  # the first point of a band component no seed reaches
        key[unreached] = cKDTree(hpts).query(p[unreached])[0] if hpts.shape[0] else 0.0
    return key


def _put_tile(w: Store, t: int, stream: np.ndarray, halo: float, face_out: str | None) -> tuple[dict[str, Any], int]:
    """Write a tile's face file, stream and seam points; returns the files and the seam's size."""
    files = {}
    if face_out is not None:
        near = stream[stream["m"] < halo]
        face = np.empty(near.shape[0], FACE)
        face["g"], face["key"] = near["g"].astype("<i8"), near["key"]
        files[Path(face_out).name] = w.put(Path(face_out).name, face[np.argsort(face["g"], kind="stable")])
    files[WL.stream(t)] = put_stream(w, WL.stream(t), stream)  # (what the merge reads: runs of rows by key)
    seam = stream["m"] < stream["key"]
    files[WL.seam(t)] = w.put(WL.seam(t), stream[seam])
    return files, int(seam.sum())


@timed_task
def order_tile(work: Store | str, t: int, tile: dict[str, Any], voxel_size: float, band_radius: float,
               halo: float, max_memory: int | None, faces: tuple[str, ...] = (), face_out: str | None = None,
               lattice: list[float] | None = None) -> dict[str, Any]:
    """FastFPS of tile ``t``: its own points, seeded with the head points in its core and halo, and
    with the halo points its neighbours have ordered (``faces``: their face files) as timed seeds:
    each enters the tile's ordering when the ordering's radius falls to its key, as it entered the
    neighbour's (``faces`` and ``face_out``: names in the store, or paths in the work directory
    whose names are taken). So the tile's points keep their distance from the neighbours' points of larger
    keys, as in one ordering of the whole scan (see :mod:`.driver`, the passes).

    Writes ``stream.<t>.keys``: the tile's points that are not head points, in its order (keys
    non-increasing), each with its key (its insertion radius in the tile, or its exact distance to
    the head when the tile reaches it from no seed); ``seam.<t>.bin``: those nearer a shared face
    than their key, with their position and margin to the tile's shared faces; and ``face_out``: the
    (input index, key) of its points within the halo width of a shared face. With ``lattice`` (the
    scan's grid: voxel corners a whole number of voxels from it), the band is on that grid and
    ``bandp.<t>.i4`` holds each core point's piece of it, for the tile's covering task
    (:func:`.pieces.tile_pieces`).
    """
    from ...sampling.fastfps import fastfps

    w = as_store(work)
    core = tile_records(w, tile["core"])
    head = w.read_array(WL.HEAD_FILE, HEAD)
    lo, hi = np.asarray(tile["lo"]), np.asarray(tile["hi"])
    interior = np.asarray(tile["interior"], bool)
    cpts = np.stack([core["x"], core["y"], core["z"]], axis=1)
    hpts = np.stack([head["x"], head["y"], head["z"]], axis=1)
    in_ext = np.all((hpts >= lo - halo) & (hpts <= hi + halo), axis=1)
    pts, seeds, timed = _seeded(w, tile, core, cpts, head, hpts, in_ext, faces)
    is_seed = np.zeros(pts.shape[0], bool)
    is_seed[seeds] = True
    o = fastfps(pts, seeds=seeds if seeds.size else None, voxel_size=voxel_size, band_radius=band_radius,
                max_memory=max_memory, timed_seeds=timed, lattice=lattice, pieces=lattice is not None)
    stream = _stream(o, is_seed, core, cpts, hpts, lo, hi, interior)
    files, n_seam = _put_tile(w, t, stream, halo, face_out)
    if o.pieces is not None:
        files[WL.band_labels(t)] = put_zipped(w, WL.band_labels(t), o.pieces[: cpts.shape[0]].astype("<i4"))
    return {"tile": t, "n_points": int(core.shape[0]), "n_stream": int(stream.shape[0]), "n_seeds": int(seeds.size),
            "n_timed": 0 if timed is None else int(timed[0].size), "n_seam": n_seam,
            "key_hist": WL.key_hist(stream["key"]),
            "band_voxels": int(o.stats.get("band_voxels", 0)), "files": files}


def _stream(o: Ordering, is_seed: np.ndarray, core: np.ndarray, cpts: np.ndarray, hpts: np.ndarray,
            lo: np.ndarray, hi: np.ndarray, interior: np.ndarray) -> np.ndarray:
    """A tile's stream: its core points that are not seeds, in its order ``o``, with their keys
    and margins."""
    at = np.flatnonzero((o.order < cpts.shape[0]) & ~is_seed[o.order])
    sel = o.order[at]
    p = cpts[sel]
    key = _keys(o, at, p, hpts)
    # the keys stay the tile's insertion radii even where a seed is nearer in Euclidean distance
    # (a head point in the halo that the tile's band does not reach, across a shared face): a key
    # lowered to that distance would merge the point late while the tile's later points, ordered
    # as if it were there, leave a hole around it (the covering at the level where the head hands
    # over to the tiles was 1.13-1.21 x the in-memory build's on a 1M-point sheet in 4 tiles)
    if key.shape[0] > 1 and not (key[1:] <= key[:-1]).all():  # (else the stable sort is the identity)
        srt = np.argsort(-key, kind="stable")
        sel, key, p = sel[srt], key[srt], p[srt]
    stream = np.empty(sel.shape[0], STREAM)
    stream["g"] = core["g"][sel]
    stream["key"] = key
    stream["x"], stream["y"], stream["z"] = p[:, 0], p[:, 1], p[:, 2]
    stream["m"] = _margins(p, lo, hi, interior)
    return stream


@timed_task
def cover_tile(work: Store | str, t: int, spacing: float, core_pieces: list[str], halo_pieces: list[str],
               pieces: dict[str, Any] | None = None, head_reach: float = 0.0) -> dict[str, Any]:
    """Exact covering radii of tile ``t``'s core in the final order, from its core and halo (their
    pieces, in block order) and the head points within ``head_reach`` of the core (:func:`head_near`);
    with ``pieces`` (see :func:`.pieces.tile_pieces`), the band pieces of the tile too, from the
    core and halo and their ranks.

    Writes ``cover.<t>.ev`` (rank, covering radius of the core by every point of smaller rank,
    whenever it changes) and ``cover.<t>.pt`` (for each core point in rank order: its rank, the
    rank of its nearest earlier point and the distance to it). Both are exact while the distance
    is below the halo width (below ``head_reach`` while every earlier point is a head point) and
    upper bounds beyond it."""
    from .pieces import borrowed_points, tile_pieces
    from .ranks import gather_ranks

    w = as_store(work)
    core = tile_records(w, core_pieces)
    halo = tile_records(w, halo_pieces)
    ext = np.concatenate([core, halo])
    ranks = gather_ranks(w, ext["g"])
    near, near_ranks = head_near(w, core, ext, head_reach)
    files, n_events = _cover(w, t, spacing, np.concatenate([ext, near]), np.concatenate([ranks, near_ranks]),
                             core.shape[0])
    res = {"tile": t, "n_ext": int(ranks.shape[0]), "n_events": n_events, "files": files}
    if pieces is not None:
        c = core.shape[0]
        borrowed, b_ranks = borrowed_points(w, halo, ranks[c:], pieces)
        del ext, halo
        piece_files, res["link_bands"] = tile_pieces(w, t, core, ranks[:c], borrowed, b_ranks, pieces)
        files.update(piece_files)
    return res


def head_near(w: Store, core: np.ndarray, ext: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The head points within ``reach`` of the box of ``core`` that ``ext`` (the core and halo) does
    not hold, as records, and their ranks (a head point's rank is its place in the head). The halo
    holds every point within the halo width of the tile; the coarse levels' covering radii are
    larger, so with the head's own points from farther away the covering of the core by a prefix
    of the head is exact wherever it is below ``reach`` (else the nearest of them is still an
    earlier point: an upper bound)."""
    from ...sampling.spacing import axis_max, axis_min

    if reach <= 0.0 or core.shape[0] == 0:
        return ext[:0], np.empty(0, np.int64)
    head = w.read_array(WL.HEAD_FILE, HEAD)
    hpts = np.stack([head["x"], head["y"], head["z"]], axis=1)
    cpts = np.stack([core["x"], core["y"], core["z"]], axis=1)
    gap = np.maximum(np.maximum(axis_min(cpts) - hpts, hpts - axis_max(cpts)), 0.0)
    by_g = np.argsort(head["g"], kind="stable")
    _, pos = in_sorted(ext["g"], head["g"][by_g])
    known = np.zeros(head.shape[0], bool)
    known[by_g[pos]] = True
    keep = np.flatnonzero((np.einsum("ij,ij->i", gap, gap) <= reach * reach) & ~known)
    rec = np.zeros(keep.shape[0], ext.dtype)
    rec["g"], rec["x"], rec["y"], rec["z"] = head["g"][keep], head["x"][keep], head["y"][keep], head["z"][keep]
    return rec, keep.astype(np.int64)


def _cover(w: Store, t: int, spacing: float, ext: np.ndarray, ranks: np.ndarray, n_core: int
           ) -> tuple[dict[str, Any], int]:
    """The covering pass of :func:`cover_tile` over ``ext`` (its first ``n_core`` records the
    core) with their ``ranks``: the files written and how many events."""
    from ..._kernels.tiled import cover_pass, stable_argsort
    from ...sampling.spacing import axis_max, axis_min

    is_core = np.zeros(ext.shape[0], bool)
    is_core[:n_core] = True
    srt = stable_argsort(np.ascontiguousarray(ranks, np.int64))
    ranks = np.ascontiguousarray(ranks[srt])
    xyz = np.ascontiguousarray(np.stack([ext["x"], ext["y"], ext["z"]], axis=1)[srt])
    is_core = np.ascontiguousarray(is_core[srt])
    n = ext.shape[0]
    ev_rank = np.empty(n + 1, np.int64)
    ev_val = np.empty(n + 1)
    pt_rank = np.empty(n_core, np.int64)
    pt_parent = np.empty(n_core, np.int64)
    pt_space = np.empty(n_core)
    # cells of about four point spacings (some 16 points of a surface), at most MAX_CELLS of them
    ext_size = axis_max(xyz) - axis_min(xyz) if n else np.ones(3)  # (np.ptp: the same values, 14 x slower)
    cell = max(4.0 * spacing, float(np.prod(ext_size + 8 * spacing) / MAX_CELLS) ** (1 / 3), 1e-300)
    ne, npt = cover_pass(xyz, ranks, is_core, cell, ev_rank, ev_val, pt_rank, pt_parent, pt_space)
    ev = np.empty(ne, EVENT)
    ev["rank"], ev["value"] = ev_rank[:ne], ev_val[:ne]
    pt = np.empty(npt, POINT)
    pt["rank"], pt["parent"], pt["space"] = pt_rank[:npt], pt_parent[:npt], pt_space[:npt]
    # (compressed in frames of the radii's bands of positions: see .radii)
    return {WL.cover_events(t): put_banded(w, WL.cover_events(t), ev, BLOCK),
            WL.cover_points(t): put_banded(w, WL.cover_points(t), pt, BLOCK)}, int(ne)
