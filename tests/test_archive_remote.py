"""Archives read over HTTP and S3 from real servers on 127.0.0.1 (a Range-honouring HTTP server
and moto's S3 server), with exact request counts."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive import layout as L
from lodbuilder.archive.writer import update_archive
from lodbuilder.errors import ArchiveError, NotAnArchiveError, ScanFileError

sys.path.insert(0, str(Path(__file__).parent))
from rangeserver import RangeServer  # noqa: E402
from remote_setup import MotoS3, level_bytes, page_size, write_served  # noqa: E402
from remote_setup import synthetic_record as synthetic  # noqa: E402

pytest.importorskip("fsspec")
pytest.importorskip("aiohttp")


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A directory with a 200k-point single-file archive and a three-scan archive with parts,
    served over HTTP."""
    root = tmp_path_factory.mktemp("served")
    write_served(root, 200_000, (50_000, 300_000, 30_000))
    with RangeServer(root) as srv:
        yield root, srv


def test_a_10k_level_over_http_is_one_head_and_two_gets(served):
    root, srv = served
    with lodbuilder.open_archive(root / "one.h5") as arc:
        local = arc.scan().level(size=10_000)
    srv.reset()
    with lodbuilder.open_archive(srv.url("one.h5")) as arc:
        lev = arc.scan().level(size=10_000)
    np.testing.assert_array_equal(lev.points, local.points)
    for key in local.attributes:
        np.testing.assert_array_equal(lev.attributes[key], local.attributes[key])
    np.testing.assert_array_equal(lev.source_index, local.source_index)
    assert (srv.count("HEAD"), srv.count("GET")) == (1, 2), srv.log
    assert len(srv.log) == 3
    budget = 2 * level_bytes(root / "one.h5", "big", 10_000) + page_size(root / "one.h5")
    assert srv.sent() <= budget, (srv.sent(), budget)
    # a rho level: the radius index is in the metadata, the radius block comes with the level
    with lodbuilder.open_archive(root / "one.h5") as arc:
        rho = float(arc.scan().radius[5000])
        local = arc.scan().level(rho=rho)
    srv.reset()
    with lodbuilder.open_archive(srv.url("one.h5")) as arc:
        lev = arc.scan().level(rho=rho)
    assert lev.size == local.size and np.array_equal(lev.points, local.points)
    assert (srv.count("HEAD"), srv.count("GET")) == (1, 2), srv.log


@pytest.mark.parametrize("scan,gets", [("s1", 2), ("s0", 3)])
def test_a_scan_of_an_archive_with_parts_over_http(served, scan, gets):
    root, srv = served
    with lodbuilder.open_archive(root / "many.h5") as arc:
        local = arc.scan(scan).level(size=10_000)
        part = {r.name: r.part for r in arc.rows}[scan]
    srv.reset()
    with lodbuilder.open_archive(srv.url("many.h5")) as arc:
        assert arc.scans == ["s0", "s1", "s2"]
        lev = arc.scan(scan).level(size=10_000)
    np.testing.assert_array_equal(lev.points, local.points)
    # the index (one HEAD, one GET for the whole small file), then the part: its size is in the
    # index (no HEAD), its metadata in the first GET, the level in one GET; a part under 8 MB
    # (small pages, s0: 50k points) has the metadata written last at its end: one GET more
    # (the index's HEAD and first GET go out together, in either order)
    assert sorted((m, p) for m, p, *_ in srv.log[:2]) == [("GET", "/many.h5"), ("HEAD", "/many.h5")]
    assert [(m, p) for m, p, *_ in srv.log[2:]] == [("GET", f"/many.h5.scans/{part}")] * gets, srv.log
    assert srv.log[2][2] == "bytes=0-65535"


def test_whole_scan_reads_and_info_over_http(served):
    root, srv = served
    with lodbuilder.open_archive(root / "one.h5") as arc:
        v = arc.scan()
        local = (v.points(), v.radius, v.parent, v.attributes())
    srv.reset()
    with lodbuilder.open_archive(srv.url("one.h5")) as arc:
        v = arc.scan()
        remote = (v.points(), v.radius, v.parent, v.attributes())
        assert arc.nbytes == (root / "one.h5").stat().st_size
    for a, b in zip(local[:3], remote[:3], strict=True):
        np.testing.assert_array_equal(a, b)
    assert local[3].keys() == remote[3].keys()
    # never more than the file, in one pass
    assert srv.sent() <= (root / "one.h5").stat().st_size
    out = subprocess.run(
        [sys.executable, "-m", "lodbuilder.cli.main", "info", "--json", srv.url("many.h5")],
        capture_output=True, text=True, timeout=120,
    )
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout)
    assert [s["name"] for s in info["scans"]] == ["s0", "s1", "s2"]
    assert info["file_size"] == (root / "many.h5").stat().st_size + sum(
        p.stat().st_size for p in (root / "many.h5.scans").iterdir()
    )


def test_slice_cli_over_http_equals_local(served, tmp_path):
    root, srv = served
    outs = []
    for src in (str(root / "one.h5"), srv.url("one.h5")):
        out = tmp_path / f"l{len(outs)}.npy"
        r = subprocess.run(
            [sys.executable, "-m", "lodbuilder.cli.main", "slice", src, "--size", "10000", "-o", str(out)],
            capture_output=True, text=True, timeout=120,
        )
        assert r.returncode == 0, r.stderr
        outs.append(np.load(out))
    assert outs[0].dtype == outs[1].dtype and np.array_equal(outs[0], outs[1])


@pytest.mark.viewer
def test_view_screenshot_over_http(served, tmp_path):
    pytest.importorskip("pyvista")
    root, srv = served
    out = tmp_path / "v.png"
    srv.reset()
    r = subprocess.run(
        [sys.executable, "-m", "lodbuilder.cli.main", "view", srv.url("many.h5"), "--scan", "s2",
         "--screenshot", str(out), "--window-size", "300", "200"],
        capture_output=True, text=True, timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert out.stat().st_size > 1000
    assert all(p.startswith("/many.h5") for _, p, *_ in srv.log)


def test_remote_errors_are_one_line(served, tmp_path):
    root, srv = served
    with pytest.raises(ScanFileError) as err:
        lodbuilder.open_archive(srv.url("missing.h5"))
    assert str(err.value) == (f"archive {srv.url('missing.h5')} does not exist (the server has no "
                              "such file); check the URL")
    (root / "text.h5").write_bytes(b"not an archive at all\n" * 100)
    with pytest.raises(NotAnArchiveError, match=r"text.h5 is not an lodbuilder archive \(not an HDF5 file\)"):
        lodbuilder.open_archive(srv.url("text.h5"))
    # building into a URL: archives are read-only remotely
    r = subprocess.run(
        [sys.executable, "-m", "lodbuilder.cli.main", "build", str(tmp_path / "x.ply"), "-o",
         srv.url("new.h5")],
        capture_output=True, text=True, timeout=120,
    )
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"lodbuilder build: error: output {srv.url('new.h5')} is a URL; archives are read-only "
        "over HTTP/S3: build into a local file and upload it (the file and its .scans directory)"
    ]
    with pytest.raises(ArchiveError, match="is a URL; archives are read-only over HTTP/S3"):
        update_archive(srv.url("new.h5"), [synthetic(100, "x")])


def test_a_crafted_index_is_refused_before_any_request(served, tmp_path):
    import h5py

    from lodbuilder.archive.scanwriter import write_index

    root, srv = served
    crafted = root / "crafted.h5"
    crafted.write_bytes((root / "many.h5").read_bytes())
    with lodbuilder.open_archive(crafted) as arc:
        rows = arc.rows
    from dataclasses import replace

    with h5py.File(crafted, "r+") as f:
        write_index(f, [replace(r, part="../one.h5") if r.name == "s1" else r for r in rows])
    srv.reset()
    with lodbuilder.open_archive(srv.url("crafted.h5")) as arc:
        with pytest.raises(lodbuilder.errors.CorruptArchiveError, match="refusing to follow it"):
            arc.scan("s1")
    assert {p for _, p, *_ in srv.log} == {"/crafted.h5"}


def test_a_server_that_ignores_ranges(served):
    root, _ = served
    with RangeServer(root, honour_range=False) as srv:
        with lodbuilder.open_archive(srv.url("one.h5")) as arc:
            lev = arc.scan().level(size=1000)
        assert lev.size == 1000
        assert srv.count("GET") == 1  # the whole file once, kept


# ----------------------------------------------------------------------------------------- S3


@pytest.fixture(scope="module")
def s3(served, tmp_path_factory):
    """moto's S3 server on 127.0.0.1 holding the served archives; its request recorder counts."""
    pytest.importorskip("s3fs")
    pytest.importorskip("moto.server")
    root, _ = served
    files = [root / "one.h5", root / "many.h5", *(root / "many.h5.scans").iterdir()]
    moto = MotoS3(root, files, "lodbuilder-test", tmp_path_factory.mktemp("moto") / "recording")
    yield moto.options, moto, moto.endpoint
    moto.stop()


def test_a_10k_level_from_s3_in_three_requests(served, s3):
    root, _ = served
    opts, rec, _ = s3
    with lodbuilder.open_archive(root / "one.h5") as arc:
        local = arc.scan().level(size=10_000)
    rec.start()
    with lodbuilder.open_archive("s3://lodbuilder-test/one.h5", storage_options=opts) as arc:
        lev = arc.scan().level(size=10_000)
    log = rec.recorded()
    np.testing.assert_array_equal(lev.points, local.points)
    assert sorted(r["method"] for r in log) == ["GET", "GET", "HEAD"], [(r["method"], r["url"]) for r in log]
    ranges = [r["headers"].get("Range") for r in log if r["method"] == "GET"]
    assert ranges[0] == "bytes=0-65535"
    fetched = sum(int(b) - int(a) + 1 for a, b in (x[6:].split("-") for x in ranges))
    assert fetched <= 2 * level_bytes(root / "one.h5", "big", 10_000) + page_size(root / "one.h5")


def test_slice_cli_from_s3_with_the_endpoint_in_the_environment(served, s3, tmp_path):
    import os

    root, _ = served
    opts, rec, endpoint = s3
    env = dict(os.environ, AWS_ENDPOINT_URL=endpoint, AWS_ACCESS_KEY_ID="test",
               AWS_SECRET_ACCESS_KEY="test", AWS_DEFAULT_REGION="us-east-1")
    out = tmp_path / "s.npy"
    r = subprocess.run(
        [sys.executable, "-m", "lodbuilder.cli.main", "slice", "s3://lodbuilder-test/many.h5",
         "--scan", "s2", "--size", "5000", "-o", str(out)],
        capture_output=True, text=True, timeout=120, env=env,
    )
    assert r.returncode == 0, r.stderr
    with lodbuilder.open_archive(root / "many.h5") as arc:
        local = arc.scan("s2").level(size=5000)
    got = np.load(out)
    np.testing.assert_array_equal(np.stack([got["x"], got["y"], got["z"]], 1), local.points)


@pytest.mark.parametrize(
    "blocked,url,message",
    [
        ("fsspec", "https://example.invalid/a.h5",
         "reading archives over HTTP/S3 needs fsspec: pip install 'lodbuilder[remote]'"),
        ("s3fs", "s3://bucket/a.h5", "reading s3:// archives needs s3fs: pip install 'lodbuilder[s3]'"),
        ("aiohttp", "https://example.invalid/a.h5",
         "reading https:// archives needs aiohttp: pip install 'lodbuilder[remote]'"),
    ],
)
def test_missing_extra_is_one_line(blocked, url, message):
    code = (
        f"import sys; sys.modules[{blocked!r}] = None\n"
        "import lodbuilder\n"
        "from lodbuilder.cli.main import main\n"
        f"sys.exit(main(['info', {url!r}]))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [f"lodbuilder info: error: {message}"]


def test_layout_constants_are_sane():
    assert L.ROW_GROUP_MIN <= 10_000  # a 10k level reads at most two row groups
    assert L.page_size(1) == L.PAGE_MIN and L.page_size(10**12, 10**9) == L.PAGE_MAX
    assert L.page_size(10**9, 100_000) == 1 << 18  # chunks pack two to a page
