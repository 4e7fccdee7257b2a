"""Generate synthetic fragmented scenes: what an airborne tile looks like to the band (hundreds of
pieces), deterministic by seed.

    python tools/make_fragmented.py --seed 3 --pieces 400 --points 200000 -o /tmp/frag.npy

A scene is a square site of side ``site`` metres with: ground patches (flat, slightly sloped,
with gaps between them: the band does not bridge them), roofs (flat or gabled, raised above the
ground, each its own piece), trees (noisy ellipsoidal crowns of scattered returns, often several
pieces each), cars (small boxes' tops and sides), wires (thin sagging lines between poles) and a
few stray points. Density is uneven: every piece draws its own spacing factor (0.5 to 3 x), so
some parts are sampled far more densely than others. ``pieces`` is the number of objects placed
(50 to 2,000), ``points`` the total, shared out by object area and density.

Prints a JSON line (file, points, objects, seed). The scene is synthetic, not a real survey.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

KINDS = ("ground", "roof", "tree", "car", "wire", "stray")
SHARES = (0.25, 0.25, 0.25, 0.12, 0.08, 0.05)  # of the objects


def _ground(rng, c, size):
    w, d = size * rng.uniform(0.6, 1.0, 2)
    sx, sy = rng.normal(0, 0.03, 2)  # a gentle slope

    def f(m):
        x, y = rng.random(m) * w, rng.random(m) * d
        return np.c_[c[0] + x, c[1] + y, sx * x + sy * y + rng.normal(0, 0.02, m)]

    return f, w * d


def _roof(rng, c, size):
    w, d = size * rng.uniform(0.3, 0.7, 2)
    z0, pitch, gable = rng.uniform(3, 12), rng.uniform(0.1, 0.6), rng.random() < 0.5

    def f(m):
        x, y = rng.random(m) * w, rng.random(m) * d
        z = z0 + (pitch * (w / 2 - np.abs(x - w / 2)) if gable else 0.0)
        return np.c_[c[0] + x, c[1] + y, z + rng.normal(0, 0.01, m)]

    return f, w * d


def _tree(rng, c, size):
    r, h = size * rng.uniform(0.1, 0.3), rng.uniform(4, 15)

    def f(m):
        v = rng.normal(size=(m, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v *= rng.random((m, 1)) ** 0.3  # returns inside the crown too
        return c + [r, r, 0] + v * [r, r, 0.6 * r] + [0, 0, h]

    return f, 4 * r * r


def _car(rng, c, size):
    w, d, hgt = rng.uniform(1.6, 2.0), rng.uniform(3.5, 5.0), rng.uniform(1.3, 1.8)

    def f(m):
        x, y = rng.random(m) * w, rng.random(m) * d
        side = rng.random(m) < 0.3
        z = np.where(side, rng.random(m) * hgt, hgt)
        x = np.where(side, np.where(rng.random(m) < 0.5, 0.0, w), x)
        return np.c_[c[0] + x, c[1] + y, z + 0.3]

    return f, w * d


def _wire(rng, c, size):
    length, ang, z0, sag = size * rng.uniform(0.8, 2.0), rng.uniform(0, np.pi), rng.uniform(6, 12), rng.uniform(0.3, 1.5)

    def f(m):
        t = np.sort(rng.random(m))
        z = z0 - sag * 4 * t * (1 - t)
        return np.c_[c[0] + t * length * np.cos(ang), c[1] + t * length * np.sin(ang), z] + rng.normal(0, 0.01, (m, 3))

    return f, length * 0.1


def _stray(rng, c, size):
    return lambda m: c + rng.normal(0, 0.05, (m, 3)) + [0, 0, rng.uniform(1, 30)], 0.01


MAKERS = {"ground": _ground, "roof": _roof, "tree": _tree, "car": _car, "wire": _wire, "stray": _stray}


def fragmented_scene(seed: int = 0, pieces: int = 200, points: int = 50_000) -> np.ndarray:
    """(N, 3) float64 points of a scene of ``pieces`` objects and ``points`` points (see the module
    docstring). The same seed gives the same scene."""
    rng = np.random.default_rng(seed)
    pieces = int(pieces)
    site = 30.0 * np.sqrt(pieces)  # about 900 m^2 per object
    kinds = rng.choice(len(KINDS), pieces, p=SHARES)
    objs, weights = [], []
    for kind in kinds:
        name = KINDS[kind]
        c = np.r_[rng.random(2) * site, 0.0]
        f, area = MAKERS[name](rng, c, 20.0)
        density = rng.uniform(0.5, 3.0) ** 2
        objs.append((name, f))
        weights.append(0.0 if name == "stray" else area * density)
    w = np.asarray(weights)
    n_stray = sum(1 for name, _ in objs if name == "stray")
    counts = np.floor(w / w.sum() * (points - 3 * n_stray)).astype(int)
    counts[np.asarray([name == "stray" for name, _ in objs])] = 3
    counts[np.argmax(w)] += points - counts.sum()
    parts = [f(int(m)) for (name, f), m in zip(objs, counts, strict=True) if m > 0]
    return np.ascontiguousarray(np.vstack(parts), dtype=np.float64)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pieces", type=int, default=200, help="objects placed (50 to 2,000)")
    ap.add_argument("--points", type=int, default=50_000)
    ap.add_argument("-o", "--output", required=True, help="a .npy file")
    a = ap.parse_args(argv)
    pts = fragmented_scene(a.seed, a.pieces, a.points)
    np.save(a.output, pts)
    print(json.dumps({"file": str(Path(a.output)), "points": int(pts.shape[0]), "objects": a.pieces,
                      "seed": a.seed, "synthetic": True}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
