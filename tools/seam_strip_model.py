"""A model of the tiled build's seams, to choose the next seam design (issue 19, item 4): not the
product's code, and not a benchmark of it.

Everything here is exact Euclidean farthest point sampling (no band, no grid) on a synthetic
wavy sheet in the unit square, so that only the seam handling differs between the variants:

* the reference: one farthest point ordering of every point (its first ``--levels-to`` share);
* the tiled orderings as the build makes them: a head (the reference's first ``--head`` points),
  then every tile of an n x n grid ordered alone, seeded with the head, in four colour classes
  (a tile sees the orderings of its neighbours of a lower colour as timed seeds: each joins when
  the tile's largest distance falls to its key; ``--blind``: no tile sees another);
* three merges of those tile orders after the head:
  ``none``: by descending key alone;
  ``defer``: the build's seam repair (``lodbuilder.build.tiled.merge``): a point nearer a shared
  face than its key, within ``alpha`` x its key of an accepted point of another tile (or of the
  head), waits until its key falls to (that distance / alpha);
  ``strip W``: every point within W x r_head of a shared face (r_head: the head's last key) is
  ordered again by an exact lazy farthest point sampling over the strip (its key: its distance to
  every point accepted so far; the head and the other points accepted at their tile keys), the
  other points keep their tile keys.

For every variant: the covering radius of each prefix (sizes from 2 x the head to ``--levels-to``
of the points, geometric) over the reference's at the same size, and the smallest distance
between points of different tiles in the prefix over that covering radius.

    python tools/seam_strip_model.py [--points 200000] [--tiles 2] [--head 330] [--widths 0.5,1,2]
        [--alpha 0.25] [--shape uniform|uneven|holes] [--out FILE]

The tile orders stop at ``--stop`` x the last level's key; the strip's points that a tile left
unordered join the strip's ordering (the strip orders every point in it). Prints one JSON
document. Takes minutes: the merges are Python loops over the tiles' ordered points.
"""

from __future__ import annotations

import argparse
import heapq
import json
import sys
from pathlib import Path
from typing import Any

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))


@nb.njit(cache=True)
def _lower(p, d, q):  # pragma: no cover - compiled
    for i in range(p.shape[0]):
        dd = np.sqrt((p[i, 0] - q[0]) ** 2 + (p[i, 1] - q[1]) ** 2 + (p[i, 2] - q[2]) ** 2)
        if dd < d[i]:
            d[i] = dd


@nb.njit(cache=True)
def fps(p, d0, seeds, seed_key, stop, most):  # pragma: no cover - compiled
    """Farthest point ordering of ``p`` (exact, O(n) a point) from the distances ``d0``, with timed
    seeds (``seeds`` by descending ``seed_key``: each joins when the largest distance falls to its
    key); stops below ``stop`` or after ``most`` points. Returns local indices and keys."""
    d = d0.copy()
    out, key = np.empty(p.shape[0], np.int64), np.empty(p.shape[0])
    m = s = 0
    while m < most:
        j = np.argmax(d)
        while s < seeds.shape[0] and seed_key[s] >= d[j]:
            _lower(p, d, seeds[s])
            s += 1
            j = np.argmax(d)
        if d[j] < stop or d[j] < 0:
            break
        out[m], key[m] = j, d[j]
        m += 1
        _lower(p, d, p[j])
        d[j] = -1.0  # (ordered)
    return out[:m], key[:m]


def sheet(n: int, shape: str, seed: int = 1) -> np.ndarray:
    """``n`` random points of a wavy sheet over the unit square (``uneven``: density falling
    along x; ``holes``: a lattice of rectangular holes cut out, fewer points)."""
    rng = np.random.default_rng(seed)
    xy = rng.random((n, 2))
    if shape == "uneven":
        xy[:, 0] = xy[:, 0] ** 2
    elif shape == "holes":
        xy = xy[((xy[:, 0] * 7) % 1 > 0.25) | ((xy[:, 1] * 5) % 1 > 0.4)]
    z = 0.02 * np.sin(6 * xy[:, 0]) * np.cos(5 * xy[:, 1])
    return np.column_stack([xy, z])


def grid_tiles(p: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's tile (n x n grid), its distance to the nearest face shared with another tile
    (inf if none) and each tile's colour (four classes: no two neighbours share one)."""
    i = np.minimum((p[:, :2] * n).astype(int), n - 1)
    tile = i[:, 0] * n + i[:, 1]
    f = p[:, :2] * n - i
    lo = np.where(i > 0, f, np.inf)
    hi = np.where(i < n - 1, 1 - f, np.inf)
    face = np.minimum(lo, hi).min(axis=1) / n
    t = np.arange(n * n)
    return tile, face, (t // n % 2) * 2 + t % n % 2


def tile_orders(p: np.ndarray, n: int, head: np.ndarray, stop: float, blind: bool = False
                ) -> tuple[dict[int, tuple], np.ndarray, np.ndarray]:
    """Each tile ordered alone after the head, colour by colour, with its lower-colour neighbours'
    orders as timed seeds (``blind``: without them, every tile alone): {tile: (input indices,
    keys)}, the points' tiles and face distances."""
    tile, face, colour = grid_tiles(p, n)
    near = cKDTree(p[head])
    res: dict[int, tuple] = {}
    for c in range(4):
        for t in np.flatnonzero(colour == c):
            idx = np.setdiff1d(np.flatnonzero(tile == t), head)
            nbrs = [u for u in res if abs(u // n - t // n) <= 1 and abs(u % n - t % n) <= 1 and not blind]
            g = np.concatenate([res[u][0] for u in nbrs] or [np.zeros(0, np.int64)])
            k = np.concatenate([res[u][1] for u in nbrs] or [np.zeros(0)])
            o = np.argsort(-k, kind="stable")
            loc, key = fps(p[idx], near.query(p[idx])[0], p[g[o]], k[o], stop, idx.shape[0])
            res[int(t)] = (idx[loc], key)
    return res, tile, face


class _Cells:
    """The accepted points in a hash of square cells (x, y), for nearest-point queries."""

    def __init__(self, p: np.ndarray, cell: float) -> None:
        self.p, self.cell, self.cells = p, cell, {}

    def add(self, i: int) -> None:
        self.cells.setdefault((int(self.p[i, 0] // self.cell), int(self.p[i, 1] // self.cell)), []).append(i)

    def nearest(self, q: np.ndarray, reach: float, skip: np.ndarray | None = None, group: int = 0) -> float:
        """Distance from ``q`` to the nearest stored point within ``reach`` (inf if none), leaving
        out those with ``skip[i] == group``."""
        c, k = self.cell, int(np.ceil(reach / self.cell))
        cx, cy = int(q[0] // c), int(q[1] // c)
        ids = [i for a in range(cx - k, cx + k + 1) for b in range(cy - k, cy + k + 1) for i in self.cells.get((a, b), ())]
        if skip is not None:
            ids = [i for i in ids if skip[i] != group]
        return float(np.sqrt(((self.p[ids] - q) ** 2).sum(axis=1)).min()) if ids else np.inf


def merge_none(res: dict[int, tuple]) -> np.ndarray:
    g = np.concatenate([v[0] for v in res.values()])
    k = np.concatenate([v[1] for v in res.values()])
    return g[np.argsort(-k, kind="stable")]


def merge_defer(p: np.ndarray, res: dict[int, tuple], tile: np.ndarray, face: np.ndarray, head: np.ndarray,
                alpha: float, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The build's seam repair (a lazy greedy over the seam points): the order and the keys the
    points were accepted at."""
    cells, group = _Cells(p, cell), tile.copy()
    group[head] = -1
    for h in head:
        cells.add(int(h))
    heap = [(-k, 0, int(i)) for g, key in res.values() for i, k in zip(g, key, strict=True)]
    heapq.heapify(heap)
    out = []
    while heap:
        nk, _, i = heapq.heappop(heap)
        k = -nk
        if face[i] < k:
            d = cells.nearest(p[i], alpha * k, group, tile[i])
            if d < alpha * k:
                heapq.heappush(heap, (-d / alpha, 1, i))
                continue
            cells.add(i)
        out.append((i, k))
    return np.array([i for i, _ in out], np.int64), np.array([k for _, k in out])


def merge_strip(p: np.ndarray, res: dict[int, tuple], face: np.ndarray, head: np.ndarray, width: float,
                cell: float) -> np.ndarray:
    """The strip within ``width`` of a shared face ordered again (:func:`reorder`; every point of the
    strip, those its tile left unordered too), the other points at their tile keys."""
    keys = {int(i): float(k) for g, key in res.values() for i, k in zip(g, key, strict=True)}
    return np.fromiter(reorder(p, keys, np.setdiff1d(np.flatnonzero(face < width), head), head, cell), np.int64)


def reorder(p: np.ndarray, keys: dict[int, float], again: np.ndarray, head: np.ndarray, cell: float
            ) -> dict[int, float]:
    """Points ``again`` (input indices) ordered again by an exact lazy farthest point sampling among
    the others (``keys``: input index -> key, accepted at their keys; the head first): the keys of
    every point after it, {input index: key}."""
    cells = _Cells(p, cell)
    for h in head:
        cells.add(int(h))
    hd = dict(zip(again.tolist(), cKDTree(p[head]).query(p[again])[0].tolist(), strict=True))
    heap = [(-k, 0, i) for i, k in keys.items() if i not in hd] + [(-d, 0, i) for i, d in hd.items()]
    heapq.heapify(heap)
    out: dict[int, float] = {}
    while heap:
        nk, _, i = heapq.heappop(heap)
        k = -nk
        if i in hd:
            k = min(cells.nearest(p[i], k), k)
            if heap and k < -heap[0][0]:
                heapq.heappush(heap, (-k, 1, i))
                continue
        out[i] = k
        cells.add(i)
    return out


def merge_staged(p: np.ndarray, res: dict[int, tuple], face: np.ndarray, corner: np.ndarray, head: np.ndarray,
                 width: float, blob: float, cell: float) -> np.ndarray:
    """The strip ordered again in two stages that a build could run as independent tasks: first
    the strip without the corners (points within ``blob`` of a corner where faces meet; each
    face's part of the strip is then apart from the others), the corners at their tile keys; then
    the corners grown by ``width`` (the first stage's points there were ordered beside the corners'
    tile keys), every other point at its key of the first stage."""
    keys = {int(i): float(k) for g, key in res.values() for i, k in zip(g, key, strict=True)}
    strip = (face < width) & ~np.isin(np.arange(p.shape[0]), head)
    near = strip & (corner < blob)
    keys = reorder(p, keys, np.flatnonzero(strip & ~near), head, cell)
    again = strip & (corner < blob + width)  # (and the first stage's points near the corners: their
    # keys were decided beside the corners' tile keys)
    keys = reorder(p, {i: k for i, k in keys.items() if not again[i]}, np.flatnonzero(again), head, cell)
    g = np.fromiter(keys, np.int64, len(keys))
    k = np.fromiter(keys.values(), float, len(keys))
    return g[np.argsort(-k, kind="stable")]


def quality(p: np.ndarray, order: np.ndarray, tile: np.ndarray, ref: np.ndarray, sizes: np.ndarray) -> dict[str, Any]:
    """Covering over the reference's at each size, and the smallest distance between points of
    different tiles over the covering radius."""
    cover, spacing = [], []
    for n in sizes:
        a = order[:n]
        r = cKDTree(p[a]).query(p)[0].max()
        cover.append(float(r / cKDTree(p[ref[:n]]).query(p)[0].max()))
        d, j = cKDTree(p[a]).query(p[a], k=8)
        spacing.append(float(np.where(tile[a][j] != tile[a][:, None], d, np.inf).min() / r))
    c, s = np.array(cover), np.array(spacing)
    return {"covering_worst": round(float(c.max()), 4), "covering_median": round(float(np.median(c)), 4),
            "spacing_min": round(float(s.min()), 4), "spacing_median": round(float(np.median(s)), 4),
            "covering": [round(x, 4) for x in cover], "spacing": [round(x, 4) for x in spacing]}


def main(argv: list[str] | None = None) -> int:
    from benchdoc import finish, stamp

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--tiles", type=int, default=2, help="tiles per side")
    ap.add_argument("--head", type=int, default=330, help="points of the head (the reference's first)")
    ap.add_argument("--widths", default="0.5,1,2", help="strip widths, in units of the head's last key")
    ap.add_argument("--alpha", type=float, default=0.25, help="the seam repair's spacing (the build's default)")
    ap.add_argument("--shape", default="uniform", choices=["uniform", "uneven", "holes"])
    ap.add_argument("--levels-to", type=float, default=0.03, help="the finest level, a share of the points")
    ap.add_argument("--stop", type=float, default=0.3, help="tile orders stop at this x the finest level's key")
    ap.add_argument("--corner", type=float, default=0.0,
                    help="also order each strip in two stages: corners of this radius (x r_head) last (0: not)")
    ap.add_argument("--blind", action="store_true", help="tiles ordered without their neighbours' orders")
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args(argv)
    doc = stamp("seam_strip_model", argv, inputs=f"synthetic {args.shape} sheet", synthetic=True)
    p = sheet(args.points, args.shape)
    m = int(args.levels_to * p.shape[0])
    ref, rkey = fps(p, np.full(p.shape[0], np.inf), np.zeros((0, 3)), np.zeros(0), 0.0, int(1.2 * m))
    head, r_head = ref[: args.head], float(rkey[args.head - 1])
    res, tile, face = tile_orders(p, args.tiles, head, args.stop * float(rkey[m - 1]), args.blind)
    c = np.arange(1, args.tiles) / args.tiles
    corner = (cKDTree(np.stack(np.meshgrid(c, c), -1).reshape(-1, 2)).query(p[:, :2])[0]
              if args.tiles > 1 else np.full(p.shape[0], np.inf))
    sizes = np.unique(np.geomspace(2 * args.head, m, 24).astype(int))
    cell = float(rkey[m - 1]) / 2
    variants = {"none": merge_none(res), f"defer {args.alpha}": merge_defer(p, res, tile, face, head, args.alpha, cell)[0]}
    strip_share = {}
    for w in [float(x) for x in args.widths.split(",")]:
        variants[f"strip {w}"] = merge_strip(p, res, face, head, w * r_head, cell)
        strip_share[f"strip {w}"] = round(float((face < w * r_head).mean()), 4)
        if args.corner:
            variants[f"strip {w}, corners {args.corner}"] = merge_staged(p, res, face, corner, head, w * r_head,
                                                                         args.corner * r_head, cell)
    doc.update({"points": int(p.shape[0]), "tiles": args.tiles ** 2, "head": args.head, "r_head": r_head,
                "tile_side_over_r_head": round(1 / args.tiles / r_head, 2), "sizes": sizes.tolist(),
                "strip_share_of_points": strip_share,
                "variants": {k: quality(p, np.concatenate([head, v]), tile, ref, sizes) for k, v in variants.items()}})
    text = json.dumps(finish(doc), indent=1)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
