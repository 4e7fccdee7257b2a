"""The first three phases of a tiled build as tasks: read, plan and distribute (the parent plans
them from the inputs' headers and sums what the tasks return; it reads no point).

* **inputs** (parent): the inputs' headers (point counts, fields, CRS) cut into read blocks: a
  small input is one block, a big one ranges of rows (a multiple of the chunk size, so that the
  chunks are the ones a single reader would read); the input index ``g`` of a point is its row in
  the inputs read one after the other, as listed.
* **read** (tasks, :func:`.blocks.read_block`): each block decoded and posed, its coordinates
  written (until the tiles' pieces are: the write reads the inputs again); the parent sums counts,
  bounds, encodings, the spacing sample and the blocks' sums into the ``spill`` marker.
* **plan** (tasks, :func:`.blocks.survey_block`): the count histogram on a grid over the exact
  bounds, and the decimated copy (the first point of each cell in input order), summed by the
  parent, which cuts the tiles (a k-d split of the histogram).
* **distribute** (tasks, :func:`.blocks.distribute_block`): each block cut into the tiles' core and
  halo pieces; a tile task reads its pieces in block order (its points in input order).

Everything the tasks return is the same whatever the blocks are (sums, minima and maxima, the
first point of a cell by input index), so the plan, the tiles and the order equal those of one
reader that reads every point in input order.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
from pathlib import Path
from typing import Any

import numpy as np

from ...progress import ProgressCallback
from . import layout as WL
from . import plan as P
from . import workdir as W
from .blocks import decimated_copy, distribute_block, read_block, survey_block
from .pool import collect, submit
from .store import Store
from .sums import done, mark, prune
from .workdir import SAMPLE, Spill

#: read tasks per worker (a big input is cut into about this many blocks per worker)
READ_TASKS_PER_WORKER = 2


def plan_inputs(sources: list[tuple[Any, ...]], parallel: int, rows: int) -> dict[str, Any]:
    """The read blocks of ``sources`` (``(stream, pose, member, reopen)``) from their headers, and
    what the scan keeps: its fields (a joint build keeps those every input with points has, and
    adds ``scan_id`` and ``scan_point``), metadata and members (an input with no points is a
    member with none: no block)."""
    joint = len(sources) > 1 or sources[0][2] is not None
    full = [s for s in sources if int(s[0].n_points) > 0] or sources
    first = full[0][0]
    common = set(first.fields)
    for s in full[1:]:
        common &= {k for k, v in s[0].fields.items() if v == first.fields.get(k)}
    names = sorted(common) if joint else list(first.fields)
    fields = {k: [np.dtype(first.fields[k][0]).str, list(first.fields[k][1])] for k in names}
    if joint:
        fields["scan_id"] = [np.dtype(np.int32).str, []]
        fields["scan_point"] = [np.dtype(np.int64).str, []]
    n = sum(int(s[0].n_points) for s in sources)
    per = rows * max(1, math.ceil(n / (rows * READ_TASKS_PER_WORKER * max(1, parallel))))
    blocks, members, g = [], [], 0
    for i, s in enumerate(sources):
        m = int(s[0].n_points)
        step = max(1, m) if s[3] is None else per  # a scan the parent hands out is one block
        blocks += [[i, a, min(m, a + step), g + a] for a in range(0, m, step)]
        path = getattr(s[0], "path", None)  # (the file a failed task's points came from: see .timing)
        members.append({"id": s[2], "n_points": m, "first": g,
                        "source": Path(path).name if path and Path(path).is_file() else None})
        g += m
    return {"n": n, "fields": fields, "joint": joint, "rows": rows, "step": max(1, n // SAMPLE),
            "metadata": dict(first.metadata) if not joint else joint_metadata(full),
            "reader": first.reader if not joint else "joint", "members": members, "blocks": blocks}


def joint_metadata(sources: list[tuple[Any, ...]]) -> dict[str, Any]:
    """The metadata of a joint scan: the sources' CRS when they all share one (the build refused
    them otherwise, or reprojected them to one), and their LAS scale when they all share one
    (with the first one's offset), so that a survey of LAS/LAZ tiles keeps integer coordinates
    where they are exact on that grid (each block checks: see :func:`.blocks.read_block`)."""
    from ...io.crs import KEY_REPROJECTION, KEY_SOURCE, KEY_UNITS, KEY_WKT, same_crs

    metas = [s[0].metadata for s in sources]
    out: dict[str, Any] = {}
    scales = [m.get("las_scales") for m in metas]
    if scales[0] is not None and metas[0].get("las_offsets") is not None and all(s == scales[0] for s in scales):
        out = {"las_scales": list(scales[0]), "las_offsets": list(metas[0]["las_offsets"])}
    if not metas[0].get(KEY_WKT) or not all(m.get(KEY_WKT) and same_crs(m[KEY_WKT], metas[0][KEY_WKT]) for m in metas):
        return out
    out.update({k: metas[0][k] for k in (KEY_WKT, KEY_UNITS, KEY_SOURCE) if metas[0].get(k) is not None})
    reps = [m[KEY_REPROJECTION] for m in metas if KEY_REPROJECTION in m]
    if reps:
        out[KEY_REPROJECTION] = reps
    return out


def read_phase(ex: cf.Executor, work: Store, name: str, sources: list[tuple[Any, ...]], parallel: int,
               progress: ProgressCallback) -> Spill:
    """Phases inputs and read: every block read by a task (an input the parent holds in memory by
    the parent), summed into the ``spill`` marker (or what a finished read recorded)."""
    doc = done(work, "spill")
    if doc is not None:  # (the sample is read by the plan alone: deleted once it is done)
        return Spill.from_json(doc, work.load_npy(WL.SAMPLE) if work.size(WL.SAMPLE) is not None else np.zeros((0, 3)))
    inp = done(work, "inputs") or mark(work, "inputs", plan_inputs(sources, parallel, W.BLOCK))
    spec = {k: inp[k] for k in ("fields", "joint", "metadata", "step", "rows")}
    results = {}
    calls: list[tuple[int, Any, tuple]] = []
    inline: list[tuple[int, Any, tuple]] = []
    for b, (i, a, z, g0) in enumerate(inp["blocks"]):
        prev = done(work, WL.read_piece(b))
        if prev is not None:
            results[b] = prev
            continue
        stream, pose, member, reopen = sources[i]
        args = (work, b, reopen if reopen is not None else (stream, pose), member, a, z, g0, spec)
        (calls if reopen is not None else inline).append((b, read_block, args))
    futs = submit(ex, calls)

    def record(res: dict[str, Any]) -> None:
        results[res["block"]] = mark(work, WL.read_piece(res["block"]), res)

    def where(b: int) -> str:
        return f"reading {sources[inp['blocks'][b][0]][0].path}"

    try:
        for _, fn, args in inline:
            record(fn(*args))
    finally:
        start = sum(int(r["n"]) for r in results.values())
        collect(futs, where, name, int(inp["n"]), progress, "read", record, lambda r: int(r["n"]), start)
    return _spill(work, inp, [results[b] for b in range(len(inp["blocks"]))])


def _spill(work: Store, inp: dict[str, Any], res: list[dict[str, Any]]) -> Spill:
    """The read blocks summed: the ``spill`` marker (and the whole sample, ``sample.npy``)."""
    from ...archive.layout import choose_encoding

    n = sum(int(r["n"]) for r in res)
    if n != int(inp["n"]):
        raise RuntimeError(f"the read blocks hold {n} points, the inputs' headers {inp['n']}")
    sample = np.concatenate([work.read_array(WL.sample(b), "<f8").reshape(-1, 3) for b in range(len(res))])
    with work.writer(WL.SAMPLE) as f:
        np.save(f, sample)
    # (the blocks' samples are not listed: deleted once summed, they are the read tasks' own)
    files = {k: v for r in res for k, v in r["files"].items() if WL.consumers(k) != ["spill"]}
    enc = choose_encoding({e for r in res for e in r["encodings"]} or {"float64"})
    sp = Spill(n, np.min([r["lo"] for r in res], axis=0), np.max([r["hi"] for r in res], axis=0),
               {k: (v[0], tuple(v[1])) for k, v in inp["fields"].items()}, sample, inp["metadata"], inp["reader"],
               inp["members"], enc, {**files, WL.SAMPLE: f.sum}, inp["blocks"], int(inp["rows"]),
               [r.get("crc") for r in res])
    mark(work, "spill", sp.to_json())
    return sp


def _blocks(sp: Spill) -> list[tuple[int, int, int]]:
    """(block, first input index, rows) of every read block."""
    return [(b, int(g0), int(z) - int(a)) for b, (_, a, z, g0) in enumerate(sp.blocks or [])]


def _survey(ex: cf.Executor, work: Store, name: str, sp: Spill, grid: P.Grid, d_cell: float, histogram: bool,
            progress: ProgressCallback) -> list[dict[str, Any]]:
    g = {"lo": grid.lo.tolist(), "cell": grid.cell, "shape": list(grid.shape)}
    calls = [(b, survey_block, (work, b, g0, m, sp.rows, g, d_cell, histogram)) for b, g0, m in _blocks(sp)]
    return collect(submit(ex, calls), lambda b: f"the plan of block {b + 1}", name, sp.n, progress, "plan",
                   count=lambda r: int(r["n"]), start=0)


def plan_phase(ex: cf.Executor, work: Store, name: str, sp: Spill, params: dict[str, Any], limit: int, cap: int,
               m_target: int, progress: ProgressCallback) -> dict[str, Any]:
    """Phase plan: the count histogram and the decimated copy from the blocks (tasks), the tiles
    (a k-d split of the histogram); ``params``: the spacing, voxel size and band radius. Returns
    the plan marker (or what a finished plan recorded)."""
    pl = done(work, "plan")
    if pl is not None:
        return pl
    n, s = sp.n, float(params["spacing"])
    grid = P.Grid.around(sp.lo, sp.hi)
    span = float(np.max(sp.hi - sp.lo)) or 1.0
    d_cell = max(s * math.sqrt(n / m_target), span / (1 << 20))
    parts = _survey(ex, work, name, sp, grid, d_cell, True, progress)
    hist = np.zeros(int(np.prod(grid.shape)), np.int64)
    for p in parts:
        hist[p["cells"]] += p["counts"]  # a block's cells are distinct
    dec = decimated_copy(parts)
    while dec.shape[0] > limit:  # the cell count overshot the target: coarser cells, one more pass
        d_cell *= 1.1 * math.sqrt(dec.shape[0] / limit)
        dec = decimated_copy(_survey(ex, work, name, sp, grid, d_cell, False, progress))
    sums = work.put(WL.DECIMATED, dec)
    tiles = P.split_tiles(hist, grid, cap)
    return mark(work, "plan", {**params, "tile_cap": cap, "tiles": [t.to_json() for t in tiles],
                                "grid": {"lo": grid.lo.tolist(), "cell": grid.cell, "shape": list(grid.shape)},
                                "d_cell": d_cell, "span": span, "n_decimated": int(dec.shape[0]),
                                "files": {WL.DECIMATED: sums}})


def distribute_phase(ex: cf.Executor, work: Store, name: str, sp: Spill, pl: dict[str, Any], halo: float,
                     progress: ProgressCallback) -> dict[str, Any]:
    """Phase distribute: every block cut into the tiles' pieces by a task; the marker holds the
    halo width, each tile's core and halo sizes and the names of its pieces in block order."""
    dist = done(work, "distribute")
    if dist is not None:  # (a resume that read blocks again, for a damaged plan: their coordinates go again)
        prune(work, [n for n in work.names("raw.") if WL.consumers(n) is not None])
        return dist
    results = {}
    calls = []
    for b, g0, m in _blocks(sp):
        prev = done(work, WL.split_piece(b))
        if prev is not None:
            results[b] = prev
        else:
            calls.append((b, distribute_block, (work, b, g0, m, sp.rows, pl["tiles"], pl["grid"], halo)))

    def record(res: dict[str, Any]) -> None:
        results[res["block"]] = mark(work, WL.split_piece(res["block"]), res)

    collect(submit(ex, calls), lambda b: f"the split of block {b + 1}", name, sp.n, progress, "split", record,
            lambda r: int(np.sum(r["n_core"])), sum(int(np.sum(r["n_core"])) for r in results.values()))
    res = [results[b] for b in range(len(results))]
    n_tiles = len(pl["tiles"])
    core = np.array([r["n_core"] for r in res], np.int64).reshape(len(res), n_tiles)
    hal = np.array([r["n_halo"] for r in res], np.int64).reshape(len(res), n_tiles)
    pieces = {"core": [[WL.core(t, int(b)) for b in np.flatnonzero(core[:, t])] for t in range(n_tiles)],
              "halo": [[WL.halo(t, int(b)) for b in np.flatnonzero(hal[:, t])] for t in range(n_tiles)]}
    files = {k: v for r in res for k, v in r["files"].items()}
    return mark(work, "distribute", {"halo": halo, "n_core": core.sum(axis=0).tolist(),
                                      "n_halo": hal.sum(axis=0).tolist(), "pieces": pieces, "files": files})

