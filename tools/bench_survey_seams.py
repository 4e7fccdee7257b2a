"""Seams of tiled archives too large for an in-memory reference (issue 19, item 4): JSON on stdout.

tools/bench_seams.py measures a tiled order against the in-memory order of the same points, which a
survey of 10^7 points and more does not have on this machine. Given archives of one survey built
in different ways (one pass, ``--seam-rounds``), this measures each by itself and against the
first, with the same measures as bench_seams:

* ``cross_spacing_min``: the smallest distance between two points of different tiles in a level
  over the level's stored radius, worst level from the head to 3 % of the points (the head a tile
  of its own); ``cross_spacing_min_head_in_tiles``: each head point in the tile whose box holds it
  (a tile orders with those head points as seeds: no seam). Target >= 0.35 (goal 0.5).
  ``levels_below_0_35`` and ``cross_new_min_above_halo``/``..._below_halo``: bench_seams' seam profile
  (the levels whose newest point is closer than 0.35 x the radius to another tile's, by which tile
  had not seen the other).
* ``covering``: the covering radius of 24 levels from the head to 3 % at ``--sample`` random points
  of the survey (the same points for every archive; lower bounds of the true radii) and
  ``cover_over_first``: each level's over the first archive's at equal size (worst and mean).

    python tools/bench_survey_seams.py one.h5 rounds.h5 --sample 200000 --synthetic
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))


def measure(path: Path, at: np.ndarray | None, levels: list[int] | None, sample: int) -> dict[str, Any]:
    """The measures of one archive (its one scan); ``at``: the sample points (None: drawn here),
    ``levels``: the level sizes (None: from this archive's head to 3 %)."""
    from bench_seams import cross_pairs, cross_spacing, seam_profile, tile_of
    from scipy.spatial import cKDTree

    import lodbuilder

    with lodbuilder.open_archive(path) as arc:
        v = arc.scan()
        p, radius, build = v.points(), v.radius[:], dict(v.build)
    tiled = build.get("tiled") or {}
    n, h = len(p), int(tiled.get("head_points", 1))
    top = max(int(0.03 * n), h + 2)
    if at is None:
        at = p[np.sort(np.random.default_rng(0).choice(n, min(sample, n), replace=False))]
    if levels is None:
        levels = sorted({int(k) for k in np.geomspace(h, top, 24)})
    sub = p[: top + 1]  # (every point of the levels measured: the pairs lie among them)
    boxes = tiled.get("tile_boxes", [])
    in_box = tile_of(sub, boxes)
    group = in_box.copy()
    group[:h] = -1
    lv = np.arange(max(h, 1), top + 1)
    out: dict[str, Any] = {"archive": str(path), "n": n, "tiles": tiled.get("tiles"), "head_points": h,
                           "rounds": {k: tiled["rounds"][k] for k in ("rounds", "q")} if tiled.get("rounds") else None,
                           "seam_alpha": tiled.get("seam_alpha")}
    for key, g in (("cross_spacing_min", group), ("cross_spacing_min_head_in_tiles", in_box)):
        e, partner = cross_pairs(sub, g, radius, top + 1)
        cs = cross_spacing(e, radius, top + 1)
        out[key] = round(float(cs[lv - 1].min()), 4)
        out[key + "_at"] = int(lv[np.argmin(cs[lv - 1])])
        if g is group:
            out |= seam_profile(e, partner, group, tiled.get("tile_colours", []), radius,
                                float(tiled.get("halo", 0.0)), lv)
    out["covering"] = [[k, float(cKDTree(p[:k]).query(at, workers=-1)[0].max())] for k in levels]
    return out | {"_at": at, "_levels": levels}


def main(argv: list[str] | None = None) -> int:
    from benchdoc import finish, stamp

    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("archives", nargs="+", type=Path, help="archives of one survey (the first: the reference)")
    ap.add_argument("--sample", type=int, default=200_000, help="points the covering is measured at")
    ap.add_argument("--synthetic", action="store_true", help="the survey is synthetic (e.g. tools/make_survey.py's)")
    args = ap.parse_args(argv)
    doc = stamp("bench_survey_seams", argv, inputs=", ".join(map(str, args.archives)), synthetic=args.synthetic)
    doc["archives"] = []
    at = levels = first = None
    for a in args.archives:
        m = measure(a, at, levels, args.sample)
        at, levels = m.pop("_at"), m.pop("_levels")
        if first is None:
            first = m
        r = [c[1] / f[1] for c, f in zip(m["covering"], first["covering"], strict=True)]
        m["cover_over_first_worst"], m["cover_over_first_mean"] = round(max(r), 4), round(float(np.mean(r)), 4)
        m["cover_over_first_worst_at"] = m["covering"][int(np.argmax(r))][0]
        doc["archives"].append(m)
        print(json.dumps({k: v for k, v in m.items() if k != "covering"}), file=sys.stderr)
    print(json.dumps(finish(doc), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
