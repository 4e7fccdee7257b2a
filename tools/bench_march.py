"""The march of many fronts at once: CPU per pop, popped one by one and in batches (JSON).

A seeded ordering (a tile's head seeds, timed seeds joining together) marches all its seeds'
fronts in one march, kept apart (``lodbuilder._kernels.march``). Popped one entry at a time, the
fronts take turns all over the band and each pop misses the caches; the kernel pops a march of
``BATCH_SOURCES`` or more fronts in batches (its voxels queued in buckets of width ``BATCH_T``,
each bucket's voxels marched at once, in voxel order). For each input and each number of fronts S (the first S points of the
input's farthest point order, so spread as a head is) this program marches the same fronts both
ways in one process, alternating, ``--repeat`` times each, and reports CPU microseconds per pop
(user + system of the process), their medians and ratio, and how the batched values differ from
the one-by-one march's (ratio of the point values: mean, min, max). Below ``BATCH_SOURCES`` fronts
the kernel pops one by one either way (``"batched": false``): those rows show the runs' spread.

Inputs (``--inputs``): the synthetic sheets and surfaces of tools/bench_inputs.py at ``--n`` points
(``uniform``, ``uneven``, ``noisy``, ``bumpy``, ``stack``), a survey LAZ of the real autzen_trim.laz
tiled 3 x 3 by tools/make_survey.py (``survey``, 990,000 points; made in a temporary folder), and
any real scan of ../shared/data by file name (``igea.ply``, ``autzen_trim.laz``, ...).

    python tools/bench_march.py --inputs uniform survey stack igea.ply --fronts 3,10,30,300,3000 --repeat 3 > run.json
    python tools/benchdoc.py store docs/bench/bench_march.json run run.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT / "tools"))

from benchdoc import publish, stamp  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
SYNTHETIC = ("uniform", "uneven", "noisy", "bumpy", "stack")


def load(name: str, n: int, tmp: Path) -> tuple[np.ndarray, str]:
    """The points of input ``name`` and how to call it in the report."""
    from lodbuilder.io import read_scan

    if name in SYNTHETIC:
        from bench_inputs import synthetic

        return synthetic(name, n), f"{name} {n} (synthetic)"
    if name == "survey":
        from make_survey import make

        out = tmp / "survey_3x3.laz"
        make(out, 3, 3)
        return read_scan(out).points, "survey 3 x 3 (autzen_trim.laz tiled by tools/make_survey.py)"
    return read_scan(DATA / name).points, f"{name} (real)"


def measure(points: np.ndarray, fronts: list[int], repeat: int) -> dict[str, Any]:
    """CPU per pop of the march of S fronts apart, one by one and batched, for each S."""
    from lodbuilder._kernels.march import BATCH_SOURCES, BATCH_T, multi_source_distance
    from lodbuilder.sampling.band import TAIL_SLOPE, plan_and_build_band
    from lodbuilder.sampling.fastfps import fastfps

    head = fastfps(points, size=max(fronts)).order
    band, _, _ = plan_and_build_band(points, None, None)
    inv = np.empty(points.shape[0], np.int32)
    inv[band.perm] = np.arange(points.shape[0], dtype=np.int32)
    pnrm = np.zeros((1, 3), np.float32)

    def march(s: int, batch: float) -> tuple[float, np.ndarray]:
        src = inv[head[:s]].astype(np.int32)
        t = time.process_time()
        dq, _, pops = multi_source_distance(band.u, band.keys, band.nbr, band.cs, band.near, band.vcost,
                                            np.ones(1), False, band.foot, pnrm, TAIL_SLOPE, src, True, batch)
        return (time.process_time() - t) / max(pops, 1) * 1e6, dq

    march(2, 0.0)  # (the kernels loaded before any timing)
    march(2, BATCH_T)
    rows = []
    for s in fronts:
        runs: dict[float, list[float]] = {0.0: [], BATCH_T: []}
        values: dict[float, np.ndarray] = {}
        for k in range(repeat):
            for b in (0.0, BATCH_T) if k % 2 == 0 else (BATCH_T, 0.0):
                us, dq = march(s, b)
                runs[b].append(round(us, 3))
                values[b] = dq
        one, bat = values[0.0], values[BATCH_T]
        m = np.isfinite(one) & (one > 0)
        r = bat[m] / one[m]
        a, b_ = float(np.median(runs[0.0])), float(np.median(runs[BATCH_T]))
        rows.append({"fronts": s, "batched": s >= BATCH_SOURCES, "one_by_one_us_per_pop": runs[0.0], "batched_us_per_pop": runs[BATCH_T],
                     "median_one_by_one": round(a, 3), "median_batched": round(b_, 3), "ratio": round(b_ / a, 3),
                     "value_ratio_mean": round(float(r.mean()), 5), "value_ratio_min": round(float(r.min()), 4),
                     "value_ratio_max": round(float(r.max()), 4)})
        print(json.dumps({"fronts": s, "ratio": rows[-1]["ratio"]}), file=sys.stderr, flush=True)
    return {"n_points": int(points.shape[0]), "voxels": int(band.keys.shape[0]), "batch_t": BATCH_T, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", nargs="+", default=["uniform", "survey", "stack", "igea.ply"])
    ap.add_argument("--n", type=int, default=1_000_000, help="points of each synthetic input")
    ap.add_argument("--fronts", default="3,10,30,300,3000", help="numbers of fronts, comma separated")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each way for each number of fronts")
    args = ap.parse_args(argv)
    fronts = [int(x) for x in args.fronts.split(",")]
    if min(fronts) < 2 or args.repeat < 1:
        ap.error("--fronts needs numbers of at least 2 and --repeat at least 1")
    result = stamp("bench_march", argv, inputs=", ".join(args.inputs),
                   synthetic=any(x in SYNTHETIC or x == "survey" for x in args.inputs))
    result["runs"] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.inputs:
            pts, label = load(name, args.n, Path(tmp))
            print(json.dumps({"input": label}), file=sys.stderr, flush=True)
            result["runs"][label] = measure(pts, fronts, args.repeat)
    publish(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
