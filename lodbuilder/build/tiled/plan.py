"""How a tiled build cuts its work: the memory budget, the tile size, the spatial tiles (a k-d split
of a point-count histogram) and the parameters every tile shares.

Memory model (measured; see tools/bench_tiled.py): an in-memory build needs about
``IN_MEMORY_BYTES_PER_POINT`` bytes per point plus the scan's own arrays; a tile ordering about
``TILE_BYTES_PER_POINT`` per point of the tile. ``max_memory`` is the budget of the whole process
tree on this machine: the parent keeps ``PARENT_RESERVE`` of it and the rest is shared by the
workers that run tiles at the same time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..._resources import default_max_memory, parse_bytes  # noqa: F401 - parse_bytes re-exported
from ...errors import InputError

IN_MEMORY_BYTES_PER_POINT = 900  # FastFPS band + ordering + the stored copy (557-870 B/pt measured)
TILE_BYTES_PER_POINT = 800  # a tile's FastFPS and its stream, with headroom
#: the coarse task's bytes per point of the decimated copy: its records and coordinates (56) and
#: the ordering on a grid of the head's scale (63-66 B/pt of peak RSS measured on copies of the
#: 99M-point survey of 0.69M, 1.91M and 2.84M points; FastFPS's own estimate is 120 B/pt and the band)
COARSE_BYTES_PER_POINT = 250
#: the parent's bytes per representative of the decimated copy while it makes the copy: the survey
#: tasks' results (key, input index, coordinates: 40) and :func:`.blocks.decimated_copy` (56,
#: measured with tracemalloc on 3.4M representatives of 900 blocks), with headroom
PARENT_COPY_BYTES_PER_POINT = 120
#: the share of the parent's memory the copy may take (the survey's first pass makes about 1.7 x
#: the copy's aim, and the aim is at most half the limit: about 0.6 of the parent's share at most)
PARENT_COPY_SHARE = 0.7
PROCESS_BYTES = 320 << 20  # a worker's own footprint: Python, NumPy, SciPy, h5py, compiled kernels
PARENT_FRACTION = 0.2  # share of the budget the parent keeps (merge buffers, write blocks)
PARENT_MIN = 600 << 20
MIN_TILE_POINTS = 2_000
#: tiles per worker the plan aims for (when the memory budget allows larger tiles): a tile waits
#: for its neighbours of smaller colours (4-5 colours on a survey), so the order phase lasts at
#: least a chain of about that many tiles. With C colours and k tiles per worker the chain is about
#: C / k of the phase's work per worker: at 4 the chain bounded the phase (the k-d split of the
#: 21.56M-point survey for 16 workers: 64 tiles in 5 colours, a chain of 1.27 x the work per worker;
#: the recorded 16-worker order phase 15.7 s against 11.5 s of work per worker), at 8 it is
#: 0.6-0.65 x (128 tiles). Smaller tiles cost more halo and seam work (the serial seam repair and
#: the join of the band pieces grow with the tile count).
TILES_PER_WORKER = 8
#: tiles sized for the workers are at least this large: a smaller tile costs more halo (read,
#: ordered as timed seeds, covered) and more seams per point (its side shrinks as the square root)
BALANCED_MIN_POINTS = 100_000
#: the k-d split halves tiles until they hold at most the capacity: a capacity this much above the
#: mean aimed for keeps a median split's unevenness from doubling the count
BALANCE_SLACK = 1.15
HIST_CELLS = 1 << 22  # cells of the count histogram (int32: 16 MiB)


def default_budget() -> int:
    return default_max_memory()


def needs_tiling(n_points: int, bytes_per_row: int, max_memory: int | None) -> bool:
    """True when an in-memory build of ``n_points`` would not fit ``max_memory``."""
    budget = default_budget() if max_memory is None else max_memory
    return n_points * (IN_MEMORY_BYTES_PER_POINT + 2 * bytes_per_row) > budget


def tile_capacity(max_memory: int, parallel: int) -> int:
    """Points per tile so that ``parallel`` tiles fit the budget at once beside the parent."""
    per_worker = worker_budget(max_memory, parallel)
    cap = int((per_worker - PROCESS_BYTES) / TILE_BYTES_PER_POINT)
    if cap < MIN_TILE_POINTS:
        raise InputError(f"max_memory={max_memory / 2**20:.0f} MiB leaves {max(per_worker, 0) / 2**20:.0f} MiB per worker "
                         f"for {parallel} worker(s): too little for a tile (each worker needs "
                         f"{(PROCESS_BYTES + MIN_TILE_POINTS * TILE_BYTES_PER_POINT) / 2**20:.0f} MiB at least); give "
                         "more memory or fewer workers")
    return cap


def coarse_capacity(max_memory: int, parallel: int) -> int:
    """Points of the decimated copy that one worker orders within its share of the budget (the
    coarse grid has far fewer voxels per point than a tile's: about 0.2 against 2-3) and that the
    parent makes within its own share (it gathers the blocks' representatives)."""
    worker = (worker_budget(max_memory, parallel) - PROCESS_BYTES) / COARSE_BYTES_PER_POINT
    parent = PARENT_COPY_SHARE * parent_budget(max_memory) / PARENT_COPY_BYTES_PER_POINT
    return max(0, int(min(worker, parent)))


def balanced_tile_points(n_points: int, parallel: int, fits: int) -> int:
    """Points per tile for ``parallel`` workers: what fits the memory budget (``fits``: see
    :func:`tile_capacity`), or less so that there are about TILES_PER_WORKER tiles per worker,
    but not below BALANCED_MIN_POINTS (one worker: what fits, the fewest tiles)."""
    if parallel <= 1:
        return fits
    aim = math.ceil(BALANCE_SLACK * n_points / (TILES_PER_WORKER * parallel))
    return min(fits, max(aim, BALANCED_MIN_POINTS))


#: bands of the merge per worker (after the serial seam repair every band is a task): on 16
#: workers the 21.56M survey's bands of at most 1M rows were 22 tasks, two rounds whose second
#: left 10 workers idle. A band costs about 0.09 CPU-s besides its rows (it opens every tile's
#: stream): in whole fine key bins (layout.hist_bins) 4 a worker made 83 bands of that survey, 10.7
#: CPU-s in all against 6.0 in 32 bands
MERGE_BANDS_PER_WORKER = 2
#: rows of a merge band sized for the workers, at least (each band reads every tile's run of it)
MIN_MERGE_BAND_ROWS = 1 << 17


def merge_band_rows(n_points: int, parallel: int, most: int) -> int:
    """Rows per band of the merge: ``most`` (see :data:`lodbuilder.build.tiled.merge.BAND_ROWS`),
    or fewer so that there are about MERGE_BANDS_PER_WORKER bands per worker, but not below
    MIN_MERGE_BAND_ROWS (the merged order is the same whatever the bands)."""
    if parallel <= 1:
        return most
    return min(most, max(MIN_MERGE_BAND_ROWS, math.ceil(n_points / (MERGE_BANDS_PER_WORKER * parallel))))


def parent_budget(max_memory: int) -> int:
    """Bytes the parent keeps of the budget."""
    return max(PARENT_MIN, int(PARENT_FRACTION * max_memory))


def worker_budget(max_memory: int, parallel: int) -> int:
    """Bytes each of ``parallel`` workers may use once the parent's share is set aside."""
    return int((max_memory - parent_budget(max_memory)) / max(parallel, 1))


@dataclass
class Grid:
    """The count histogram: ``shape`` cells of size ``cell`` from ``lo``."""

    lo: np.ndarray
    cell: float
    shape: tuple[int, int, int]

    @classmethod
    def around(cls, lo: np.ndarray, hi: np.ndarray, cells: int = HIST_CELLS) -> Grid:
        ext = np.maximum(np.asarray(hi, float) - np.asarray(lo, float), 0.0)
        span = float(ext.max()) or 1.0
        # cubic cells, at most ``cells`` of them
        vol = float(np.prod(np.maximum(ext, span * 1e-6)))
        cell = max((vol / cells) ** (1 / 3), span / 4096)
        shape = tuple(int(max(1, math.ceil(e / cell + 1e-9))) for e in ext)
        while shape[0] * shape[1] * shape[2] > cells:
            cell *= 1.1
            shape = tuple(int(max(1, math.ceil(e / cell + 1e-9))) for e in ext)
        return cls(np.asarray(lo, float), cell, shape)  # type: ignore[arg-type]

    def index(self, pts: np.ndarray) -> np.ndarray:
        """Flat cell index of each point (clamped into the grid)."""
        ijk = np.floor((pts - self.lo) / self.cell).astype(np.int64)
        for a in range(3):
            np.clip(ijk[:, a], 0, self.shape[a] - 1, out=ijk[:, a])
        return (ijk[:, 0] * self.shape[1] + ijk[:, 1]) * self.shape[2] + ijk[:, 2]


@dataclass
class Tile:
    """A box of grid cells ``[i0, i1) x [j0, j1) x [k0, k1)`` and its world bounds; ``interior``
    marks the faces shared with other tiles (lo/hi per axis), the only ones that make seams."""

    index: int
    cells: tuple[tuple[int, int], tuple[int, int], tuple[int, int]]
    lo: np.ndarray
    hi: np.ndarray
    n_points: int
    interior: np.ndarray = field(default_factory=lambda: np.zeros((2, 3), bool))

    def to_json(self) -> dict[str, Any]:
        return {"index": self.index, "cells": [list(c) for c in self.cells], "lo": self.lo.tolist(),
                "hi": self.hi.tolist(), "n_points": self.n_points, "interior": self.interior.tolist()}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Tile:
        return cls(int(d["index"]), tuple(tuple(c) for c in d["cells"]), np.asarray(d["lo"]),  # type: ignore[arg-type]
                   np.asarray(d["hi"]), int(d["n_points"]), np.asarray(d["interior"], bool))


def split_tiles(hist: np.ndarray, grid: Grid, cap: int) -> list[Tile]:
    """Cut the histogram's occupied box into tiles of at most ``cap`` points (as far as single
    cells allow): recursive median splits of the longest side, like a k-d tree."""
    counts = hist.reshape(grid.shape)
    occ = np.argwhere(counts > 0)
    if occ.size == 0:
        raise InputError("no points to tile")
    full = tuple((0, s) for s in grid.shape)
    out: list[tuple[tuple[tuple[int, int], ...], int]] = []
    stack = [full]
    while stack:
        box = stack.pop()
        sub = counts[box[0][0]:box[0][1], box[1][0]:box[1][1], box[2][0]:box[2][1]]
        n = int(sub.sum())
        if n == 0:
            continue
        sizes = [b[1] - b[0] for b in box]
        if n <= cap or max(sizes) <= 1:
            out.append((box, n))
            continue
        axis = int(np.argmax(sizes))
        prof = sub.sum(axis=tuple(a for a in range(3) if a != axis))
        cum = np.cumsum(prof)
        cut = int(np.searchsorted(cum, n / 2)) + 1
        cut = min(max(cut, 1), sizes[axis] - 1)
        lo_box = list(box)
        hi_box = list(box)
        lo_box[axis] = (box[axis][0], box[axis][0] + cut)
        hi_box[axis] = (box[axis][0] + cut, box[axis][1])
        stack.append(tuple(hi_box))
        stack.append(tuple(lo_box))
    tiles = []
    for i, (box, n) in enumerate(out):
        lo = grid.lo + np.array([b[0] for b in box]) * grid.cell
        hi = grid.lo + np.array([b[1] for b in box]) * grid.cell
        interior = np.array([[b[0] > 0 for b in box], [b[1] < s for b, s in zip(box, grid.shape, strict=True)]])
        tiles.append(Tile(i, box, lo, hi, n, interior))  # type: ignore[arg-type]
    return tiles


def tile_lookup(tiles: list[Tile], grid: Grid) -> np.ndarray:
    """Flat cell index -> tile index (int16; every cell of the grid belongs to one tile)."""
    table = np.full(grid.shape, -1, dtype=np.int16)
    for t in tiles:
        (i0, i1), (j0, j1), (k0, k1) = t.cells
        table[i0:i1, j0:j1, k0:k1] = t.index
    return table.reshape(-1)


def tile_neighbours(tiles: list[Tile], halo: float) -> list[list[int]]:
    """For each tile, the tiles whose boxes come within ``halo`` of it (they share halo points)."""
    lo = np.array([t.lo for t in tiles]).reshape(-1, 3)
    hi = np.array([t.hi for t in tiles]).reshape(-1, 3)
    out = []
    for i in range(len(tiles)):
        near = np.all((lo <= hi[i] + halo) & (hi >= lo[i] - halo), axis=1)
        near[i] = False
        out.append(np.flatnonzero(near).tolist())
    return out


def colour_tiles(neighbours: list[list[int]]) -> list[int]:
    """A colour per tile, no two neighbours alike (greedy, most neighbours first): tiles of one
    colour can be ordered at the same time, each seeing the tiles of other colours."""
    colour = [-1] * len(neighbours)
    for i in sorted(range(len(neighbours)), key=lambda i: (-len(neighbours[i]), i)):
        taken = {colour[j] for j in neighbours[i]}
        colour[i] = next(c for c in range(len(neighbours) + 1) if c not in taken)
    return colour
