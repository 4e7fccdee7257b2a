"""``lodbuilder export ARCHIVE -o OUT.html``: one self-contained page, checked in headless
Chromium (Debian's package, driven by playwright with the system executable): it renders, raises
no error, makes no request, draws the coarse prefix first and colours by RGB, radius, importance.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from lodbuilder.cli.main import main

CHROMIUM = os.environ.get("LODBUILDER_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
#: the flags of a headless Chromium on a machine with no GPU and no network (SwiftShader WebGL)
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


@pytest.fixture(scope="module")
def demo_archive(small_archive):
    """A 3,000-point coloured sheet with a curvature importance map."""
    return small_archive(3000, seed=3, importance="curvature")


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"no chromium at {CHROMIUM} (apt-get install -y chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()


class Page:
    """A page opened from a file, with every request, page error and console error recorded;
    any request that is not the page's own file is aborted (and recorded)."""

    def __init__(self, browser, path: Path, size=(800, 600)):
        self.requests: list[str] = []
        self.errors: list[str] = []
        self.console: list[str] = []
        self.own = path.resolve().as_uri()
        self.page = browser.new_page(viewport={"width": size[0], "height": size[1]})
        self.page.on("request", lambda r: self.requests.append(r.url))
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.on(
            "console", lambda m: self.console.append(m.text) if m.type == "error" else None
        )
        self.page.route(
            "**/*",
            lambda route: route.continue_() if route.request.url == self.own else route.abort(),
        )
        self.page.goto(self.own)
        self.page.wait_for_timeout(50)
        for _ in range(600):  # the page sets LOD.state.ready after its last chunk and frame
            if self.state().get("ready"):
                break
            self.page.wait_for_timeout(50)

    def state(self) -> dict:
        # (a function, not a string: the page's CSP forbids eval, which string predicates use)
        return json.loads(self.page.evaluate("() => JSON.stringify(window.LOD ? LOD.state : {})"))

    def image(self) -> np.ndarray:
        from io import BytesIO

        from PIL import Image

        return np.asarray(Image.open(BytesIO(self.page.screenshot())).convert("RGB"))

    def close(self) -> None:
        self.page.close()


def js_number(v: float) -> str:
    """A number as the page prints it (its fmt function)."""
    if abs(v) >= 1e4 or (abs(v) < 1e-2 and v != 0):
        return re.sub(r"e([+-])0*(\d)", r"e\1\2", f"{v:.2e}")
    return repr(float(f"{v:.3g}")).removesuffix(".0")


def drawn_share(img: np.ndarray) -> float:
    """Share of non-white pixels in the middle of the picture (where the scan is drawn)."""
    h, w, _ = img.shape
    mid = img[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4]
    return float(np.mean(np.any(mid < 245, axis=2)))


def test_export_web_page_renders_offline(demo_archive, browser, tmp_path, capsys):
    out = tmp_path / "demo.html"
    assert main(["export", str(demo_archive), "-o", str(out)]) == 0
    assert capsys.readouterr().out.startswith(
        f"wrote 3,000 of 3,000 points of scan 'demo' to {out} ("
    )
    text = out.read_text()
    # nothing is fetched: no address in the page, a CSP that forbids every request
    assert "default-src 'none'" in text
    assert not re.search(r"(src|href)=\"(?!data:)", text) and "http://" not in text
    page = Page(browser, out)
    try:
        state = page.state()
        assert state["ready"] and state["error"] is None
        assert state["loaded"] == state["drawn"] == 3000
        assert page.errors == [] and page.console == []
        assert page.requests == [page.own]  # the page itself, nothing else
        img = page.image()
        assert drawn_share(img) > 0.15
        assert len(np.unique(img.reshape(-1, 3), axis=0)) > 100  # RGB colours, not one flat colour
        info = page.page.inner_text("#info")
        assert info == "demo: 3,000 of 3,000 points; CRS unknown, coordinates in scan units"
    finally:
        page.close()


def test_colour_modes_and_legend(demo_archive, browser, tmp_path):
    out = tmp_path / "demo.html"
    assert main(["export", str(demo_archive), "-o", str(out), "--size", "2000"]) == 0
    page = Page(browser, out)
    try:
        p = page.page
        options = p.eval_on_selector_all("#mode option", "els => els.map(e => e.textContent)")
        assert options == ["RGB", "radius", "elevation", "importance: curvature", "rank"]
        assert not p.is_visible("#legend")  # RGB has no scale
        rgb = page.image()
        shots = {}
        for value, label in (("s0", "radius"), ("s2", "importance: curvature"), ("rank", "rank")):
            p.select_option("#mode", value)
            p.wait_for_timeout(100)
            assert page.state()["mode"] == value
            assert p.is_visible("#legend")
            shots[label] = page.image()
            assert np.abs(shots[label].astype(int) - rgb).mean() > 1.0
        p.select_option("#mode", "s0")
        assert p.inner_text("#legendTitle") == "radius (scan units, log)"
        p.select_option("#mode", "s1")
        assert p.inner_text("#legendTitle") == "elevation z (scan units)"
        p.select_option("#mode", "s2")
        assert p.inner_text("#legendTitle") == "importance: curvature"
        assert np.abs(shots["radius"].astype(int) - shots["rank"]).mean() > 0.5
        assert page.errors == [] and page.requests == [page.own]
    finally:
        page.close()


def test_level_slider_shows_the_prefixes(demo_archive, browser, tmp_path):
    import lodbuilder

    out = tmp_path / "demo.html"
    assert main(["export", str(demo_archive), "-o", str(out)]) == 0
    with lodbuilder.open_archive(demo_archive) as arc:
        radius = np.asarray(arc.scan().radius)
    page = Page(browser, out)
    try:
        p = page.page
        full = page.image()
        assert "3,000 of 3,000 points (100 %), rho = 0 (every point)" in p.inner_text("#levelText")
        assert p.inner_text("#status") == "3,000 of 3,000 points drawn"
        p.eval_on_selector("#level", "el => { el.value = '0'; el.dispatchEvent(new Event('input')); }")
        p.wait_for_timeout(100)
        assert page.state()["drawn"] == 1
        # one point is no level of 'every point' (it read 'rho = 0 (every point)'), and the
        # corner counter follows the level (it kept the full count)
        assert p.inner_text("#levelText").startswith(f" 1 of 3,000 points (0.0333 %), rho = {js_number(float(radius[1]))} ")
        assert p.inner_text("#status") == "1 of 3,000 points drawn"
        # a middle stop: the prefix of k points and its covering radius radius[k]
        n_stops = int(p.get_attribute("#level", "max")) + 1
        p.eval_on_selector(
            "#level",
            f"el => {{ el.value = '{n_stops // 2}'; el.dispatchEvent(new Event('input')); }}",
        )
        p.wait_for_timeout(100)
        k = page.state()["drawn"]
        assert 1 < k < 3000
        text = p.inner_text("#levelText")
        assert text.startswith(f" {k:,} of 3,000 points")
        assert f"rho = {js_number(float(radius[k]))} scan units" in text
        # radius colours follow the level: the scale starts at its rho (it was page-wide)
        p.select_option("#mode", "s0")
        p.wait_for_timeout(100)
        assert p.inner_text("#legendLo") == js_number(float(radius[k]))
        by_level = page.image()
        p.eval_on_selector("#level", "el => { el.value = '0'; el.dispatchEvent(new Event('input')); }")
        p.eval_on_selector(
            "#level",
            f"el => {{ el.value = '{n_stops // 2}'; el.dispatchEvent(new Event('input')); }}",
        )
        p.wait_for_timeout(100)
        assert np.abs(page.image().astype(int) - by_level).mean() < 0.5  # the same level, same colours
        p.select_option("#mode", "rgb")
        coarse = page.image()
        assert drawn_share(coarse) < drawn_share(full) or np.abs(coarse.astype(int) - full).mean() > 1
    finally:
        page.close()


class SlowServer:
    """An HTTP server on 127.0.0.1 that sends a file in two parts: the bytes up to ``cut``, then,
    after ``pause`` seconds, the rest (a large page arriving over a slow link)."""

    def __init__(self, path: Path, cut: int, pause: float = 1.0):
        import http.server
        import threading
        import time

        data = path.read_bytes()

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):
                self.send_response(200)
                self.send_header("Content-Type", "text/html; charset=utf-8")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data[:cut])
                self.wfile.flush()
                time.sleep(pause)
                self.wfile.write(data[cut:])

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/{path.name}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


def test_large_page_draws_coarse_points_first(browser, tmp_path, monkeypatch):
    """The data comes in chunks of growing size, each a longer prefix of the farthest-point
    order, each followed by the call that draws it: while the rest of a large page is still
    arriving, the browser shows the coarse prefix it has."""
    from lodbuilder.export import web

    monkeypatch.setattr(web, "FIRST_CHUNK", 64)
    rng = np.random.default_rng(0)
    pts = rng.random((20000, 3)) * [1, 1, 0.1]
    radius = 1.0 / np.sqrt(np.arange(1, 20001))  # any non-increasing radii
    out = tmp_path / "big.html"
    page_info = web.write_web_page(out, pts, radius, 0.001, n_total=40000)
    assert page_info.chunks == 6  # 64, 256, 1024, 4096, 16384, 20000
    text = out.read_text()
    blocks = re.findall(r'<script type="application/octet-stream" id="c(\d)">([^<]*)</script>', text)
    sizes = [len(base64.b64decode(b)) // 7 for _, b in blocks]  # x, y, z: 6 bytes; radius: 1
    assert sizes == [64, 192, 768, 3072, 12288, 3616]
    # the first three chunks arrive, then the rest a second later
    cut = text.index("<script>LOD.chunk(2);</script>") + len("<script>LOD.chunk(2);</script>")
    server = SlowServer(out, len(text[:cut].encode()))
    try:
        page = browser.new_page(viewport={"width": 800, "height": 600})
        seen = []
        page.on("request", lambda r: seen.append(r.url))
        page.goto(server.url, wait_until="commit")
        page.wait_for_timeout(600)  # the pause: the first 1,024 points are there
        early = json.loads(page.evaluate("() => JSON.stringify(window.LOD ? LOD.state : {})"))
        assert early["loaded"] == 1024 and early["drawn"] == 1024 and not early["ready"]
        for _ in range(200):
            state = json.loads(page.evaluate("() => JSON.stringify(LOD.state)"))
            if state["ready"]:
                break
            page.wait_for_timeout(50)
        assert state["loaded"] == state["drawn"] == 20000
        assert state["history"][0] <= 1024 and state["history"] == sorted(state["history"])
        assert page.inner_text("#status") == "20,000 of 20,000 points drawn (the level's prefix: coarse to fine)"
        assert seen == [server.url]
        page.close()
    finally:
        server.close()


def test_positions_round_trip_within_the_quantisation(tmp_path):
    from lodbuilder.export import web

    rng = np.random.default_rng(1)
    pts = rng.random((500, 3)) * [100.0, 50.0, 2.0] + [4.5e5, 5.0e6, 10.0]
    q, lo, span = web._quantise(pts)
    back = lo + q.astype(float) / 65535.0 * span + (pts.min(0) + pts.max(0)) / 2
    assert np.abs(back - pts).max() <= span.max() / 131070 * 1.0001


def test_export_errors(demo_archive, tmp_path, capsys):
    arc = str(demo_archive)
    cases = [
        (
            ["-o", str(tmp_path / "x.ply")],
            f"-o {tmp_path / 'x.ply'}: name it OUT.copc.laz (COPC), OUT.html (web page) or DIR/tileset.json (3D Tiles); "
            "for .ply, .las, .laz, .csv, .npy... use lodbuilder slice",
        ),
        (
            ["-o", str(tmp_path / "x.html"), "--size", "2000", "--max-points", "1000"],
            "the level has 2,000 points, more than a web page holds (1,000); ask for a coarser "
            "level (--rho, --size) or raise --max-points",
        ),
        (["-o", str(tmp_path / "x.html"), "--max-points", "0"], "--max-points must be at least 1, got 0"),
        (["-o", arc.replace(".h5", ".html"), "--size", "0"], "size must be between 1 and the number of points (3000), got 0"),
        (["-o", str(tmp_path / "no" / "x.html")], f"-o {tmp_path / 'no' / 'x.html'}: output directory {tmp_path / 'no'} does not exist; create it first"),
    ]
    for args, message in cases:
        assert main(["export", arc] + args) == 2
        assert capsys.readouterr().err == f"lodbuilder export: error: {message}\n"
    assert list(tmp_path.iterdir()) == []
    assert main(["export", arc, "-o", str(tmp_path / "x.html"), "--max-points", "1000"]) == 0
    assert "wrote 1,000 of 3,000 points" in capsys.readouterr().out
    assert main(["export", arc, "-o", arc]) == 2
    assert capsys.readouterr().err == f"lodbuilder export: error: -o {arc} is the input archive; choose another output\n"


def test_both_exporters_check_a_level_the_same_way(tmp_path):
    """One set of checks (lodbuilder.export.check_level_output) for the COPC file and the page."""
    pytest.importorskip("copclib")
    from lodbuilder.errors import InputError
    from lodbuilder.export.copc import write_copc
    from lodbuilder.export.web import write_web_page

    pts, rad = np.zeros((4, 3)), np.ones(4)
    for write, kind, suffix, good, bad in (
        (lambda o, p, r: write_copc(o, p, {}, r, 0.0), "COPC output", ".copc.laz", "a.copc.laz", "a.laz"),
        (lambda o, p, r: write_web_page(o, p, r, 0.0), "web page", ".html", "a.HTM", "a.htm.gz"),
    ):
        cases = [
            ((tmp_path / bad, pts, rad), f"{kind} {tmp_path / bad} must end in {suffix}"),
            ((tmp_path / good, np.zeros((0, 3)), np.ones(0)), "points must have shape (K, 3) with K >= 1, got (0, 3)"),
            ((tmp_path / good, np.zeros((4, 2)), rad), "points must have shape (K, 3) with K >= 1, got (4, 2)"),
            ((tmp_path / good, pts, np.ones(3)), "radius must have shape (4,) like the points, got (3,)"),
        ]
        for args, message in cases:
            with pytest.raises(InputError) as info:
                write(*args)
            assert str(info.value) == message
        assert list(tmp_path.iterdir()) == []
        write(tmp_path / good, pts, rad)
        assert [p.name for p in tmp_path.iterdir()] == [good]
        (tmp_path / good).unlink()


def test_web_page_names_the_crs_and_units(shared_data, tmp_path):
    """autzen_trim.laz carries a CRS in feet: the page's header line and legends say so."""
    pytest.importorskip("pyproj")
    import lodbuilder

    arc = tmp_path / "autzen.h5"
    lodbuilder.build_archive(shared_data / "autzen_trim.laz", arc, name="autzen")
    out = tmp_path / "autzen.html"
    assert main(["export", str(arc), "--size", "5000", "-o", str(out), "-q"]) == 0
    header = json.loads(
        re.search(r'<script id="lod-header" type="application/json">(.*?)</script>',
                  out.read_text()).group(1)
    )
    assert header["info"] == (
        "autzen: 5,000 of 110,000 points; CRS NAD_1983_HARN_Lambert_Conformal_Conic, "
        "coordinates in foot"
    )
    assert header["unit"] == "foot"
    assert header["scalars"][0]["title"] == "radius (foot, log)"
    assert header["rgb"] and header["n"] == 5000 and header["n_total"] == 110000


def test_survey_colours_and_the_coarsest_level(shared_data, browser, tmp_path):
    """An airborne tile: elevation, intensity and classification (ASPRS names in a legend of
    swatches, drawn in their colours); the coarsest stop (the first point) says its covering radius:
    the second piece enters at its Euclidean distance (it read 'rho = 0 (every point)')."""
    import lodbuilder

    arc = tmp_path / "autzen.h5"
    lodbuilder.build_archive(shared_data / "autzen_trim.laz", arc, name="autzen")
    with lodbuilder.open_archive(arc) as a:
        r1 = float(np.asarray(a.scan().radius)[1])
        assert np.isfinite(r1)  # only the first point has radius inf
    out = tmp_path / "a.html"
    assert main(["export", str(arc), "--size", "20000", "-o", str(out), "-q"]) == 0
    page = Page(browser, out)
    try:
        p = page.page
        options = p.eval_on_selector_all("#mode option", "els => els.map(e => e.textContent)")
        assert options == ["RGB", "radius", "elevation", "intensity", "classification", "rank"]
        p.select_option("#mode", "c0")
        p.wait_for_timeout(150)
        assert p.inner_text("#legendTitle") == "classification"
        assert p.inner_text("#legendList").split("\n") == ["1 unassigned", "2 ground"]
        img = page.image()
        ground = np.all(np.abs(img.astype(int) - [166, 118, 64]) <= 6, axis=2)
        assert ground.sum() > 500  # ground points (and the legend swatch) in ASPRS brown
        p.eval_on_selector("#level", "el => { el.value = '0'; el.dispatchEvent(new Event('input')); }")
        p.wait_for_timeout(100)
        assert p.inner_text("#levelText") == f" 1 of 110,000 points (0.000909 %), rho = {float(f'{r1:.3g}'):g} foot"
        assert page.errors == [] and page.requests == [page.own]
    finally:
        page.close()
