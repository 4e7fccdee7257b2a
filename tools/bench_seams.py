"""Benchmark the seams of the tiled build (issue 19, item 4): JSON on stdout.

For each input and tile count, the tiled build (``_tile_points`` forces the tile count, one worker)
against the in-memory build of the same points (``lodbuilder.fastfps``):

* ``cover_ratio_worst``: the largest ratio of the tiled order's true covering radius to the
  in-memory order's, at equal sizes, over the levels from the head's size to 3 % of the points among
  24 from half the head's size (brute force: a k-d tree over each prefix, every point queried; the
  levels below the head, the coarse level's order: ``cover_ratio_below_head``). Target <= 1.05.
* ``cross_spacing_min``: the smallest distance between two points of different tiles (the coarse
  head counts as one more tile) in a level, over the level's stored radius, the worst level from
  the head to 3 % (``..._all``: over every level). Target >= 0.35 (goal 0.5). The in-memory order
  measured with the same tiles: ``cross_spacing_in_memory``. ``cross_spacing_min_head_in_tiles``:
  the same as ``cross_spacing_min`` with each head point counted in the tile whose box holds it (a
  tile orders with the head points in its box and halo as seeds, so a pair of a head point and a
  point of its tile is no seam: on autzen such pairs are points of the band far apart along it and
  close in space, which the in-memory order has too).
* ``cross_new_min_above_halo`` / ``..._below_halo``: the smallest spacing of the pair each level's
  newest point makes with an earlier point of another tile, over the levels whose radius is above
  the halo width (``halo``; a tile sees its neighbours' points only within it) and over the others;
  ``levels_below_0_35``: the levels where that pair is closer than 0.35 x the radius, by which tile
  had not seen the other (``newest_of_lower_colour``: the newest point's tile ordered first).
* ``reference_spread`` (``--reference-spread K``): K in-memory orders of each input from random
  start points against the default in-memory order, at the same levels (head to 3 %): how much
  two valid farthest point orders differ at one size, the scale ``cover_ratio_worst`` is read on.
* ``decimation``: points per point of the decimated copy (the coarse level's input; the library asks
  for n / 8 at these sizes, its cell grid gives 1 in 4-6), or with ``--decimation D`` about n / D as
  a survey's (21.56M -> 400,000: 54; the cell grid gives 1 in 25-40 at 200,000 points).
* ``merge_seconds``: the merge's tasks' durations summed (the seam repair and the bands) from the
  build record (``task_seconds``), per million points.
* ``order_cpu_seconds``: the CPU seconds of the order phase's tasks (every ``order_tile``, or the one
  ``order_rounds``), from the same table.
* With ``--rounds R --q Q``: the tiles ordered in R radius rounds of ratio Q
  (:mod:`lodbuilder.build.tiled.rounds`; ``--rounds auto``: the build option ``seam_rounds`` as
  it is, its own R and q), and ``round_costs``: one tile (the first box and
  its halo) ordered alone by :mod:`lodbuilder.sampling.resumable` in those rounds without sources:
  the largest bytes of its state in the grid phase and in the tail, and the CPU seconds (least of
  3) of one ordering (``cpu_one``), of the rounds with the state kept (``cpu_rounds_kept``) and of
  the rounds by restarts (``cpu_restarts``: one ordering down to each round's radius, then one to
  the end).

Inputs (``--inputs``): ``autzen`` (the real autzen_trim.laz tiled 2 x 2 by tools/make_survey.py,
every ``--thin``-th point), ``uniform`` and ``uneven`` (synthetic wavy sheets of tools/bench_inputs.py),
``fragmented`` (the synthetic scene of tools/make_fragmented.py).

    python tools/bench_seams.py --n 200000 --tiles 4 16 --seam-spacing 0 0.25 0.5 --decimation 0 54
    python tools/bench_seams.py --n 200000 --tiles 16 --inputs uniform --seam-spacing 0 --rounds 21 --q 1.1
    python tools/bench_seams.py --n 1000000 --tiles 16 --inputs uniform --seam-spacing 0 --rounds 42 --q 1.05 \
        --workers 2 --one-pass-too --sample 200000 --no-round-costs

With ``--workers W`` (> 1) the build runs on W worker processes and the rounds on W owners
(:mod:`lodbuilder.build.tiled.affinity`): ``order_wall_seconds`` (the order phase's wall time from
the build record), ``owner_state_bytes`` (each owner's largest sum of its tiles' state bytes),
``owner_bytes_estimate`` against ``worker_budget`` (the rule that refuses rounds whose states do not fit;
``rounds_used``: whether the build ordered in rounds) and the CPU seconds of every step (``round_steps``: one task per owner and colour in each round; ``round_finish``).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

INPUTS = ("autzen", "uniform", "uneven", "fragmented")
#: the order phase's tasks (one pass; the one-task rounds; the parallel rounds' steps and writes)
ORDER_TASKS = ("order_tile", "order_rounds", "round_steps", "round_finish")


def make_input(name: str, n: int, d: Path, thin: int, survey: tuple[int, int] = (2, 2)) -> Path:
    """The input file of ``name`` (about ``n`` points; autzen: ``survey`` = NX x NY copies of every
    ``thin``-th point)."""
    from lodbuilder.io import write_points

    if name == "autzen":
        from make_survey import make

        out = d / f"autzen_{survey[0]}x{survey[1]}.laz"
        make(out, survey[0], survey[1], thin=thin)
        return out
    if name == "fragmented":
        from make_fragmented import fragmented_scene

        pts = fragmented_scene(seed=0, pieces=max(20, n // 2000), points=n)
    else:
        from bench_inputs import range_scan_sheet, uneven_sheet

        pts = range_scan_sheet(n) if name == "uniform" else uneven_sheet(n)
    return write_points(d / f"{name}.npy", pts)


def tile_of(p: np.ndarray, boxes: list) -> np.ndarray:
    """The first tile box holding each point (-1: none)."""
    out = np.full(len(p), -1)
    for t, b in enumerate(np.asarray(boxes)):
        inside = np.all((p >= b[:3]) & (p <= b[3:]), axis=1) & (out < 0)
        out[inside] = t
    return out


def cross_pairs(p: np.ndarray, group: np.ndarray, radius: np.ndarray, upto: int) -> tuple[np.ndarray, np.ndarray]:
    """For each point k (1 .. upto - 1): the distance to its nearest earlier point of another group
    within the radius of the level it completes (``radius[k + 1]``; inf: none) and that point (-1)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(p)
    j = np.arange(1, upto)
    near = tree.query_ball_point(p[j], radius[j + 1], workers=-1)
    e = np.full(upto, np.inf)
    partner = np.full(upto, -1)
    for k, idx in zip(j, near, strict=True):
        idx = np.asarray(idx, dtype=np.int64)
        idx = idx[(idx < k) & (group[idx] != group[k])]
        if idx.size:
            d = np.linalg.norm(p[idx] - p[k], axis=1)
            e[k], partner[k] = float(d.min()), int(idx[np.argmin(d)])
    return e, partner


def cross_spacing(e: np.ndarray, radius: np.ndarray, upto: int) -> np.ndarray:
    """For each level size k (1 .. upto): the smallest distance between two of its first k points
    of different groups (``e`` of :func:`cross_pairs`) over the level's radius ``radius[k]``
    (values above 1 are capped at 1)."""
    run = np.minimum.accumulate(e[:upto])  # run[k - 1]: smallest distance among the first k points
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.minimum(run / radius[1: upto + 1], 1.0)


def seam_profile(e: np.ndarray, partner: np.ndarray, group: np.ndarray, colour: list, radius: np.ndarray,
                 halo: float, lv: np.ndarray) -> dict[str, Any]:
    """Where the levels ``lv`` (sizes) lose their cross-tile spacing: the smallest spacing of the pair
    each level's newest point makes (its distance to the nearest earlier point of another tile over
    the level's radius), over the levels whose radius is above the halo width (the tiles see each
    other's points only within the halo) and over those at or below it; and for the levels where it is
    below 0.35, which of the two tiles had not seen the other: the newest point's tile of the lower
    colour (ordered before the other, blind to it), of the higher colour (it had the other's
    points as timed seeds), or the partner a head point."""
    new = np.minimum(e[lv - 1] / radius[lv], 1.0)
    above = radius[lv] > halo
    blame = {"newest_of_lower_colour": 0, "newest_of_higher_colour": 0, "with_head": 0}
    for k in lv[new < 0.35]:
        a, b = group[k - 1], group[partner[k - 1]]
        if a < 0 or b < 0:
            blame["with_head"] += 1
        else:
            blame["newest_of_lower_colour" if colour[a] < colour[b] else "newest_of_higher_colour"] += 1
    return {"cross_new_min_above_halo": round(float(new[above].min()), 4) if above.any() else None,
            "cross_new_min_below_halo": round(float(new[~above].min()), 4) if (~above).any() else None,
            "levels_above_halo": int(above.sum()), "levels_below_0_35": blame}


#: None, or the rows of the points the covering is measured at (``--sample``: a random subset, so
#: the covering radii are lower bounds, the same subset for the tiled and the in-memory order)
COVER_AT: np.ndarray | None = None


def covering(pts: np.ndarray, order: np.ndarray, k: int) -> float:
    from scipy.spatial import cKDTree

    at = pts if COVER_AT is None else pts[COVER_AT]
    return float(cKDTree(pts[order[:k]]).query(at, workers=-1)[0].max())


def one_case(f: Path, d: Path, tile_points: int, seam: float | None, ref_cache: dict,
             rounds: tuple[int, float] | str | None = None, workers: int = 1) -> dict[str, Any]:
    import lodbuilder

    kw: dict[str, Any] = {"_tile_points": tile_points, "workers": workers, "seam_rounds": rounds is not None}
    if seam is not None:
        kw["seam_spacing"] = seam
    out = d / f"t{tile_points}.h5"
    t0 = time.perf_counter()
    sizes: dict[str, Any] = {}
    with tile_rounds(None if rounds == "auto" else rounds), (state_sizes() if workers == 1 else contextlib.nullcontext(sizes)) as sizes:
        lodbuilder.build_archive(f, out, **kw)
    seconds = time.perf_counter() - t0
    with lodbuilder.open_archive(out) as arc:
        v = arc.scan()
        src, radius, p_stored = v.source_index[:], v.radius[:], v.points()
        build = dict(v.build)
    out.unlink()
    n = len(src)
    pts = np.empty_like(p_stored)
    pts[src] = p_stored
    if "order" not in ref_cache:
        t1 = time.perf_counter()
        ref_cache["order"] = lodbuilder.fastfps(pts).order
        ref_cache["seconds"] = time.perf_counter() - t1
    tiled = build.get("tiled", {})
    h = int(tiled.get("head_points", 1))
    top = max(int(0.03 * n), h + 2)
    boxes = tiled.get("tile_boxes", [])
    group = tile_of(p_stored, boxes)
    group[:h] = -1  # the coarse head: a tile of its own
    ref_p = pts[ref_cache["order"]]
    ref_group = tile_of(ref_p, boxes)
    sweep = []
    for k in sorted({int(k) for k in np.geomspace(max(h // 2, 2), top, 24)}):
        ct, cm = covering(pts, src, k), covering(pts, ref_cache["order"], k)
        sweep.append([k, round(ct / cm, 4), round(cross_min(ref_p[:k], ref_group[:k]) / cm, 4)])
    worst = max((r for r in sweep if r[0] >= h), key=lambda r: r[1])
    upto = n - 1 if COVER_AT is None else top + 1  # (--sample: the levels up to 3 % only)
    e, partner = cross_pairs(p_stored, group, radius, upto)
    cs = cross_spacing(e, radius, upto)  # cs[k - 1]: level of size k
    lv = np.arange(max(h, 1), top + 1)
    at = int(lv[np.argmin(cs[lv - 1])])
    # the same with each head point in the tile whose box holds it (a tile orders with every head
    # point in its box and halo as a seed: such a pair is no seam)
    cs_box = cross_spacing(cross_pairs(p_stored, tile_of(p_stored, boxes), radius, upto)[0], radius, upto)
    at_box = int(lv[np.argmin(cs_box[lv - 1])])
    halo = float(tiled.get("halo", 0.0))
    merge = [r for r in (build.get("tasks") or {}).get("rows", []) if r[0] in ("seam_repair", "merge_band")]
    order = [r for r in (build.get("tasks") or {}).get("rows", []) if r[0] in ORDER_TASKS]
    rinfo = tiled.get("rounds") or {}
    return {"n": n, "tile_points": tile_points, "tiles": tiled.get("tiles"), "head_points": h,
            "coarse_points": tiled.get("coarse_points"), "decimation": round(n / max(int(tiled.get("coarse_points", 1)), 1), 1),
            "halo": round(halo, 6), "tile_boxes": boxes, "head_radius": round(float(tiled.get("head_radius", 0.0)), 6),
            "seam_alpha": tiled.get("seam_alpha"), "seam_points": tiled.get("seam_points"),
            "seam_deferrals": tiled.get("seam_deferrals"), "seconds_tiled": round(seconds, 2),
            "cover_ratio_worst": worst[1], "cover_ratio_worst_at": worst[0],
            "cover_ratio_below_head": max([r[1] for r in sweep if r[0] < h], default=None),
            "cross_spacing_min": round(float(cs[lv - 1].min()), 4), "cross_spacing_min_at": at,
            "cross_spacing_min_all": round(float(np.nanmin(cs[h:])), 4) if COVER_AT is None else None,
            "cross_spacing_min_head_in_tiles": round(float(cs_box[lv - 1].min()), 4),
            "cross_spacing_min_head_in_tiles_at": at_box,
            "cross_spacing_in_memory": min(r[2] for r in sweep),
            **seam_profile(e, partner, group, tiled.get("tile_colours", []), radius, halo, lv),
            "spacing_over_radius_min": tiled.get("spacing_over_radius_min"),
            "merge_seconds": round(sum(r[5] for r in merge), 3) if merge else None,
            "merge_cpu_seconds": round(sum(r[6] for r in merge), 3) if merge else None,
            "order_cpu_seconds": round(sum(r[6] for r in order), 3),
            "rounds": [rinfo["rounds"], rinfo["q"]] if rinfo else None, **sizes,
            "workers": workers, "order_wall_seconds": (build.get("phase_seconds") or {}).get("order"),
            "rounds_used": bool(rinfo),
            "owner_state_bytes": rinfo.get("owner_state_bytes"),
            "owner_bytes_estimate": rinfo.get("owner_bytes_estimate"), "worker_budget": rinfo.get("worker_budget"),
            "sweep": sweep}


def reference_spread(f: Path, ref_cache: dict, case: dict[str, Any], k: int) -> dict[str, Any]:
    """How far in-memory farthest point orders of the same points differ among themselves: ``k``
    orders from random start points (``lodbuilder.fastfps(seeds=[s])``), each one's covering over
    the default in-memory order's at the levels of ``case``'s sweep from its head to 3 %: the worst
    and best ratio of each (the scale against which a tiled order's ``cover_ratio_worst`` reads)."""
    import lodbuilder
    from lodbuilder.io.api import read_scan

    pts = read_scan(f).points
    levels = [r[0] for r in case["sweep"] if r[0] >= case["head_points"]]
    ref = {lv: covering(pts, ref_cache["order"], lv) for lv in levels}
    out = []
    for s in np.random.default_rng(1).choice(len(pts), k, replace=False):
        order = lodbuilder.fastfps(pts, seeds=[int(s)]).order
        r = [covering(pts, order, lv) / ref[lv] for lv in levels]
        out.append({"start": int(s), "worst": round(max(r), 4), "worst_at": levels[int(np.argmax(r))],
                    "best": round(min(r), 4), "mean": round(float(np.mean(r)), 4)})
    return {"levels": len(levels), "orders": out, "worst": max(o["worst"] for o in out)}


def cross_min(p: np.ndarray, group: np.ndarray) -> float:
    """The smallest distance between two points of different groups."""
    from scipy.spatial import cKDTree

    best = np.inf
    for g in np.unique(group):
        a, b = p[group == g], p[group != g]
        if len(a) and len(b):
            best = min(best, float(cKDTree(b).query(a)[0].min()))
    return best


@contextlib.contextmanager
def coarse_points(m: int | None) -> Iterator[None]:
    """Builds in this block take a decimated copy of at most ``m`` points (None: the library's)."""
    from lodbuilder.build.tiled import driver

    old = driver.COARSE_POINTS
    if m is not None:
        driver.COARSE_POINTS = max(m, driver.COARSE_MIN)
    try:
        yield
    finally:
        driver.COARSE_POINTS = old


@contextlib.contextmanager
def tile_rounds(rounds: tuple[int, float] | None) -> Iterator[None]:
    """Builds in this block order their tiles in radius rounds (R, q) (None: in one pass)."""
    from lodbuilder.build.tiled import rounds as R

    old = R.TILE_ROUNDS
    R.TILE_ROUNDS = rounds
    try:
        yield
    finally:
        R.TILE_ROUNDS = old


@contextlib.contextmanager
def state_sizes() -> Iterator[dict[str, Any]]:
    """The bytes of every tile's resumable state together (``FastFPSState.nbytes`` summed over the
    states alive, after each start and each round of a tile): the largest sum, the points of those
    states (halos included), and the sum once every tile is in the Euclidean tail. The build's
    tasks run in this process (the executor made inline) so that the states can be seen."""
    from lodbuilder.build import runner
    from lodbuilder.sampling import resumable

    out: dict[str, Any] = {}
    live: dict[int, tuple[int, int, str]] = {}
    old_start, old_resume, old_ex = resumable.start_fastfps, resumable.resume_fastfps, runner.make_executor

    def note(state: Any) -> None:
        live[id(state)] = (state.nbytes, state.pts.shape[0], state.phase)
        total = sum(v[0] for v in live.values())
        if total > out.get("states_bytes_peak", -1):
            out["states_bytes_peak"], out["states_points"] = total, sum(v[1] for v in live.values())
        if all(v[2] == "tail" for v in live.values()):
            out["states_bytes_tail_peak"] = max(out.get("states_bytes_tail_peak", 0), total)

    def start(*a: Any, **k: Any) -> Any:
        state = old_start(*a, **k)
        note(state)
        return state

    def resume(state: Any, *a: Any, **k: Any) -> Any:
        o = old_resume(state, *a, **k)
        note(state)
        return o

    old_news = resumable.resume_news

    def news(state: Any, *a: Any, **k: Any) -> Any:
        out = old_news(state, *a, **k)
        note(state)
        return out

    def inline(*a: Any, **k: Any) -> Any:
        return old_ex(*a, **{**k, "inline": True})

    resumable.start_fastfps, resumable.resume_fastfps, runner.make_executor = start, resume, inline
    resumable.resume_news = news
    try:
        yield out
    finally:
        resumable.start_fastfps, resumable.resume_fastfps, runner.make_executor = old_start, old_resume, old_ex
        resumable.resume_news = old_news
        if out.get("states_points"):
            out["states_bytes_per_point"] = round(out["states_bytes_peak"] / out["states_points"], 1)
            if "states_bytes_tail_peak" in out:
                out["states_bytes_tail_per_point"] = round(out["states_bytes_tail_peak"] / out["states_points"], 1)


def round_costs(f: Path, case: dict[str, Any], rounds: tuple[int, float]) -> dict[str, Any]:
    """One tile of ``case`` (its first box and the halo around it) ordered alone, in rounds: the
    bytes of its state (largest over the rounds; in the grid phase and in the tail) and the CPU
    seconds of its rounds against one ordering of it (no sources: the engine's cost of stopping
    and going on) and against restarting the ordering at every round (what the rounds cost
    without a kept state: an ordering down to each round's radius)."""
    from lodbuilder.io.api import read_scan
    from lodbuilder.sampling.fastfps import fastfps
    from lodbuilder.sampling.resumable import resume_fastfps, start_fastfps

    pts = np.asarray(read_scan(f).points, dtype=np.float64)
    box = np.asarray(case["tile_boxes"][0])
    halo = case["halo"]
    pts = pts[np.all((pts >= box[:3] - halo) & (pts <= box[3:] + halo), axis=1)]
    radii = [case["head_radius"] / rounds[1] ** p for p in range(1, rounds[0] + 1)] + [None]
    size = {"grid": 0, "tail": 0}

    def kept() -> None:
        state = start_fastfps(pts)
        for rho in radii:
            resume_fastfps(state, rho=rho)
            size[state.phase] = max(size[state.phase], state.nbytes)

    kept()  # (warm: the resumable kernels loaded from numba's cache in this process)
    cpu = {"one": np.inf, "kept": np.inf, "restarts": np.inf}
    for _ in range(3):  # (the least of 3, alternated)
        c0 = time.process_time()
        one = fastfps(pts)
        c1 = time.process_time()
        kept()
        c2 = time.process_time()
        for rho in radii[:-1]:
            fastfps(pts, rho=rho)
        c3 = time.process_time()
        for k, v in (("one", c1 - c0), ("kept", c2 - c1), ("restarts", c3 - c2 + c1 - c0)):
            cpu[k] = min(cpu[k], v)
    return {"points": int(len(pts)), "state_bytes_grid": size["grid"], "state_bytes_tail": size["tail"],
            "bytes_per_point": round(max(size.values()) / len(pts), 1), "cpu_one": round(cpu["one"], 3),
            "cpu_rounds_kept": round(cpu["kept"], 3), "cpu_restarts": round(cpu["restarts"], 3),
            "grid_points_of_one": one.stats["grid_points"]}


def main(argv: list[str] | None = None) -> int:
    from benchdoc import finish, stamp

    from lodbuilder.io.api import read_scan

    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--n", type=int, default=200_000, help="points of each synthetic input")
    p.add_argument("--thin", type=int, default=2, help="autzen: keep every THIN-th point (2: 220,000 points)")
    p.add_argument("--tiles", type=int, nargs="+", default=[4, 16], help="about this many tiles (sets _tile_points)")
    p.add_argument("--inputs", nargs="+", default=list(INPUTS), choices=INPUTS)
    p.add_argument("--seam-spacing", type=float, nargs="+", default=[None],
                   help="seam spacings to build with (default: the library's)")
    p.add_argument("--decimation", type=int, nargs="+", default=[0],
                   help="build with a decimated copy (the coarse level's input) of about n / D points, as a "
                        "survey's (21.56M points -> 400,000: 54); 0: the library's choice (it asks for n / 8 at "
                        "these sizes and its cell grid gives 1 point in 4-6)")
    p.add_argument("--rounds", default="0",
                   help="order the tiles in this many radius rounds (lodbuilder.build.tiled.rounds; 0: one pass; "
                        "auto: the build option seam_rounds, its rounds and ratio)")
    p.add_argument("--q", type=float, default=1.1, help="the rounds' radius ratio")
    p.add_argument("--survey", type=int, nargs=2, default=[2, 2], metavar=("NX", "NY"),
                   help="autzen: NX x NY copies (3 3 with --thin 1: about 1M points)")
    p.add_argument("--sample", type=int, default=0,
                   help="measure the covering at this many random points (a lower bound; 0: every point) "
                        "and the cross-tile spacing up to the 3 %% level only (for 1M points and more)")
    p.add_argument("--no-round-costs", action="store_true", help="skip round_costs (the one tile alone)")
    p.add_argument("--workers", type=int, default=1,
                   help="build on this many workers (the rounds on as many owners, lodbuilder.build.tiled.affinity; "
                        "1: every task in this process, with every tile state's bytes summed)")
    p.add_argument("--reference-spread", type=int, default=0, metavar="K",
                   help="also order each input in memory from K other random start points and measure their "
                        "covering against the default in-memory order at the same levels (reference_spread)")
    p.add_argument("--one-pass-too", action="store_true",
                   help="with --rounds: also build each case in one pass, alternating (order CPU and wall against it)")
    args = p.parse_args(argv)
    rounds = "auto" if args.rounds == "auto" else (int(args.rounds), args.q) if int(args.rounds) else None
    doc = stamp("bench_seams", argv, inputs=", ".join(args.inputs), synthetic=args.inputs != ["autzen"])
    doc["cases"] = []
    with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR")) as tmp:
        d = Path(tmp)
        for name in args.inputs:
            f = make_input(name, args.n, d, args.thin, tuple(args.survey))
            ref: dict = {}
            n_all = len(read_scan(f).points)
            global COVER_AT
            COVER_AT = np.sort(np.random.default_rng(0).choice(n_all, args.sample, replace=False)) if args.sample else None
            for tiles in args.tiles:
                n_est = n_all
                for seam, dec, rr in itertools.product(args.seam_spacing, args.decimation,
                                                       [None, rounds] if rounds and args.one_pass_too else [rounds]):
                    with coarse_points(n_est // dec if dec else None):
                        case = one_case(f, d, max(1000, int(1.05 * n_est / tiles)), seam, ref, rr, args.workers)
                    if rr and not args.no_round_costs:
                        case["round_costs"] = round_costs(f, case, tuple(case["rounds"]))
                    case = {"input": name, "synthetic": name != "autzen", "decimation_asked": dec, **case,
                            "seconds_in_memory": round(ref["seconds"], 2)}
                    doc["cases"].append(case)
                    print(json.dumps({k: v for k, v in case.items() if k not in ("sweep", "tile_boxes")}), file=sys.stderr)
            if args.reference_spread:
                doc.setdefault("reference_spread", []).append(
                    {"input": name, **reference_spread(f, ref, case, args.reference_spread)})
                print(json.dumps(doc["reference_spread"][-1]), file=sys.stderr)
    print(json.dumps(finish(doc), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
