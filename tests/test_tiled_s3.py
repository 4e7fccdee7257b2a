"""A tiled build whose work files live on an object store (moto's S3 server on 127.0.0.1), so that
Dask workers need no directory shared with the parent (issue 19, item 3): the archive equals,
dataset by dataset, that of a local process-pool build; a build stopped part way resumes from the
objects it left, and a damaged object is done again like a damaged work file."""

from __future__ import annotations

import hashlib
import logging
import os
import uuid

import numpy as np
import pytest

import lodbuilder

pytest.importorskip("moto.server")
pytest.importorskip("s3fs")

TILE_POINTS = 2_500
BUCKET = "lodbuilder-work"


def _scan_points():
    rng = np.random.default_rng(7)
    side = 110
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2).astype(float)
    g = (g + rng.uniform(-0.3, 0.3, g.shape)) / side
    return np.c_[g, 0.08 * np.sin(4 * np.pi * g[:, 0]) * np.cos(4 * np.pi * g[:, 1])]


@pytest.fixture(scope="module")
def s3():
    """moto's S3 server with an empty bucket; fsspec's configuration points s3:// at it (as a
    user's ~/.config/fsspec or FSSPEC_S3_* variables would)."""
    import boto3
    import fsspec.config
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    endpoint = f"http://{host}:{port}"
    client = boto3.client("s3", endpoint_url=endpoint, aws_access_key_id="test", aws_secret_access_key="test",
                          region_name="us-east-1")
    client.create_bucket(Bucket=BUCKET)
    old = fsspec.config.conf.get("s3")
    fsspec.config.conf["s3"] = {"endpoint_url": endpoint, "key": "test", "secret": "test"}
    try:
        yield client
    finally:
        if old is None:
            fsspec.config.conf.pop("s3", None)
        else:
            fsspec.config.conf["s3"] = old
        server.stop()


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    from lodbuilder.io import write_points

    d = tmp_path_factory.mktemp("src")
    return write_points(d / "sheet.npy", _scan_points())


@pytest.fixture(scope="module")
def pooled(tmp_path_factory, source):
    """The same scan built with a local process pool and a local work directory."""
    out = tmp_path_factory.mktemp("pool") / "pool.h5"
    res = lodbuilder.build_archive(source, out, workers=2, _tile_points=TILE_POINTS)
    assert res.scans[0].method == "tiled"
    return out


def _keys(client, prefix):
    got = client.list_objects_v2(Bucket=BUCKET, Prefix=prefix).get("Contents") or []
    return sorted(o["Key"] for o in got)


def _datasets(path):
    """name -> SHA-256 of every dataset's bytes."""
    import h5py

    out = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            out[name] = hashlib.sha256(obj[()].tobytes() if obj.shape != () else repr(obj[()]).encode()).hexdigest()

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    return out


def _same_scan(a, b):
    with lodbuilder.open_archive(a) as x, lodbuilder.open_archive(b) as y:
        va, vb = x.scan("sheet"), y.scan("sheet")
        for field in ("source_index", "radius", "parent"):
            np.testing.assert_array_equal(getattr(va, field)[:], getattr(vb, field)[:])
        np.testing.assert_array_equal(va.points(), vb.points())
        return va.build


def test_dask_workers_without_a_shared_directory_build_the_same_archive(s3, source, pooled, tmp_path):
    """Workers of a LocalCluster run in another directory with another TMPDIR and write their work
    objects to S3; the parent writes nothing beside the archive but the part it downloads."""
    from dask.distributed import Client, LocalCluster

    elsewhere = tmp_path / "workers"
    (elsewhere / "tmp").mkdir(parents=True)
    url = f"s3://{BUCKET}/dask-{uuid.uuid4().hex[:8]}"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                      env={"TMPDIR": str(elsewhere / "tmp")}) as cluster, Client(cluster) as client:
        client.run(os.chdir, str(elsewhere))
        assert set(client.run(os.getcwd).values()) == {str(elsewhere)}
        out = tmp_path / "archive" / "s3.h5"
        out.parent.mkdir()
        res = lodbuilder.build_archive(source, out, scheduler=cluster.scheduler_address, work_dir=url,
                                       _tile_points=TILE_POINTS)
    st = res.scans[0]
    assert st.status == "built" and st.method == "tiled"
    build = _same_scan(out, pooled)
    assert _datasets(out) == _datasets(pooled)
    tasks = build["tasks"]["rows"]
    assert {r[0] for r in tasks} >= {"read_block", "order_tile", "cover_tile", "seam_repair", "merge_band",
                                      "radii_band"}
    assert os.getpid() not in {r[-1] for r in tasks}  # every task ran on a worker
    assert _keys(s3, url[len(f"s3://{BUCKET}/"):]) == []  # the work objects are gone once the scan is in
    assert sorted(p.name for p in (tmp_path / "archive").iterdir()) == ["s3.h5"]
    assert list((elsewhere / "tmp").iterdir()) == []  # the workers' temporaries are gone too


def _stop_after_orderings(monkeypatch, count):
    """Stop the build (as Ctrl-C does) once ``count`` tile orderings are recorded."""
    from lodbuilder.build.tiled import driver as D

    put_json, seen = D.put_json, []

    def put(store, name, doc):
        put_json(store, name, doc)
        if name.startswith("order."):
            seen.append(name)
            if len(seen) == count:
                raise KeyboardInterrupt

    monkeypatch.setattr(D, "put_json", put)


def test_a_stopped_build_resumes_from_the_store_and_redoes_a_damaged_object(s3, source, pooled, tmp_path,
                                                                            monkeypatch, caplog):
    import s3fs

    url = f"s3://{BUCKET}/resume-{uuid.uuid4().hex[:8]}"
    out = tmp_path / "r.h5"
    with monkeypatch.context() as mp:
        _stop_after_orderings(mp, 2)
        with pytest.raises(KeyboardInterrupt):
            lodbuilder.build_archive(source, out, workers=2, work_dir=url, _tile_points=TILE_POINTS)
    prefix = url[len(f"s3://{BUCKET}/"):]
    keys = _keys(s3, prefix)
    (work,) = {k.rsplit("/", 1)[0] for k in keys}
    names = {k.rsplit("/", 1)[1] for k in keys}
    assert {"spill.json", "plan.json", "distribute.json", "decimated.bin", "head.bin"} <= names
    assert not [n for n in names if n.startswith(("raw.", "sample."))]  # (read by the plan and the split alone)
    assert not any(n.endswith(".work") or ".tmp" in n for n in names)
    done_tiles = sorted(n.split(".")[1] for n in names if n.startswith("order.") and n.endswith(".1.json"))
    assert len(done_tiles) == 2
    fs = s3fs.S3FileSystem(**__import__("fsspec").config.conf["s3"])
    for name in ("decimated.bin", f"stream.{done_tiles[0]}.keys"):  # flip bytes of two objects
        data = bytearray(fs.cat_file(f"{BUCKET}/{work}/{name}"))
        for i in np.linspace(0, len(data) - 1, 5).astype(int):
            data[i] ^= 0x5A
        fs.pipe_file(f"{BUCKET}/{work}/{name}", bytes(data))
    with caplog.at_level(logging.WARNING, logger="lodbuilder.build.tiled.sums"):
        res = lodbuilder.build_archive(source, out, workers=2, work_dir=url, _tile_points=TILE_POINTS)
    assert res.scans[0].status == "built"
    build = _same_scan(out, pooled)
    assert _datasets(out) == _datasets(pooled)
    assert build["tiled"]["resumed"]["tiles_ordered_before"] == 1  # the damaged tile was ordered again
    msgs = [r.getMessage() for r in caplog.records]
    store_url = f"s3://{BUCKET}/{work}"
    assert f"tiled build in {store_url}: the plan phase (decimated.bin does not match its checksum); doing it again" in msgs
    assert (f"tiled build in {store_url}: the ordering of tile {int(done_tiles[0]) + 1} (pass 1) "
            f"(stream.{done_tiles[0]}.keys does not match its checksum); doing it again") in msgs
    assert _keys(s3, prefix) == []


KILLED = """
import sys
import lodbuilder
if __name__ == "__main__":
    lodbuilder.build_archive(sys.argv[1], sys.argv[2], workers=2, work_dir=sys.argv[3], _tile_points=int(sys.argv[4]))
"""


@pytest.mark.parametrize("moment", ["tile", "radii"])
def test_kill_9_then_resume_from_the_store(s3, source, pooled, tmp_path, moment):
    """kill -9 of the build (its named moment: after the first tile ordering's marker, after the
    radii's marker), then the same build again resumes from the objects on S3 to the same archive."""
    import subprocess
    import sys

    import fsspec.config

    from lodbuilder.build.tiled.layout import FAULT_ENV

    url = f"s3://{BUCKET}/kill-{moment}-{uuid.uuid4().hex[:8]}"
    out = tmp_path / "k.h5"
    script = tmp_path / "killed.py"
    script.write_text(KILLED)
    conf = fsspec.config.conf["s3"]
    env = dict(os.environ, **{FAULT_ENV: moment, "FSSPEC_S3_ENDPOINT_URL": conf["endpoint_url"],
                              "FSSPEC_S3_KEY": conf["key"], "FSSPEC_S3_SECRET": conf["secret"]})
    r = subprocess.run([sys.executable, str(script), str(source), str(out), url, str(TILE_POINTS)], env=env,
                       capture_output=True, timeout=600)
    assert r.returncode == -9, r.stderr.decode()[-2000:]
    names = {k.rsplit("/", 1)[1] for k in _keys(s3, url[len(f"s3://{BUCKET}/"):])}
    assert ("radii.json" in names) == (moment == "radii") and "plan.json" in names
    res = lodbuilder.build_archive(source, out, workers=2, work_dir=url, _tile_points=TILE_POINTS)
    assert res.scans[0].status == "built"
    build = _same_scan(out, pooled)
    assert _datasets(out) == _datasets(pooled)
    assert build["tiled"]["resumed"]["tiles_ordered_before"] >= 1
    assert _keys(s3, url[len(f"s3://{BUCKET}/"):]) == []


def test_a_work_store_that_cannot_be_written_fails_before_any_work(s3, source, tmp_path):
    from lodbuilder.errors import WorkStoreError

    url = "s3://no-such-bucket-here/w"
    with pytest.raises(WorkStoreError) as e:
        lodbuilder.build_archive(source, tmp_path / "n.h5", workers=1, work_dir=url, _tile_points=TILE_POINTS)
    msg = str(e.value)
    assert msg.startswith("work store s3://no-such-bucket-here/w/n.h5/sheet.") and "does not exist" in msg
    assert msg.endswith("; check the URL, and the credentials and endpoint in fsspec's configuration (AWS_* or "
                        "FSSPEC_S3_* variables, ~/.config/fsspec)")
    assert "\n" not in msg and not (tmp_path / "n.h5").exists()


def test_seam_rounds_on_dask_with_the_work_on_s3_give_the_pool_s_archive(s3, source, tmp_path):
    """The rounds' owners (Dask workers, each tile's state pinned to one) write their tiles' streams
    to the object store: the archive is the one the process pool gives with a local work directory."""
    pool = tmp_path / "pool.h5"
    lodbuilder.build_archive(source, pool, workers=2, _tile_points=TILE_POINTS, seam_rounds=True)
    url = f"s3://{BUCKET}/rounds-{uuid.uuid4().hex[:8]}"
    out = tmp_path / "s3.h5"
    res = lodbuilder.build_archive(source, out, dask_local=2, work_dir=url, _tile_points=TILE_POINTS,
                                   seam_rounds=True)
    assert res.scans[0].status == "built"
    build = _same_scan(out, pool)
    assert build["tiled"]["rounds"]["owners"] == 2
    assert _datasets(out) == _datasets(pool)
    assert _keys(s3, url[len(f"s3://{BUCKET}/"):]) == []
