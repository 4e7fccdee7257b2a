"""Geodesic covering of the small bunny resolutions: band ordering of one or more trees against
exact Euclidean FPS (JSON).

Inputs (real, ``../shared/data``): bun_zipper_res2/res3/res4.ply (8,171 / 1,889 / 453 points),
Stanford's decimations of bun_zipper.ply (35,947 vertices, 69,451 triangles), which serves as the
geodesic reference. For every scan and every ordering (the band ordering of each ``--trees`` entry,
run in a fresh process with that tree on PYTHONPATH, and lodbuilder's exact Euclidean FPS) and
every size level k = 1, 2, 5, 10, 20 % of the points: the geodesic covering radius of the prefix,
max over the scan's points of the distance along the surface to the nearest of the first k points,
and its ratio to the ordering's own radius there (the next insertion radius: the rho whose level is
that prefix; Euclidean for Euclidean FPS), and to Euclidean FPS's covering at equal size.

Geodesics: multi-source Dijkstra (scipy.sparse.csgraph, ``min_only``) on the fine mesh's graph,
edges = the triangles' edges plus the chords to the 2-ring (straight lengths; the 2-ring cuts the
graph's metrication error: a path along edges only is up to ~8 % longer than the surface
geodesic); every scan point is mapped to its nearest vertex of the mesh's one connected piece (the file's
other 1,113 vertices belong to no triangle). The method's own error is
reported: ``map_max``/``map_median`` (distance from a scan point to its fine vertex; a covering
radius can move by at most 2 x map_max), and ``metrication``: on 2,000 random pairs of fine
vertices 2-8 mean edge lengths apart (where the surface is nearly flat, so the geodesic is close
to the chord) the ratio of graph distance to Euclidean distance (median, p95) for the 1-ring and
the 2-ring graph.

    python tools/bench_tiny.py [--trees new=.,old=/tmp/old50_lead] [--json OUT] [--markdown docs/benchmarks.md]
    python tools/bench_tiny.py --from-json OUT --markdown docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT / "tools"))

DATA = ROOT.parent / "shared" / "data"
SCANS = ("bun_zipper_res4.ply", "bun_zipper_res3.ply", "bun_zipper_res2.ply")
FINE = "bun_zipper.ply"
FRACTIONS = (0.01, 0.02, 0.05, 0.10, 0.20)

_ORDER = (
    "import sys, numpy as np\n"
    "import lodbuilder\n"
    "from lodbuilder.io import read_scan\n"
    "from lodbuilder.sampling.fastfps import fastfps\n"
    "o = fastfps(read_scan(sys.argv[1]).points)\n"
    "np.savez(sys.argv[2], order=o.order, radius=o.radius, thin=o.stats.get('thin_points', 0),"
    " grid=o.stats.get('grid_points', 0), tree=lodbuilder.__file__)\n"
)


def band_ordering(tree: str, scan: Path, out: Path) -> dict:
    """The default band ordering of ``scan`` by the lodbuilder of ``tree`` (a fresh process)."""
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
    # cwd: not the checkout this tool runs from ("-c" puts the working directory first on sys.path)
    subprocess.run([sys.executable, "-c", _ORDER, str(scan), str(out)], env=env, check=True, cwd=out.parent)
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def fine_graph(path: Path, two_ring: bool):
    """Vertices and the sparse edge-length graph of the fine mesh."""
    import scipy.sparse as sp
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    v = np.stack([ply["vertex"][a] for a in "xyz"], axis=1).astype(np.float64)
    faces = np.stack(ply["face"]["vertex_indices"]).astype(np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    n = v.shape[0]
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    if two_ring:
        a = ((a + a @ a) > 0).astype(np.float64)
    a.setdiag(0)
    a.eliminate_zeros()
    coo = a.tocoo()
    w = np.linalg.norm(v[coo.row] - v[coo.col], axis=1)
    return v, sp.csr_matrix((w, (coo.row, coo.col)), shape=(n, n))


def metrication(v: np.ndarray, graphs: dict, seed: int = 0) -> dict:
    """Graph distance / chord on random vertex pairs 2-8 mean edge lengths apart."""
    from scipy.sparse.csgraph import dijkstra

    rng = np.random.default_rng(seed)
    edge = float(np.median(graphs["1-ring"].data))
    src = rng.choice(v.shape[0], 40, replace=False)
    out = {}
    for name, g in graphs.items():
        d = dijkstra(g, indices=src, limit=10 * edge)
        ratios = []
        for row, s in enumerate(src):
            chord = np.linalg.norm(v - v[s], axis=1)
            ok = np.flatnonzero((chord > 2 * edge) & (chord < 8 * edge) & np.isfinite(d[row]))
            take = rng.choice(ok, min(50, ok.size), replace=False)
            ratios.extend(d[row, take] / chord[take])
        r = np.asarray(ratios)
        out[name] = {"pairs": int(r.size), "median": float(np.median(r)), "p95": float(np.percentile(r, 95))}
    out["mean_edge"] = edge
    return out


def covering(graph, vid: np.ndarray, order: np.ndarray, k: int) -> float:
    """Max over the scan's points (fine vertices ``vid``) of the graph distance to the first k."""
    from scipy.sparse.csgraph import dijkstra

    d = dijkstra(graph, indices=np.unique(vid[order[:k]]), min_only=True)
    return float(d[vid].max())


def markdown(doc: dict) -> str:
    """The 'tiny' section of docs/benchmarks.md."""
    from benchdoc import measured

    m = doc["metrication"]
    names = [*doc["trees"], "euclidean_fps"]
    lines = [
        f"{measured(doc)}. Inputs real (../shared/data). Trees: "
        + ", ".join(f"{k} = `{v}`" for k, v in doc["trees"].items())
        + "; euclidean_fps = lodbuilder's exact Euclidean FPS.",
        "",
        "Per level (the first k points): the geodesic covering radius (max over the scan's points of "
        "the distance along bun_zipper.ply's surface to the nearest of the k, Dijkstra on its 2-ring "
        "graph) divided by the ordering's own radius there (*cover / rho*: above 1 the level's rho "
        "promises more than it holds), and divided by Euclidean FPS's covering at the same size "
        "(*vs FPS*: above 1 the level is coarser). Method error: the 2-ring graph is "
        f"{100 * (m['2-ring']['median'] - 1):.1f} % longer than the chord on pairs 2-8 edges apart "
        f"(median, p95 {100 * (m['2-ring']['p95'] - 1):.1f} %; 1-ring {100 * (m['1-ring']['median'] - 1):.1f} %); "
        "scan points lie up to map_max from their fine vertex (common to all orderings).",
        "",
        "| scan | points | map_max mm | k | " + " | ".join(f"{t} cover/rho" for t in names)
        + " | " + " | ".join(f"{t} vs FPS" for t in doc["trees"]) + " |",
        "|---|---|---|---|" + "---|" * (len(names) + len(doc["trees"])),
    ]
    for sc in doc["scans"]:
        for lv in sc["levels"]:
            lines.append(
                f"| {sc['scan']} | {sc['points']:,} | {1e3 * sc['map_max']:.2f} | {lv['size']} | "
                + " | ".join(f"{lv[f'ratio_{t}_vs_rho']:.2f}" for t in names)
                + " | " + " | ".join(f"{lv[f'ratio_{t}_vs_fps']:.2f}" for t in doc["trees"]) + " |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from benchdoc import publish, stamp
    from scipy.spatial import cKDTree

    from lodbuilder.io import read_scan
    from lodbuilder.sampling.fastfps import euclidean_fps

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trees", default=f"new={ROOT},old=/tmp/old50_lead")
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--json", help="also write the JSON here")
    ap.add_argument("--markdown", help="also write the 'tiny' section of this markdown file")
    ap.add_argument("--from-json", help="render the markdown section from a saved JSON report")
    args = ap.parse_args(argv)
    if args.from_json:
        from benchdoc import load_run, write_section

        doc = load_run(args.from_json)
        write_section(Path(args.markdown or ROOT / "docs" / "benchmarks.md"), "tiny", markdown(doc))
        return 0
    trees = dict(t.split("=", 1) for t in args.trees.split(","))
    data = Path(args.data)
    doc = stamp("bench_tiny", argv, inputs=f"real: {', '.join(SCANS)}; reference mesh {FINE}", synthetic=False)
    doc["trees"] = trees
    v, g1 = fine_graph(data / FINE, False)
    _, g2 = fine_graph(data / FINE, True)
    doc["metrication"] = metrication(v, {"1-ring": g1, "2-ring": g2})
    from scipy.sparse.csgraph import connected_components

    _, lab = connected_components(g1, directed=False)
    main_part = np.flatnonzero(lab == np.argmax(np.bincount(lab)))  # 34,834 of 35,947: the rest are unused
    doc["fine_vertices_used"] = int(main_part.size)
    kd = cKDTree(v[main_part])
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_tiny_{os.getpid()}.npz"
    doc["scans"] = []
    for name in SCANS:
        pts = read_scan(data / name).points
        n = pts.shape[0]
        dmap, vid = kd.query(pts)
        vid = main_part[vid]
        orders = {t: band_ordering(path, data / name, tmp) for t, path in trees.items()}
        e = euclidean_fps(pts)
        orders["euclidean_fps"] = {"order": e.order, "radius": e.radius}  # radius: Euclidean
        entry: dict = {
            "scan": name, "points": n, "map_max": float(dmap.max()), "map_median": float(np.median(dmap)),
            "thin_points": {t: int(o["thin"]) for t, o in orders.items() if "thin" in o},
            "grid_points": {t: int(o["grid"]) for t, o in orders.items() if "grid" in o},
            "imported": {t: str(o["tree"]) for t, o in orders.items() if "tree" in o},
            "levels": [],
        }
        for f in FRACTIONS:
            k = max(2, round(f * n))
            lv: dict = {"fraction": f, "size": k}
            for t, o in orders.items():
                lv[f"cover_{t}"] = covering(g2, vid, o["order"], k)
                lv[f"cover1_{t}"] = covering(g1, vid, o["order"], k)
                if "radius" in o:
                    lv[f"rho_{t}"] = float(o["radius"][k])  # the next insertion radius
            for t in trees:
                lv[f"ratio_{t}_vs_fps"] = lv[f"cover_{t}"] / lv["cover_euclidean_fps"]
            for t in orders:
                lv[f"ratio_{t}_vs_rho"] = lv[f"cover_{t}"] / lv[f"rho_{t}"]
            entry["levels"].append(lv)
        doc["scans"].append(entry)
        print(json.dumps({"scan": name, "levels": [
            {k2: round(x, 4) if isinstance(x, float) else x for k2, x in lv.items() if "ratio" in k2 or k2 == "size"}
            for lv in entry["levels"]]}), file=sys.stderr)
    tmp.unlink(missing_ok=True)
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=2, default=float))
    publish(doc, section="tiny", render=markdown, markdown=args.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
