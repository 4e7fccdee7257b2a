"""``lodbuilder export ARCHIVE -o DIR/tileset.json``: 3D Tiles 1.1 whose tiles' geometricError is
the stored covering radius of the points of their depth and above, points as binary glTF,
refinement ADD; valid against the 3D Tiles 1.1 schema subset we write
(tests/schemas/tileset-1.1-subset.schema.json), and drawn by CesiumJS (npm 'cesium', installed
in tools/cesiumjs) in headless Chromium with no request leaving the local server."""

from __future__ import annotations

import functools
import http.server
import json
import os
import shutil
import struct
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from lodbuilder.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "tests" / "schemas" / "tileset-1.1-subset.schema.json"
CESIUMJS = ROOT / "tools" / "cesiumjs"


@pytest.fixture(scope="module")
def autzen(autzen_archive_full):
    return autzen_archive_full


@pytest.fixture(scope="module")
def tiles(autzen, tmp_path_factory):
    out = tmp_path_factory.mktemp("tiles") / "tileset.json"
    assert main(["export", str(autzen), "-o", str(out), "-q"]) == 0
    return out


def read_glb(path: Path) -> tuple[dict, np.ndarray, np.ndarray]:
    """(glTF JSON, (n, 3) positions, (n, 4) colours) of one of our point tiles."""
    raw = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", raw)
    assert (magic, version, length) == (b"glTF", 2, len(raw))
    jlen, jtype = struct.unpack_from("<I4s", raw, 12)
    assert jtype == b"JSON"
    doc = json.loads(raw[20:20 + jlen])
    blen, btype = struct.unpack_from("<I4s", raw, 20 + jlen)
    assert btype == b"BIN\0"
    body = raw[28 + jlen:28 + jlen + blen]
    (prim,) = doc["meshes"][0]["primitives"]
    assert prim["mode"] == 0  # POINTS
    acc = doc["accessors"]
    n = acc[prim["attributes"]["POSITION"]]["count"]
    pos = np.frombuffer(body, dtype="<f4", count=3 * n).reshape(n, 3)
    col = np.frombuffer(body, dtype=np.uint8, count=4 * n, offset=12 * n).reshape(n, 4)
    np.testing.assert_allclose(pos.min(axis=0), acc[0]["min"], rtol=1e-6)
    np.testing.assert_allclose(pos.max(axis=0), acc[0]["max"], rtol=1e-6)
    return doc, pos, col


def walk(tile, depth=0, parent=None):
    yield tile, depth, parent
    for child in tile.get("children", []):
        yield from walk(child, depth + 1, tile)


def test_tileset_is_valid_3d_tiles_1_1(tiles):
    jsonschema = pytest.importorskip("jsonschema")
    doc = json.loads(tiles.read_text())
    schema = json.loads(SCHEMA.read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.Draft202012Validator(schema).validate(doc)
    assert doc["root"]["refine"] == "ADD"
    bad = dict(doc, root=dict(doc["root"], refine="MERGE"))  # the schema can fail
    assert not jsonschema.Draft202012Validator(schema).is_valid(bad)


def test_geometric_errors_are_the_stored_covering_radii(autzen, tiles):
    """Every tile of depth d has geometricError rho_d = radius[n_d] (metres: the CRS is in
    feet), the points of depths <= d are the first n_d of the ordering, every point is in its
    tile's box, and the union of the tiles is the level."""
    import lodbuilder

    doc = json.loads(tiles.read_text())
    factor = doc["asset"]["extras"]["metres_per_unit"]
    assert factor == pytest.approx(0.3048)
    with lodbuilder.open_archive(autzen) as arc:
        view = arc.scan()
        radius = np.asarray(view.radius)
        pts = np.asarray(view.points())
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    local = (pts - centre) * factor
    by_depth: dict[int, list[np.ndarray]] = {}
    errors: dict[int, float] = {}
    for tile, depth, parent in walk(doc["root"]):
        box = np.array(tile["boundingVolume"]["box"])
        c, h = box[:3], box[[3, 7, 11]]
        if parent is not None:
            pb = np.array(parent["boundingVolume"]["box"])
            assert np.all(c - h >= pb[:3] - pb[[3, 7, 11]] - 1e-9)
            assert np.all(c + h <= pb[:3] + pb[[3, 7, 11]] + 1e-9)
            assert tile["geometricError"] <= parent["geometricError"]
        _, pos, _ = read_glb(tiles.parent / tile["content"]["uri"])
        xyz = np.column_stack([pos[:, 0], -pos[:, 2], pos[:, 1]]).astype(np.float64)  # glTF y-up
        assert np.all(np.abs(xyz - c) <= h + 1e-3)
        by_depth.setdefault(depth, []).append(xyz)
        assert errors.setdefault(depth, tile["geometricError"]) == tile["geometricError"]
    tree = cKDTree_or_skip()(local)
    seen: list[np.ndarray] = []
    for d in sorted(by_depth):
        dist, idx = tree.query(np.concatenate(by_depth[d]))
        assert dist.max() < 1e-3  # float32 positions of the level's points
        seen.append(idx)
        n_d = sum(i.size for i in seen)
        # depths <= d hold the first n_d points of the ordering (autzen: none moved up)
        np.testing.assert_array_equal(np.sort(np.concatenate(seen)), np.arange(n_d))
        want = radius[n_d] * factor if n_d < radius.size else 0.0
        assert errors[d] == pytest.approx(want, rel=1e-12)
    assert n_d == radius.size
    assert doc["geometricError"] >= errors[0]


def cKDTree_or_skip():
    spatial = pytest.importorskip("scipy.spatial")
    return spatial.cKDTree


def test_tiles_take_the_copc_depths(tmp_path, monkeypatch):
    """Tiles and COPC share the octree depths: the deepest holds at least 7/8 of the points
    (with K / 4, 40,000 surface-like radii gave 6 depths and 80 % in the deepest; fewer, bigger
    tiles load in fewer CesiumJS frames: 1M points 169 -> 41 tiles)."""
    from lodbuilder.export import copc
    from lodbuilder.export.copc import write_copc
    from lodbuilder.export.tiles import write_tiles

    monkeypatch.setattr(copc, "ROOT_POINTS", 30)
    rng = np.random.default_rng(2)
    pts = rng.random((40000, 3)) * [100, 100, 1]
    radius = 1.0 / np.sqrt(np.arange(1, 40001))
    radius[0] = np.inf
    (tmp_path / "t").mkdir()
    ts = write_tiles(tmp_path / "t" / "tileset.json", pts, radius, 0.0)
    cf = write_copc(tmp_path / "c.copc.laz", pts, {}, radius, 0.0)
    assert ts.depths == cf.depths == 5
    doc = json.loads((tmp_path / "t" / "tileset.json").read_text())
    deepest = [t for t, d, _ in walk(doc["root"]) if d == 4]
    n = sum(read_glb(tmp_path / "t" / t["content"]["uri"])[1].shape[0] for t in deepest)
    assert n >= 40000 * 7 // 8


def test_tiles_errors(autzen, tmp_path, capsys):
    (tmp_path / "tileset_tiles").mkdir()
    (tmp_path / "tileset_tiles" / "mine.txt").write_text("keep me")
    out = tmp_path / "tileset.json"
    assert main(["export", str(autzen), "-o", str(out)]) == 2
    assert capsys.readouterr().err == (
        f"lodbuilder export: error: {tmp_path / 'tileset_tiles'} exists and is not a lodbuilder "
        "tiles folder; move it or choose another -o name\n"
    )
    assert (tmp_path / "tileset_tiles" / "mine.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tileset_tiles"]
    # a second export over a first one replaces its tiles
    shutil.rmtree(tmp_path / "tileset_tiles")
    assert main(["export", str(autzen), "--size", "20000", "-o", str(out), "-q"]) == 0
    assert main(["export", str(autzen), "--size", "5000", "-o", str(out), "-q"]) == 0
    n = sum(read_glb(p)[1].shape[0] for p in (tmp_path / "tileset_tiles").glob("*.glb"))
    assert n == 5000


def cesium_build() -> Path:
    """tools/cesiumjs/node_modules/cesium/Build/Cesium (npm install there), or skip."""
    build = CESIUMJS / "node_modules" / "cesium" / "Build" / "Cesium"
    if not build.is_dir():
        npm = shutil.which("npm")
        if npm is None:
            pytest.skip("npm is not installed: cannot install CesiumJS")
        r = subprocess.run([npm, "install", "--no-audit", "--no-fund"], cwd=CESIUMJS,
                           capture_output=True, text=True, timeout=600)
        if r.returncode != 0 or not build.is_dir():
            pytest.skip(f"npm install in tools/cesiumjs failed (offline?): {r.stderr.strip()[-200:]}")
    return build


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # noqa: D102
        pass


def test_cesiumjs_draws_the_tileset(tiles, tmp_path):
    """CesiumJS loads every tile of the tileset in headless Chromium, draws points, and makes no
    request outside the local server (no imagery, terrain or Ion)."""
    from test_export_web import CHROMIUM, CHROMIUM_ARGS

    if not Path(CHROMIUM).is_file():
        pytest.skip(f"no chromium at {CHROMIUM}")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    site = tmp_path / "site"
    site.mkdir()
    (site / "cesium").symlink_to(cesium_build())
    (site / "tiles").symlink_to(tiles.parent)
    shutil.copy(CESIUMJS / "view.html", site / "index.html")
    handler = functools.partial(_Quiet, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}/"
    try:
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 800, "height": 600})
            requests: list[str] = []
            errors: list[str] = []
            page.on("request", lambda r: requests.append(r.url))
            page.on("pageerror", lambda e: errors.append(str(e)))
            t0 = time.perf_counter()
            page.goto(base + "index.html?sse=1")  # every tile
            page.wait_for_function("() => LOD.loaded || LOD.error", timeout=120_000)
            seconds = time.perf_counter() - t0
            state = page.evaluate("() => LOD")
            page.wait_for_timeout(500)
            png = page.screenshot()
            browser.close()
    finally:
        server.shutdown()
    assert state["error"] is None and not errors, (state, errors)
    doc = json.loads(tiles.read_text())
    n_tiles = sum(1 for _ in walk(doc["root"]))
    assert state["tiles"] == n_tiles and state["points"] > 0
    outside = [u for u in requests if not u.startswith(base) and not u.startswith("data:")]
    assert outside == []
    assert any(u.endswith(".glb") for u in requests)
    from io import BytesIO

    from PIL import Image

    if os.environ.get("LODBUILDER_SCREENS"):  # keep the picture for a person to look at
        Path(os.environ["LODBUILDER_SCREENS"], "cesium_autzen_tiles.png").write_bytes(png)
    img = np.asarray(Image.open(BytesIO(png)).convert("RGB"), dtype=np.int64)
    lit = np.count_nonzero(img.sum(axis=2) > 60)
    assert lit > 2000, lit  # points drawn on the black background
    print(f"CesiumJS loaded {n_tiles} tiles in {seconds:.1f} s; {lit} lit pixels")
