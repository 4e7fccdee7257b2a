"""The tasks that read a survey and cut it into tiles, one block of input points each (run on the
workers; the parent only plans them and sums what they return).

A *block* is a range of rows of one input file (a whole small file, or a range of a big LAS/LAZ,
PLY or NPY file that the reader seeks to). Its points have the consecutive input indices
``g0 .. g0 + m`` (the inputs one after the other, as listed). Three tasks per block:

* :func:`read_block`: decode the rows, apply the pose, write the block's coordinates and return
  its count, exact bounds, the coordinate encodings it allows, its points of the scan's spacing
  sample (input index a multiple of the sample step) and the sums of its rows (the attributes are
  not copied: the write reads the block from the input again, :func:`.write.bucket_block`);
* :func:`survey_block`: the block's share of the plan: its count histogram on the plan's grid and
  its cell representatives of the decimated copy (the first point of each cell in input order);
* :func:`distribute_block`: the block's points written into per-tile pieces (core and halo).

Every file is written whole to the work store and appears when complete (:mod:`.store`); a task's
result lists its files with their sums, and the parent records it as the task's marker.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import numpy as np

from ...errors import FormatError
from . import layout as WL
from .plan import Grid, Tile, tile_lookup
from .store import Store, Writer, as_store
from .timing import timed_task
from .workdir import REC, Zipped, opaque_rows, unzipped, zipped_blocks

JOINT_FIELDS = ("scan_id", "scan_point")


class _Out:
    """Work objects written whole, committed together by :meth:`publish` (a task's outputs);
    those named in ``zipped`` (every one: True) are written compressed (see .workdir.Zipped)."""

    def __init__(self, store: Store, zipped: tuple[str, ...] | bool = ()) -> None:
        self.store = store
        self.zipped = zipped
        self.files: dict[str, Writer | Zipped] = {}

    def write(self, name: str, data: np.ndarray) -> None:
        if name not in self.files:
            w = self.store.writer(name)
            zip_it = self.zipped if isinstance(self.zipped, bool) else name in self.zipped
            self.files[name] = Zipped(w) if zip_it else w
        self.files[name].write(data)

    def close(self) -> None:
        """Discard what was not published (a failed task leaves no object)."""
        for f in self.files.values():
            f.close()

    def publish(self) -> dict[str, list[int]]:
        return {name: f.commit() for name, f in self.files.items()}


def block_rows(stream: Any, pose: Any, member: int | None, start: int, stop: int, spec: dict[str, Any]
               ) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
    """Rows ``start .. stop`` of one input as the build keeps them, chunk by chunk: the posed
    float64 coordinates and the attribute records (:func:`.layout.attr_record` of ``spec``'s
    fields; None when it keeps no field: a joint build's ``scan_id`` is ``member``, its
    ``scan_point`` the row). The read and the write's permutation (which reads the input again:
    :func:`.write.bucket_block`) both read a block through this; FormatError when the input holds
    fewer rows than its header declares."""
    from ...io.pose import apply_pose

    fields = {k: (v[0], tuple(v[1])) for k, v in spec["fields"].items()}
    rec_dt = WL.attr_record(fields)
    own = [k for k in fields if not (spec["joint"] and k in JOINT_FIELDS)]
    got = 0
    for chunk in stream.chunks(int(spec["rows"]), start, stop):
        pts = chunk.points if pose is None else apply_pose(chunk.points, np.asarray(pose))
        pts = np.ascontiguousarray(pts, dtype="<f8")
        m = pts.shape[0]
        rec = None
        if rec_dt.itemsize:
            rec = np.empty(m, rec_dt)
            for i, k in enumerate(fields):
                rec[f"a{i}"] = chunk.attributes[k] if k in own else (
                    np.full(m, member or 0) if k == "scan_id" else np.arange(chunk.start, chunk.start + m))
        got += m
        yield pts, rec
    if got != stop - start:
        raise FormatError(f"{stream.path}: rows {start}..{stop} hold {got} points, the header declares "
                          f"{stop - start}; re-export the file")


def rows_sum(crc: list[int], pts: np.ndarray, rec: np.ndarray | None) -> list[int]:
    """``crc`` (CRC-32 of a block's coordinates, of its attribute records) carried over one more
    chunk of :func:`block_rows` (chunks of any size give the block's sums)."""
    return [zlib.crc32(cast(Any, pts), crc[0]), crc[1] if rec is None else zlib.crc32(cast(Any, rec), crc[1])]


@timed_task
def read_block(work: Store | str, b: int, source: Any, member: int | None, start: int, stop: int, g0: int,
               spec: dict[str, Any]) -> dict[str, Any]:
    """Read rows ``start .. stop`` of one input (``source``: a picklable opener returning
    ``(stream, pose)``, or that pair) as block ``b`` (input indices from ``g0``). ``spec``: the
    fields kept, whether the build is joint, the metadata the encoding is chosen by, the sample
    step and the rows per chunk. Writes the block's coordinates (``raw.<b>.xyz``, read by the
    plan and the split) and its sample; its attributes are not kept (the write reads the input
    again: the returned ``crc`` checks that it reads the same rows)."""
    from ...archive.layout import encode_points
    from ...sampling.spacing import axis_max, axis_min

    stream, pose = source() if callable(source) else source
    step, meta = int(spec["step"]), spec["metadata"]
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    samples, encodings = [], set()
    out = _Out(as_store(work), (WL.raw_xyz(b),))
    g, crc = g0, [0, 0]
    try:
        for pts, rec in block_rows(stream, pose, member, start, stop, spec):
            out.write(WL.raw_xyz(b), pts)
            crc = rows_sum(crc, pts, rec)
            encodings.add(encode_points(pts, meta)[1])
            lo, hi = np.minimum(lo, axis_min(pts)), np.maximum(hi, axis_max(pts))
            samples.append(pts[(-g) % step::step])
            g += pts.shape[0]
        smp = np.concatenate(samples) if samples else np.zeros((0, 3))
        out.write(WL.sample(b), np.ascontiguousarray(smp, dtype="<f8"))
        files = out.publish()
    finally:
        out.close()
    return {"block": b, "n": g - g0, "lo": lo.tolist(), "hi": hi.tolist(), "encodings": sorted(encodings),
            "crc": crc, "files": files}


def _xyz_blocks(work: Store, b: int, m: int, rows: int) -> Any:
    for lo, a in zipped_blocks((work, WL.raw_xyz(b)), "<f8", 3 * m, 3 * rows):
        yield lo // 3, a.reshape(-1, 3)


@timed_task
def survey_block(work: Store | str, b: int, g0: int, m: int, rows: int, grid: dict[str, Any], d_cell: float,
                 histogram: bool = True) -> dict[str, Any]:
    """Block ``b``'s count histogram on ``grid`` (sparse: occupied cells and counts, when
    ``histogram``) and its representatives of the decimated copy: for each cubic cell of size
    ``d_cell`` (from the grid's corner) its first point (cell key, input index, coordinates)."""
    w = as_store(work)
    gr = Grid(np.asarray(grid["lo"]), float(grid["cell"]), tuple(grid["shape"]))
    occupied, counts = [], []  # (sparse: a dense histogram of the whole grid per block cost more than the block)
    keys, gs, xyz = [], [], []
    for r0, pts in _xyz_blocks(w, b, m, rows):
        if histogram:
            cells, n_in = np.unique(gr.index(pts), return_counts=True)
            occupied.append(cells)
            counts.append(n_in.astype(np.int64))
        c = np.floor((pts - gr.lo) / d_cell).astype(np.int64)
        key = (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]
        ukey, first = np.unique(key, return_index=True)
        keys.append(ukey)
        gs.append(first + g0 + r0)
        xyz.append(pts[first])
    key_a, g_a, p_a = np.concatenate(keys), np.concatenate(gs), np.concatenate(xyz)
    order = np.lexsort((g_a, key_a))
    key_a, g_a, p_a = key_a[order], g_a[order], p_a[order]
    keep = np.ones(key_a.shape[0], bool)
    keep[1:] = key_a[1:] != key_a[:-1]
    cells, hist = _sparse_sum(occupied, counts)
    return {"block": b, "n": m, "cells": cells, "counts": hist, "keys": key_a[keep], "g": g_a[keep],
            "xyz": p_a[keep]}


def _sparse_sum(cells: list[np.ndarray], counts: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The sum of sparse histograms (each: increasing cells, their counts): its occupied cells,
    increasing, and their counts."""
    if len(cells) <= 1:
        return (cells[0], counts[0]) if cells else (np.zeros(0, np.int64), np.zeros(0, np.int64))
    occupied, at = np.unique(np.concatenate(cells), return_inverse=True)
    total = np.zeros(occupied.shape[0], np.int64)
    np.add.at(total, at, np.concatenate(counts))
    return occupied, total


def decimated_copy(parts: list[dict[str, Any]]) -> np.ndarray:
    """The decimated copy from every block's representatives: the first point of each cell in
    input order, as REC records in input order. The parent runs it on every block's result: it
    sorts the keys and input indices alone and gathers the coordinates one axis at a time (56 B a
    representative besides the results, where sorting whole rows took 113 B and 3 x the CPU)."""
    keys = np.concatenate([p["keys"] for p in parts])
    gs = np.concatenate([p["g"] for p in parts])
    order = np.lexsort((gs, keys))
    k = keys[order]
    del keys
    first = np.empty(k.shape[0], bool)  # (the first of each cell's rows in key, then input order)
    first[:1] = True
    np.not_equal(k[1:], k[:-1], out=first[1:])
    del k
    sel = order[first]  # rows of the concatenation
    del order, first
    sel = sel[np.argsort(gs[sel], kind="stable")]
    out = np.empty(sel.shape[0], REC)
    out["g"] = gs[sel]
    del gs
    for a, axis in enumerate("xyz"):
        out[axis] = np.concatenate([p["xyz"][:, a] for p in parts])[sel]
    return out


@timed_task
def distribute_block(work: Store | str, b: int, g0: int, m: int, rows: int, tiles: list[dict[str, Any]],
                     grid: dict[str, Any], halo: float) -> dict[str, Any]:
    """Write block ``b``'s points into the pieces of the tiles (``core.<t>.<b>.bin``: the tile's
    own points; ``halo.<t>.<b>.bin``: points of other tiles within ``halo`` of its box); returns
    the rows of each tile's pieces."""
    w = as_store(work)
    tl = [Tile.from_json(t) for t in tiles]
    gr = Grid(np.asarray(grid["lo"]), float(grid["cell"]), tuple(grid["shape"]))
    lookup = tile_lookup(tl, gr)
    t_lo = np.array([t.lo for t in tl], float).reshape(-1, 3)
    t_hi = np.array([t.hi for t in tl], float).reshape(-1, 3)
    n_core = np.zeros(len(tl), np.int64)
    n_halo = np.zeros(len(tl), np.int64)
    out = _Out(w, True)
    try:
        for r0, pts in _xyz_blocks(w, b, m, rows):
            _split(out, b, g0 + r0, pts, lookup[gr.index(pts)], t_lo, t_hi, halo, gr.cell, n_core, n_halo)
        files = out.publish()
    finally:
        out.close()
    return {"block": b, "n_core": n_core.tolist(), "n_halo": n_halo.tolist(), "files": files}


def _split(out: _Out, b: int, g0: int, pts: np.ndarray, own: np.ndarray, t_lo: np.ndarray, t_hi: np.ndarray,
           halo: float, cell: float, n_core: np.ndarray, n_halo: np.ndarray) -> None:
    """One chunk of a block into the tiles' core and halo pieces (``cell``: the grid's cell size)."""
    from ..._kernels.tiled import halo_members

    m, n_tiles = pts.shape[0], t_lo.shape[0]
    rec = np.empty(m, REC)
    rec["g"] = np.arange(g0, g0 + m)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    raw = opaque_rows(rec)
    order = np.argsort(own, kind="stable")
    bounds = np.searchsorted(own[order], np.arange(n_tiles + 1))
    # a point lies in another tile's halo only within the halo width of its own tile's faces (the
    # tiles' boxes do not overlap); it is tested against the tiles near its own (a point lies at most
    # a grid cell outside its own tile's box: the grid clamps)
    near = _near_tiles(t_lo, t_hi, 2 * halo + cell)
    start, members = halo_members(pts, np.ascontiguousarray(own, np.int64), t_lo, t_hi, halo,
                                  np.concatenate([[0], np.cumsum(near.sum(axis=1))]), np.nonzero(near)[1])
    for t in range(n_tiles):
        sel = order[bounds[t]:bounds[t + 1]]
        if sel.size:
            out.write(WL.core(t, b), raw[sel])
            n_core[t] += sel.size
        if start[t + 1] > start[t]:
            out.write(WL.halo(t, b), raw[members[start[t]:start[t + 1]]])
            n_halo[t] += int(start[t + 1] - start[t])


def _near_tiles(t_lo: np.ndarray, t_hi: np.ndarray, reach: float) -> np.ndarray:
    """(T, T) bool: tile b's box comes within ``reach`` of tile a's on every axis (b != a)."""
    near = np.all((t_lo[None, :] <= t_hi[:, None] + reach) & (t_hi[None, :] >= t_lo[:, None] - reach), axis=2)
    np.fill_diagonal(near, False)
    return near


def tile_records(work: Store | Path, names: list[str]) -> np.ndarray:
    """A tile's core or halo: its pieces (``names``, in block order; compressed) one after the other."""
    store = as_store(work)
    parts = [unzipped(store.get(n), REC, n) for n in names]
    return np.concatenate(parts) if parts else np.zeros(0, REC)
