"""Remote reads are bounded (reliability-3 items 12, 14, 15 and 21): a stalled server ends a
command within --timeout (it held one 300 s per request); a URL with a query string (a signed URL)
reads a grown archive's parts (they became ``g.h5?v=1.scans/...``); a redirect to another host is
refused unless --follow-redirects; a server without Range support is read whole with a warning.
Real HTTP on 127.0.0.1 (tests/rangeserver.py)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest
from clirun import in_child

import lodbuilder
from lodbuilder.archive import remote
from lodbuilder.errors import ArchiveError

sys.path.insert(0, str(Path(__file__).parent))
from rangeserver import RangeServer  # noqa: E402
from remote_setup import write_served  # noqa: E402

pytest.importorskip("fsspec")
pytest.importorskip("aiohttp")


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("served")
    write_served(root, 100_000, (20_000, 30_000))
    return root


def cli(*args):
    return in_child(*args, timeout=120)


def test_the_default_timeout_is_30_s():
    assert remote.DEFAULT_TIMEOUT == 30.0


def test_a_stalled_server_ends_within_the_timeout(root):
    with RangeServer(root, delay=20) as srv:
        url = srv.url("one.h5")
        t = time.monotonic()
        r = cli("info", url, "--timeout", "0.5")
        took = time.monotonic() - t
    assert r.returncode == 2, r.stderr
    assert r.stderr.splitlines() == [
        f"lodbuilder info: error: archive {url}: the server did not answer within 0.5 s; try "
        "again later or give more time with --timeout SECONDS"], r.stderr
    assert took < 15  # (python start-up and imports included; the server would take 20 s)
    with RangeServer(root, delay=20) as srv:
        t = time.monotonic()
        with pytest.raises(ArchiveError, match="did not answer within 0.5 s"):
            lodbuilder.open_archive(srv.url("one.h5"), storage_options={"timeout": 0.5})
        assert time.monotonic() - t < 10


def test_bad_timeouts_are_refused():
    r = cli("info", "http://127.0.0.1:9/a.h5", "--timeout", "0")
    assert r.returncode == 2
    assert r.stderr.splitlines() == [
        "lodbuilder info: error: argument --timeout: must be a number of seconds above 0, got '0' "
        "(see 'lodbuilder info --help')"]


def test_a_signed_url_reads_a_grown_archive(root):
    with RangeServer(root) as srv:
        url = srv.url("many.h5") + "?X-Sig=ab%2Fcd&v=1"
        with lodbuilder.open_archive(url) as arc:
            assert arc.scan("s1").level(size=100).size == 100
        parts = [p for _, p, *_ in srv.log if p.startswith("/many.h5.scans/")]
        assert parts and all(p.endswith("?X-Sig=ab%2Fcd&v=1") for p in parts), srv.log


def test_a_redirect_to_another_host_is_refused(root):
    with RangeServer(root) as srv:
        other = srv.url("one.h5", host="localhost")
        srv.redirects = {"/moved.h5": other, "/here.h5": "/one.h5"}
        url = srv.url("moved.h5")
        r = cli("info", url)
        assert r.returncode == 2
        assert r.stderr.splitlines() == [
            f"lodbuilder info: error: archive {url}: the server redirects to another host "
            f"({other}); pass --follow-redirects to follow it, or use that URL"], r.stderr
        assert not any(p == "/one.h5" for _, p, *_ in srv.log)
        r = cli("info", url, "--follow-redirects")
        assert r.returncode == 0, r.stderr
        assert "big" in r.stdout
        r = cli("info", srv.url("here.h5"))  # the same host: followed
        assert r.returncode == 0, r.stderr


def test_a_server_without_ranges_warns(root, tmp_path):
    with RangeServer(root, honour_range=False) as srv:
        url = srv.url("one.h5")
        r = cli("slice", url, "--size", "100", "-o", tmp_path / "x.ply")
    assert r.returncode == 0, r.stderr
    size = (root / "one.h5").stat().st_size
    assert r.stderr.splitlines() == [
        f"WARNING lodbuilder.archive.remote: {url}: the server ignores range requests, so the "
        f"whole file was read ({size / 1e6:.1f} MB); serve it with range support (e.g. "
        "RangeHTTPServer, nginx, S3) to read levels in a few small requests"], r.stderr
