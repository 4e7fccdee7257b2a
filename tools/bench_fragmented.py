"""Coarse levels of fragmented scans: the Euclidean covering radius of lodbuilder's prefixes
against exact Euclidean farthest point sampling (fpsample) of the same size.

    python tools/bench_fragmented.py -o run.json        # then: python tools/benchdoc.py store
    python tools/bench_fragmented.py --surface -o s.json  #   docs/bench/bench_fragmented.json run|surface F
    python tools/bench_fragmented.py --quick            # one small generated scene, no real scans

Scenes: synthetic fragmented scenes of tools/make_fragmented.py (several seeds and piece counts),
synthetic coarse closed surfaces (tori whose tube is 5-6 point spacings across: every point's other
side lies within the band's reach, as on the bunny's decimations) and every real scan of
../shared/data (autzen, simple.las, the ten bunny range scans, the bunny's reconstruction and its
decimations, bunnyDouble.e57, Igea, frag_115, the pump). For each scene: the
ordering's time, its band pieces, and at sizes log-spaced from 1 point to 5 % of N the covering
radius (largest distance from any input point to the prefix, by k-d tree) of lodbuilder's prefix
and of fpsample's (``fps_sampling``, exact Euclidean FPS from the same first point),
their ratio, and whether the stored radius bounds the covering radius. Targets (issue 20): ratio
<= 1.25 at every size, <= 1.05 from 1 % of N on. Each scene also gets the SHA-256 of its order
(to compare orderings between commits). Prints JSON (stamped with date, commit and command).

``--surface`` asks, on the bunny meshes (PLY files with triangles; each restricted to its largest
connected mesh component), how much of lodbuilder's excess over Euclidean FPS its distances along
the surface explain: the same levels against an ordering by distances along the mesh (farthest
point sampling on the mesh's edge graph, Dijkstra), with the covering radius measured both
in space and along the mesh.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

REAL = ("autzen_trim.laz", "simple.las", "bun000.ply", "bun045.ply", "bun090.ply", "bun180.ply", "bun270.ply",
        "bun315.ply", "chin.ply", "ear_back.ply", "top2.ply", "top3.ply", "bun_zipper.ply", "bun_zipper_res2.ply",
        "bun_zipper_res3.ply", "bun_zipper_res4.ply", "bunnyDouble.e57", "igea.ply", "frag_115.ply",
        "pumpAVisualReferenceImage.e57")  # every real scan of ../shared/data
MESHES = ("bun_zipper.ply", "bun_zipper_res2.ply", "bun_zipper_res3.ply")
GENERATED = ((0, 50, 100_000), (1, 300, 200_000), (2, 1000, 200_000), (3, 2000, 300_000))
COARSE = ((2000, 5.0), (8000, 6.0))  # coarse closed surfaces: tori whose tube is this many spacings across


def _commit() -> str:
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def covering(pts: np.ndarray, kept: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    return float(cKDTree(kept).query(pts)[0].max())


def sizes_for(n: int, count: int = 14) -> list[int]:
    top = max(1, int(0.05 * n))
    return sorted({int(round(x)) for x in np.geomspace(1, top, count)} | {max(1, int(0.01 * n)), top})


def scene(name: str, pts: np.ndarray) -> dict:
    import fpsample

    from lodbuilder.sampling.fastfps import fastfps

    n = pts.shape[0]
    t0 = time.perf_counter()
    o = fastfps(pts)
    seconds = time.perf_counter() - t0
    sizes = sizes_for(n)
    top = sizes[-1]
    # the plain O(N k) FPS: fpsample's k-d variants (1.0.2) do not start from ``start_idx``
    ref = np.asarray(fpsample.fps_sampling(pts, top, start_idx=int(o.order[0])))
    levels = []
    for k in sizes:
        ours = covering(pts, pts[o.order[:k]])
        theirs = covering(pts, pts[ref[:k]])
        bound = float(o.radius[k]) if k < len(o) else 0.0
        levels.append({"size": k, "fraction": k / n, "cover": ours, "fpsample_cover": theirs,
                       "ratio": ours / theirs if theirs > 0 else 1.0, "stored_radius": bound,
                       "bound_holds": ours <= bound})
    late = [lv["ratio"] for lv in levels if lv["size"] >= 0.01 * n]
    return {
        "scene": name, "points": n, "seconds": round(seconds, 3), "pieces": o.stats.get("pieces"),
        "seeds_with_inf": int(np.isinf(o.radius).sum()),
        "order_sha256": hashlib.sha256(np.ascontiguousarray(o.order, dtype=np.int64).tobytes()).hexdigest(),
        "max_ratio": max(lv["ratio"] for lv in levels), "max_ratio_from_1pct": max(late) if late else None,
        "bound_holds": all(lv["bound_holds"] for lv in levels), "levels": levels,
    }


def coarse_torus(n: int, tube_spacings: float, seed: int = 0) -> np.ndarray:
    """n random points on a torus of ring radius 1 whose tube is ``tube_spacings`` point spacings
    across: a closed surface sampled coarsely for its shape, like the bunny's decimations."""
    from lodbuilder.datasets import torus

    return torus(n, seed=seed, major=1.0, minor=(tube_spacings / 2) ** 2 * 4 * np.pi**2 / n)[0]


def _mesh(path: Path) -> tuple[np.ndarray, object]:
    """The points of the largest connected component of a triangle mesh and its edge graph
    (Euclidean edge lengths)."""
    import pyvista as pv
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = pv.read(str(path))
    pts, f = np.asarray(m.points, np.float64), m.faces.reshape(-1, 4)[:, 1:]
    e = np.vstack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    w = np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1)
    g = coo_matrix((w, (e[:, 0], e[:, 1])), shape=(len(pts),) * 2).tocsr()
    g = g.maximum(g.T)
    _, lab = connected_components(g, directed=False)
    keep = lab == np.bincount(lab).argmax()
    return np.ascontiguousarray(pts[keep]), g[keep][:, keep]


def _mesh_fps(g, start: int, k: int) -> np.ndarray:
    """Farthest point sampling by distance along the mesh graph ``g`` (k points from ``start``)."""
    from scipy.sparse.csgraph import dijkstra

    d = dijkstra(g, directed=False, indices=start)
    order = [start]
    for _ in range(k - 1):
        j = int(np.argmax(d))
        order.append(j)
        d = np.minimum(d, dijkstra(g, directed=False, indices=j, limit=d[j]))
    return np.asarray(order)


def surface(name: str) -> dict:
    """lodbuilder, Euclidean FPS and FPS along the mesh on one bunny mesh (see the module)."""
    import fpsample
    from scipy.sparse.csgraph import dijkstra

    from lodbuilder.sampling.fastfps import fastfps

    pts, g = _mesh(DATA / name)
    o = fastfps(pts)
    sizes = sizes_for(pts.shape[0])
    start = int(o.order[0])
    runs = {"lodbuilder": o.order, "fpsample": np.asarray(fpsample.fps_sampling(pts, sizes[-1], start_idx=start)),
            "mesh_fps": _mesh_fps(g, start, sizes[-1])}
    levels = []
    for k in sizes:
        lv: dict = {"size": k}
        for key, order in runs.items():
            lv[f"{key}_cover"] = covering(pts, pts[order[:k]])
            lv[f"{key}_surface_cover"] = float(dijkstra(g, directed=False, indices=np.unique(order[:k]),
                                                        min_only=True).max())
        levels.append(lv)
    late = [lv for lv in levels if lv["size"] >= 0.01 * pts.shape[0]]

    def worst(a: str, b: str, rows: list[dict]) -> float:
        return max(r[a] / r[b] for r in rows)

    return {"scene": name, "points": int(pts.shape[0]), "pieces": o.stats.get("pieces"),
            "from_1pct": {"cover_over_fpsample": worst("lodbuilder_cover", "fpsample_cover", late),
                          "mesh_fps_cover_over_fpsample": worst("mesh_fps_cover", "fpsample_cover", late),
                          "surface_cover_over_mesh_fps": worst("lodbuilder_surface_cover", "mesh_fps_surface_cover", late),
                          "fpsample_surface_cover_over_mesh_fps": worst("fpsample_surface_cover",
                                                                        "mesh_fps_surface_cover", late)},
            "levels": levels}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-o", "--output", help="write the JSON here too")
    ap.add_argument("--quick", action="store_true", help="one small generated scene only")
    ap.add_argument("--surface", action="store_true", help="the bunny meshes, along the surface too (only)")
    a = ap.parse_args(argv)
    from make_fragmented import fragmented_scene

    from lodbuilder.io import read_scan

    out = []
    gen = () if a.surface else GENERATED[:1] if a.quick else GENERATED
    for seed, pieces, points in gen:
        out.append(scene(f"synthetic fragmented seed={seed} objects={pieces}", fragmented_scene(seed, pieces, points)))
        print(json.dumps({k: v for k, v in out[-1].items() if k != "levels"}), file=sys.stderr)
    for n, tube in () if a.surface or a.quick else COARSE:
        out.append(scene(f"synthetic coarse torus n={n} tube={tube:g} spacings", coarse_torus(n, tube)))
        print(json.dumps({k: v for k, v in out[-1].items() if k != "levels"}), file=sys.stderr)
    for f in MESHES if a.surface else ():
        out.append(surface(f))
        print(json.dumps({k: v for k, v in out[-1].items() if k != "levels"}), file=sys.stderr)
    if not (a.quick or a.surface):
        for f in REAL:
            if (DATA / f).exists():
                out.append(scene(f, read_scan(DATA / f).points))
                print(json.dumps({k: v for k, v in out[-1].items() if k != "levels"}), file=sys.stderr)
    doc = {
        "benchmark": "bench_fragmented" + ("_surface" if a.surface else ""),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "commit": _commit(),
        "command": " ".join(["python", "tools/bench_fragmented.py", *(argv if argv is not None else sys.argv[1:])]),
        "targets": {"max_ratio": 1.25, "max_ratio_from_1pct": 1.05},
        "scenes": out,
    }
    text = json.dumps(doc, indent=1)
    if a.output:
        Path(a.output).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
