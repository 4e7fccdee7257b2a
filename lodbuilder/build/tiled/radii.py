"""The stored radius and parent of every position of a tiled build, assembled in bands of stored
positions by tasks (the parent only carries two numbers from band to band).

A band ``[k0, k1)`` of positions needs, from every tile, its covering events with rank in the band
and the last one before it (the tile's covering radius at ``k0``), and its points' records with
rank in the band: both files are sorted by rank, so a task reads them with two binary searches and
one slice (:func:`_slice`), never whole. Two rounds:

1. :func:`radii_band`: the largest covering radius over the tiles at each position, capped by the
   coarse level's certified bound, made non-increasing *within* the band (``radloc.<b>.f8``); the
   parents (``parent.<b>.i8``, final) and the running minimum of the spacing (``space.<b>.f8``);
   returns the band's last radius and spacing;
2. :func:`finish_band`: with the minimum of the earlier bands' last values (the parent's prefix
   minimum over bands: O(bands)), the final radii (``radius.<b>.f8``: min(local, incoming), i.e.
   the running minimum over the whole order) and the band's worst spacing over radius.

The arithmetic is that of one sequential pass (a running minimum is the minimum of the band's own
running minimum and the incoming value), so the radii are the same bytes whatever the bands.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ...progress import ProgressCallback
from . import layout as WL
from .pool import collect, submit
from .store import Store, as_store
from .sums import done, get_json, mark
from .timing import timed_task
from .workdir import banded_slice, get_zipped, put_framed, put_zipped

EVENT, POINT, HEAD = WL.EVENT, WL.POINT, WL.HEAD


def _events(work: Store, n_tiles: int, k0: int, k1: int) -> tuple[np.ndarray, ...]:
    """Every tile's events in the band as merge_events wants them (rank, tile, value; by rank), and
    each tile's value at k0."""
    from ..._kernels.tiled import stable_argsort

    evs, cur = [], np.full(n_tiles, np.inf)
    for t in range(n_tiles):
        recs, before = banded_slice(work, WL.cover_events(t), EVENT, k0, k1)
        evs.append(recs)
        if before is not None:
            cur[t] = float(before["value"])
    ev = np.concatenate(evs) if evs else np.zeros(0, EVENT)
    tile = np.repeat(np.arange(n_tiles, dtype=np.int64), [e.shape[0] for e in evs])
    by_rank = stable_argsort(np.ascontiguousarray(ev["rank"] - k0, np.int64))  # (a tile's own events stay in order)
    return (np.ascontiguousarray(ev["rank"][by_rank], np.int64), tile[by_rank],
            np.ascontiguousarray(ev["value"][by_rank], np.float64), cur)


@timed_task
def radii_band(work: Store | str, band: int, k0: int, k1: int, n_tiles: int, delta: float, r_cut: float) -> dict[str, Any]:
    """Round 1 of band ``band`` (positions ``k0 .. k1``): see the module."""
    from ..._kernels.tiled import merge_events

    w = as_store(work)
    head = w.read_array(WL.HEAD_FILE, HEAD)
    h = head.shape[0]
    ev_rank, ev_tile, ev_val, cur = _events(w, n_tiles, k0, k1)
    rad = np.empty(k1 - k0)
    merge_events(ev_rank, ev_tile, ev_val, cur, k0, k1, rad)
    ks = np.arange(k0, k1)
    inh = ks < h
    # the coarse level's certified bound (radius on the decimated copy + its cell diagonal)
    bound = np.full(k1 - k0, r_cut + delta)
    bound[inh] = np.where(ks[inh] == 0, np.inf, head["r"][np.minimum(ks[inh], h - 1)] + delta)
    rad = np.minimum.accumulate(np.minimum(rad, bound))
    par = np.full(k1 - k0, -1, np.int64)
    space = np.full(k1 - k0, np.inf)
    for t in range(n_tiles):
        recs, _ = banded_slice(w, WL.cover_points(t), POINT, k0, k1)
        par[recs["rank"] - k0] = recs["parent"]
        space[recs["rank"] - k0] = recs["space"]
    # a head point with no earlier point in its tile's halo: its parent on the coarse copy
    hk = inh & (par < 0) & (ks > 0)
    par[hk] = head["parent"][ks[hk]]
    space = np.minimum.accumulate(space)
    b = band
    files = {WL.radius_local(b): put_zipped(w, WL.radius_local(b), rad), WL.space(b): put_zipped(w, WL.space(b), space),
             WL.parent(b): put_framed(w, WL.parent(b), par)}
    return {"band": b, "last_radius": float(rad[-1]), "last_space": float(space[-1]), "files": files}


@timed_task
def finish_band(work: Store | str, band: int, k0: int, k1: int, run_min: float, run_space: float) -> dict[str, Any]:
    """Round 2 of band ``band``: the final radii with the earlier bands' minima (``run_min``,
    ``run_space``), and the band's worst spacing over radius (ratio, position)."""
    w, b = as_store(work), band
    rad = np.minimum(get_zipped(w, WL.radius_local(b), "<f8"), run_min)
    space = get_zipped(w, WL.space(b), "<f8")
    # spacing of level k (its first k points): every position before k
    lvl_space = np.minimum(np.concatenate([[np.inf], space[:-1]]), run_space)
    ok = (rad > 0) & np.isfinite(rad) & np.isfinite(lvl_space)
    worst, at = math.inf, -1
    if ok.any():
        ratio = lvl_space[ok] / rad[ok]
        i = int(np.argmin(ratio))
        worst, at = float(ratio[i]), int(np.arange(k0, k1)[ok][i])
    return {"band": b, "worst": worst, "at": at, "files": {WL.radius(b): put_framed(w, WL.radius(b), rad)}}


def radii_phase(ex: Any, work: Any, name: str, n: int, n_tiles: int, delta: float, band: int,
                progress: ProgressCallback = None) -> dict[str, Any]:
    """The radii and parents of every position, in bands of ``band`` positions (tasks); returns the
    radii marker: the bands, their files and the worst spacing over radius of any level."""
    doc = done(work, "radii")
    if doc is not None:
        return doc
    r_cut = float((get_json(work, WL.marker("coarse")) or {})["r_cut"])
    bands = [(k0, min(n, k0 + band)) for k0 in range(0, n, band)]
    first: dict[int, dict[str, Any]] = {}
    calls: list[tuple[int, Any, tuple]] = []
    for b, (k0, k1) in enumerate(bands):
        prev = done(work, WL.band_piece(b))
        if prev is not None:
            first[b] = prev
        else:
            calls.append((b, radii_band, (work, b, k0, k1, n_tiles, delta, r_cut)))

    def record(res: dict[str, Any]) -> None:
        first[res["band"]] = mark(work, WL.band_piece(res["band"]), res)

    where = "the radii of positions {} to {}".format
    size = {b: k1 - k0 for b, (k0, k1) in enumerate(bands)}
    collect(submit(ex, calls), lambda b: where(*bands[b]), name, n, progress, "radii", record,
            lambda r: size[r["band"]], sum(size[b] for b in first))
    run_min, run_space = math.inf, math.inf
    second: list[tuple[int, Any, tuple]] = []
    for b, (k0, k1) in enumerate(bands):
        second.append((b, finish_band, (work, b, k0, k1, run_min, run_space)))
        run_min, run_space = min(run_min, first[b]["last_radius"]), min(run_space, first[b]["last_space"])
    fin = {r["band"]: r for r in collect(submit(ex, second), lambda b: where(*bands[b]), name, len(bands), None,
                                         "radii")}
    worst, at = math.inf, -1
    for b in range(len(bands)):  # the first position of the smallest ratio, as one pass finds it
        if fin[b]["worst"] < worst:
            worst, at = fin[b]["worst"], fin[b]["at"]
    files = {k: v for b in range(len(bands)) for r in (fin[b], first[b]) for k, v in r["files"].items()
             if not k.startswith(("radloc.", "space."))}
    doc = {"spacing_over_radius_min": worst, "spacing_over_radius_min_at": at, "bands": bands, "files": files}
    return mark(work, "radii", doc)
