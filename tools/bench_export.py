"""Benchmark: COPC export and the standalone web page of a 1M-point archive (JSON to stdout).

Input: a synthetic scan (lodbuilder's demo surface: a wavy sheet with RGB, ``--points`` points,
default 1,000,000), built once into an archive (or ``--archive A.h5`` to reuse one). Measured:

* ``copc``: ``export -o OUT.copc.laz`` (target <= 10 s for 1M points) without rank/radius
  (``default``), with ``--rank-radius`` (``level``: a sublevel byte a point and the sub-level
  table) and with ``--rank-radius exact`` (the uint32 rank and the radius by rank): seconds,
  bytes, bytes a point, depths, nodes; for ``level`` a check that sampled sub-level bounds of
  laspy's CopcReader return the archive's levels with the archive's rho, for ``exact`` that
  every depth query returns its prefix of ranks;
* ``copc_vs_source`` (``--source LAZ``, repeatable: each built into an archive first): the COPC
  size against the source LAZ's, without rank/radius (target <= 1.15 x) and in both
  ``--rank-radius`` modes (target <= 1.5 x), the bytes a point of each depth, and the bytes of
  our tables;
* ``web``: ``export -o OUT.html`` (target <= 30 MB for 1M points): seconds, bytes, and the time
  headless Chromium (Debian's, through playwright) takes from navigation to the last frame drawn
  (target <= 15 s), with the requests the page made;
* ``tiles``: ``export -o DIR/tileset.json`` (3D Tiles 1.1; target: valid against the schema subset
  of tests/schemas, drawn by CesiumJS in headless Chromium within 20 s with 0 requests outside the
  local server): seconds, bytes, tiles, and the seconds from navigation until every tile is loaded
  (tools/cesiumjs/view.html: Cesium's defaults; then every tile, ``?sse=1``; every tile without
  MSAA; every tile with point attenuation), the frames drawn and when the last tile arrived;
* ``pyvista_export_html`` (the peer, when trame, trame-vtk, trame-vuetify and trame-pyvista are
  importable): PyVista's ``Plotter.export_html`` of the same points with RGB, its bytes and
  seconds, and the requests Chromium makes when it opens the file.

    python tools/bench_export.py [--points 1000000] [--archive A.h5] [--source S.laz ...]
                                 [--copc-only] [--markdown docs/benchmarks.md]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from benchdoc import load_run, machine, measured, publish, stamp, write_section

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = os.environ.get("LODBUILDER_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]


def render(path: Path, ready_js: str | None, wait_s: float = 0.0) -> dict:
    """Open ``path`` in headless Chromium: seconds from navigation until ``ready_js`` is true
    (or ``wait_s`` when None), and every request the page made."""
    from playwright.sync_api import sync_playwright

    out: dict = {}
    with sync_playwright() as p:
        t0 = time.perf_counter()
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        out["launch_s"] = round(time.perf_counter() - t0, 2)
        page = browser.new_page(viewport={"width": 1200, "height": 800})
        requests: list[str] = []
        errors: list[str] = []
        page.on("request", lambda r: requests.append(r.url))
        page.on("pageerror", lambda e: errors.append(str(e)))
        t0 = time.perf_counter()
        page.goto(path.resolve().as_uri(), timeout=120_000)
        if ready_js is None:
            page.wait_for_timeout(wait_s * 1000)
        else:
            while not page.evaluate(ready_js):
                page.wait_for_timeout(20)
                if time.perf_counter() - t0 > 120:
                    out["timeout"] = True
                    break
        out["render_s"] = round(time.perf_counter() - t0, 2)
        if ready_js is not None:
            out["history"] = page.evaluate("() => LOD.state.history")
        own = path.resolve().as_uri()
        out["requests"] = len(requests)
        out["outside_requests"] = sorted({u for u in requests if u != own})
        out["page_errors"] = errors
        browser.close()
    return out


def bytes_by_depth(path: Path) -> list[float]:
    """Compressed bytes per point of each depth's nodes (from the COPC hierarchy): where the
    bytes go (a coarse depth is a sparse subsample, which LAZ codes at about twice the cost)."""
    import laspy
    from laspy.copc import load_octree_for_query

    with laspy.CopcReader.open(str(path)) as reader:
        found = load_octree_for_query(reader.source, reader.copc_info, reader.root_page,
                                      query_bounds=None, level_range=None)
    size: dict[int, list[int]] = {}
    for n in found:
        acc = size.setdefault(n.key.level, [0, 0])
        acc[0] += n.byte_size
        acc[1] += n.point_count
    return [round(size[d][0] / size[d][1], 2) for d in sorted(size)]


def record_bytes(path: Path, record_id: int) -> int:
    """Bytes of our EVLR ``record_id`` (2: the radius by rank, 3: the sub-level table)."""
    import laspy

    from lodbuilder.export.copc import VLR_USER_ID

    with laspy.open(str(path)) as r:
        return sum(len(v.record_data) for v in r.header.evlrs
                   if v.user_id == VLR_USER_ID and v.record_id == record_id)


def depth_queries_ok(out: Path, levels: list) -> bool:
    """Every depth query of laspy's CopcReader returns the prefix of ranks the EVLR names."""
    import laspy
    import numpy as np

    ok = True
    with laspy.CopcReader.open(str(out)) as reader:
        for lv in levels:
            rank = np.sort(np.asarray(reader.query(level=range(lv["depth"] + 1))["rank"]))
            ok &= bool(rank.size == lv["points"])
            ok &= bool(np.array_equal(rank[: lv["fps_prefix"]], np.arange(lv["fps_prefix"])))
    return ok


def sublevel_queries_ok(view, out: Path, rows: int = 9) -> bool:
    """For ``rows`` rows of the sub-level table (spread over it): the points of depths < D and
    of depth D with sublevel <= s (laspy's CopcReader) are the archive's level of the row's
    prefix (integer coordinates as multisets), and the row's rho is the archive's."""
    import laspy
    import numpy as np

    from lodbuilder.export.copc import read_sublevels

    table = read_sublevels(out)
    with laspy.CopcReader.open(str(out)) as reader:
        scales, offsets = reader.header.scales, reader.header.offsets
        depths = [reader.query(level=d) for d in range(int(table["depth"].max()) + 1)]
    xyz = [np.column_stack([np.asarray(g.X), np.asarray(g.Y), np.asarray(g.Z)]).astype(np.int64)
           for g in depths]
    every = np.rint((view.points(view.n_ordered) - offsets) / scales).astype(np.int64)
    ok = True
    for i in np.unique(np.linspace(0, table.size - 1, rows).astype(int)):
        d, s, p = int(table["depth"][i]), int(table["sublevel"][i]), int(table["prefix"][i])
        sub = np.asarray(depths[d]["sublevel"])
        got = np.concatenate(xyz[:d] + [xyz[d][sub <= s]])
        want = every[:p]
        ok &= bool(got.shape == want.shape and np.array_equal(
            got[np.lexsort(got.T[::-1])], want[np.lexsort(want.T[::-1])]))
        ok &= bool(table["rho"][i] == view.level(size=p).rho)
    return ok


#: the COPC variants measured: no rank/radius, --rank-radius (level), --rank-radius exact
MODES = {"default": None, "level": "level", "exact": "exact"}


def bench_copc(view, out: Path) -> dict:
    from lodbuilder.export.copc import RADIUS_RECORD_ID, SUBLEVEL_RECORD_ID, export_copc

    res = {}
    for key, mode in MODES.items():
        t0 = time.perf_counter()
        got = export_copc(view, out, view.n_ordered, rank_radius=mode)
        secs = time.perf_counter() - t0
        one = {
            "seconds": round(secs, 2),
            "bytes": got.n_bytes,
            "bytes_per_point": round(got.n_bytes / got.n_points, 3),
            "depths": got.depths,
            "nodes": got.nodes,
            "promoted": got.promoted,
            "points_by_depth": [lv["points"] for lv in got.levels],
            "bytes_per_point_by_depth": bytes_by_depth(out),
        }
        if mode == "exact":
            one["radius_table_bytes"] = record_bytes(out, RADIUS_RECORD_ID)
            one["depth_queries_return_their_prefix"] = depth_queries_ok(out, got.levels)
        if mode == "level":
            one["sublevel_table_bytes"] = record_bytes(out, SUBLEVEL_RECORD_ID)
            one["sublevel_queries_return_the_archive_levels"] = sublevel_queries_ok(view, out)
        res[key] = one
    return res


def bench_tiles(view, tmp: Path) -> dict:
    """Export 3D Tiles, validate the tileset, and time CesiumJS drawing it (tools/cesiumjs)."""
    import functools
    import http.server
    import shutil
    import threading

    import jsonschema

    from lodbuilder.export.tiles import export_tiles

    out = tmp / "tiles" / "tileset.json"
    out.parent.mkdir()
    t0 = time.perf_counter()
    ts = export_tiles(view, out, view.n_ordered)
    res = {"seconds": round(time.perf_counter() - t0, 2), "bytes": ts.n_bytes, "tiles": ts.tiles,
           "depths": ts.depths, "geometric_errors": ts.geometric_errors}
    schema = json.loads((ROOT / "tests" / "schemas" / "tileset-1.1-subset.schema.json").read_text())
    res["schema_valid"] = jsonschema.Draft202012Validator(schema).is_valid(json.loads(out.read_text()))
    build = ROOT / "tools" / "cesiumjs" / "node_modules" / "cesium" / "Build" / "Cesium"
    if not build.is_dir():
        res["cesium"] = {"skipped": "npm install in tools/cesiumjs first"}
        return res
    site = tmp / "site"
    site.mkdir()
    (site / "cesium").symlink_to(build)
    (site / "tiles").symlink_to(out.parent)
    shutil.copy(ROOT / "tools" / "cesiumjs" / "view.html", site / "index.html")

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(site)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}/"
    from playwright.sync_api import sync_playwright

    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
            res["cesium"] = {}
            # Cesium's defaults (screen-space error 16, MSAA 4, no point attenuation); every tile
            # (sse 1); every tile without MSAA (cheaper in SwiftShader); with attenuation
            for key, query in (("sse_16", "sse=16"), ("sse_1", "sse=1"),
                               ("sse_1_msaa_1", "sse=1&msaa=1"), ("sse_1_attenuation", "sse=1&att=1")):
                page = browser.new_page(viewport={"width": 1200, "height": 800})
                requests: list[str] = []
                page.on("request", lambda r, requests=requests: requests.append(r.url))
                t0 = time.perf_counter()
                page.goto(base + f"index.html?{query}")
                page.wait_for_function("() => LOD.loaded || LOD.error", timeout=300_000, polling=50)
                state = page.evaluate("() => LOD")
                frames = state["frames"]
                last = next((f[0] for f in frames if f[1] == state["tiles"]), None)
                res["cesium"][key] = {
                    "query": query,
                    "all_tiles_loaded_s": round(time.perf_counter() - t0, 2),
                    "last_tile_loaded_s": None if last is None else round(last / 1000, 2),
                    "frames": len(frames),
                    "tiles_loaded": state["tiles"], "points_drawn": state["points"],
                    "error": state["error"], "requests": len(requests),
                    "outside_requests": sorted({u for u in requests if not u.startswith(base)}),
                }
                page.close()
            browser.close()
    finally:
        server.shutdown()
    return res


def bench_source(source: Path, tmp: Path) -> dict:
    """Build ``source`` (a LAZ file) into an archive with defaults, export its COPC without and
    with rank/radius, and compare the sizes with the source's."""
    import lodbuilder

    arc = tmp / (source.stem + ".h5")
    t0 = time.perf_counter()
    lodbuilder.build_archive(source, arc, name=source.stem)
    build_s = time.perf_counter() - t0
    with lodbuilder.open_archive(arc) as a:
        view = a.scan()
        res = bench_copc(view, tmp / (source.stem + ".copc.laz"))
    size = source.stat().st_size
    return {
        "source": source.name,
        "source_bytes": size,
        "points": view.n_ordered,
        "build_s": round(build_s, 2),
        "copc": res,
        "source_bytes_per_point": round(size / view.n_ordered, 3),
        "ratio": round(res["default"]["bytes"] / size, 3),
        "ratio_level": round(res["level"]["bytes"] / size, 3),
        "ratio_exact": round(res["exact"]["bytes"] / size, 3),
    }


def bench_web(view, out: Path, size: int) -> dict:
    from lodbuilder.export.web import export_web

    t0 = time.perf_counter()
    page = export_web(view, out, size)
    res = {"points": size, "seconds": round(time.perf_counter() - t0, 2), "bytes": page.n_bytes}
    res["chromium"] = render(out, "() => !!(window.LOD && LOD.state.ready)")
    return res


def bench_pyvista(view, out: Path, size: int) -> dict:
    try:
        import pyvista as pv
        import trame_vtk  # noqa: F401
    except ImportError as exc:
        return {"skipped": f"not importable: {exc.name}"}
    import numpy as np

    pts = view.points(size)
    att = view.attributes(size, ["red", "green", "blue"])
    rgb = np.column_stack([att[c] for c in ("red", "green", "blue")])
    t0 = time.perf_counter()
    pl = pv.Plotter(off_screen=True)
    mesh = pv.PolyData(pts)
    mesh["rgb"] = rgb
    pl.add_mesh(mesh, scalars="rgb", rgb=True, style="points", point_size=2)
    try:
        pl.export_html(str(out))
    except Exception as exc:  # trame pieces missing
        return {"skipped": " ".join(str(exc).split())[:200]}
    finally:
        pl.close()
    res = {"points": size, "seconds": round(time.perf_counter() - t0, 2), "bytes": out.stat().st_size}
    res["chromium"] = render(out, None, wait_s=10.0)
    res["chromium"]["note"] = "render_s is a fixed 10 s wait: vtk.js gives no ready signal"
    return res


def markdown(r: dict) -> str:
    c, w = r["copc"], r.get("web")
    lines = [
        f"{measured(r)}; {r['machine']['cpu_count']} cores. Input: "
        + (f"synthetic wavy sheet with RGB, {r['n_points']:,} points (archive built in {r['build_s']} s)."
           if r.get("inputs_synthetic", True) else f"{r['inputs']}, {r['n_points']:,} points."),
        "",
        "| output | seconds | size | notes |",
        "|---|---:|---:|---|",
        f"| COPC | {c['default']['seconds']} | {c['default']['bytes'] / 1e6:.1f} MB | "
        f"{c['default']['depths']} depths, {c['default']['nodes']} nodes, points by depth "
        f"{', '.join(f'{x:,}' for x in c['default']['points_by_depth'])} |",
        f"| COPC --rank-radius (level) | {c['level']['seconds']} | {c['level']['bytes'] / 1e6:.1f} MB | "
        f"{c['level']['bytes_per_point']} bytes a point; sampled sub-level queries return the archive's "
        f"levels: {c['level']['sublevel_queries_return_the_archive_levels']} |",
        f"| COPC --rank-radius exact | {c['exact']['seconds']} | {c['exact']['bytes'] / 1e6:.1f} MB | "
        f"{c['exact']['bytes_per_point']} bytes a point; every depth query returns its prefix: "
        f"{c['exact']['depth_queries_return_their_prefix']} |",
    ]
    if w:
        ch = w["chromium"]
        lines.append(
            f"| web page (ours) | {w['seconds']} | {w['bytes'] / 1e6:.1f} MB | headless Chromium: "
            f"last frame {ch['render_s']} s after navigation (launch {ch['launch_s']} s), "
            f"{ch['requests']} request(s), outside: {len(ch['outside_requests'])} |"
        )
    t = r.get("tiles")
    if t:
        ce = t.get("cesium", {})
        runs = [f"`?{v.get('query', k)}`: {v['tiles_loaded']} tiles, {v['points_drawn']:,} points drawn in "
                f"{v['all_tiles_loaded_s']} s, {len(v['outside_requests'])} request(s) outside"
                for k, v in ce.items() if k.startswith("sse_")]
        lines.append(
            f"| 3D Tiles 1.1 | {t['seconds']} | {t['bytes'] / 1e6:.1f} MB | {t['tiles']} tiles, "
            f"{t['depths']} depths; schema subset valid: {t['schema_valid']}; CesiumJS "
            + ("; ".join(runs) if runs else str(ce.get("skipped"))) + " |"
        )
    for src in r.get("copc_vs_source", []):
        lines.append(
            f"| COPC of {src['source']} ({src['points']:,} points) | "
            f"{src['copc']['default']['seconds']} | {src['copc']['default']['bytes'] / 1e6:.2f} MB | "
            f"{src['ratio']} x the source LAZ ({src['source_bytes'] / 1e6:.2f} MB); "
            f"--rank-radius (level) {src['ratio_level']} x, --rank-radius exact {src['ratio_exact']} x "
            f"({src['source_bytes_per_point']} / {src['copc']['default']['bytes_per_point']} / "
            f"{src['copc']['level']['bytes_per_point']} / {src['copc']['exact']['bytes_per_point']} "
            f"bytes a point: source / COPC / level / exact); {src['copc']['default']['depths']} depths, "
            f"points by depth {', '.join(f'{x:,}' for x in src['copc']['default']['points_by_depth'])} |"
        )
    pv = r.get("pyvista_export_html", {})
    for label, res in pv.items():
        if "skipped" in res:
            lines.append(f"| PyVista export_html, {label} | - | - | skipped: {res['skipped']} |")
        else:
            outside = res["chromium"]["outside_requests"]
            hosts = sorted({u.split("/")[2] for u in outside if "://" in u})
            lines.append(
                f"| PyVista export_html, {label} points | {res['seconds']} | "
                f"{res['bytes'] / 1e6:.1f} MB | {res['chromium']['requests']} requests, "
                f"{len(outside)} outside ({', '.join(hosts) or 'none'}) |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--archive", help="reuse this archive (its only scan) instead of building one")
    ap.add_argument("--no-peer", action="store_true", help="skip PyVista's export_html")
    ap.add_argument("--source", action="append", default=[],
                    help="a LAZ file: build it, export its COPC and compare sizes (repeatable)")
    ap.add_argument("--copc-only", action="store_true", help="skip the web page and the peer")
    ap.add_argument(
        "--peer-path",
        help="a directory appended to sys.path for the peer's trame packages "
        "(e.g. pip install --target DIR trame trame-vtk trame-vuetify trame-pyvista nest_asyncio2)",
    )
    ap.add_argument("--markdown", help="update the 'export' section of this file")
    ap.add_argument("--from-json", help="write --markdown from the JSON of an earlier run")
    args = ap.parse_args(argv)
    if args.from_json:
        if not args.markdown:
            ap.error("--from-json needs --markdown")
        write_section(Path(args.markdown), "export", markdown(load_run(args.from_json)))
        return 0
    if args.peer_path:
        sys.path.append(args.peer_path)


    import lodbuilder
    from lodbuilder.datasets import demo_scan

    result = stamp(
        "bench_export",
        argv,
        inputs=f"archive {args.archive}" if args.archive else "synthetic wavy sheet with RGB "
        f"(lodbuilder.datasets.demo_scan), {args.points:,} points",
        synthetic=not args.archive,
    )
    with tempfile.TemporaryDirectory(prefix="bench-export-") as tmp:
        arc = Path(args.archive) if args.archive else Path(tmp) / "bench.h5"
        t0 = time.perf_counter()
        if not args.archive:
            lodbuilder.build_archive(demo_scan(args.points, seed=1, name="demo"), arc, name="demo")
        result["build_s"] = round(time.perf_counter() - t0, 2)
        with lodbuilder.open_archive(arc) as a:
            view = a.scan()
            result["n_points"] = view.n_ordered
            result["copc"] = bench_copc(view, Path(tmp) / "out.copc.laz")
            if not args.copc_only:
                result["web"] = bench_web(view, Path(tmp) / "out.html", view.n_ordered)
                result["tiles"] = bench_tiles(view, Path(tmp))
            if not (args.no_peer or args.copc_only):
                result["pyvista_export_html"] = {
                    f"{k:,}": bench_pyvista(view, Path(tmp) / f"pv{k}.html", k)
                    for k in sorted({min(100_000, view.n_ordered), view.n_ordered})
                }
        result["copc_vs_source"] = [bench_source(Path(src), Path(tmp)) for src in args.source]
    result["machine"] = machine()
    publish(result, section="export", render=markdown, markdown=args.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
