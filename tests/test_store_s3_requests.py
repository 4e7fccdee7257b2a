"""How many requests the work store makes on S3 (moto's server on 127.0.0.1, its requests counted):
each costs a few milliseconds of CPU in the task and in the server, and a tiled build makes
thousands (issue 19: Dask with its work files on S3 within 1.2 x of the process pool)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

pytest.importorskip("moto.server")
pytest.importorskip("s3fs")

BUCKET = "lodbuilder-requests"


class Counter:
    """A WSGI wrapper around moto's application: the requests as (method, has a Range header)."""

    def __init__(self, app):
        self.app, self.seen, self.lock = app, [], threading.Lock()

    def __call__(self, environ, start_response):
        with self.lock:
            self.seen.append((environ["REQUEST_METHOD"], "HTTP_RANGE" in environ))
        return self.app(environ, start_response)

    def take(self):
        with self.lock:
            out, self.seen = self.seen, []
        return out


@pytest.fixture(scope="module")
def server():
    import boto3
    from moto.moto_server import threaded_moto_server as tms
    from moto.server import ThreadedMotoServer

    made = []
    plain = tms.DomainDispatcherApplication

    def counted(*a, **k):
        made.append(Counter(plain(*a, **k)))
        return made[-1]

    tms.DomainDispatcherApplication = counted
    srv = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    try:
        srv.start()
    finally:
        tms.DomainDispatcherApplication = plain
    host, port = srv.get_host_and_port()
    endpoint = f"http://{host}:{port}"
    boto3.client("s3", endpoint_url=endpoint, aws_access_key_id="test", aws_secret_access_key="test",
                 region_name="us-east-1").create_bucket(Bucket=BUCKET)
    try:
        yield endpoint, made[0]
    finally:
        srv.stop()


@pytest.fixture
def store(server):
    import s3fs

    from lodbuilder.build.tiled.store import FsspecStore

    endpoint, counter = server
    fs = s3fs.S3FileSystem(key="test", secret="test", endpoint_url=endpoint, skip_instance_cache=True)
    st = FsspecStore(f"s3://{BUCKET}/run", fs=fs)
    st.put("a.bin", np.arange(1000, dtype=np.int64))
    counter.take()
    return st, counter


def test_a_whole_object_is_one_get(store):
    st, counter = store
    assert st.get("a.bin") == np.arange(1000, dtype=np.int64).tobytes()
    assert counter.take() == [("GET", False)]  # (s3fs asked its size first: HEAD, GET)


def test_a_whole_array_is_one_get(store):
    st, counter = store
    np.testing.assert_array_equal(st.read_array("a.bin", np.int64), np.arange(1000))
    assert counter.take() == [("GET", False)]  # (was HEAD, ranged GET)
    np.testing.assert_array_equal(st.read_array("a.bin", np.int32), np.arange(1000, dtype=np.int64).view(np.int32))
    counter.take()
    np.testing.assert_array_equal(st.read_array("a.bin", np.int64, 10, 5), np.arange(10, 15))
    assert counter.take() == [("GET", True)]


def test_a_missing_marker_is_one_request(store):
    st, counter = store
    assert st.marker("missing.json") is None
    assert counter.take() == [("GET", False)]  # (was HEAD, then a listing of the prefix)
    with pytest.raises(FileNotFoundError, match=r"missing\.bin is missing"):
        st.read_array("missing.bin", np.int64)
    with pytest.raises(FileNotFoundError):
        st.get("missing.bin")


def test_a_process_task_log_is_one_object(store, monkeypatch):
    from lodbuilder.build.tiled import store as S

    st, counter = store
    st.log("tasks.7.jsonl", '{"a": 1}')
    st.log("tasks.7.jsonl", '{"a": 2}')
    assert counter.take() == [("PUT", False), ("PUT", False)]  # (each line there when its task ends)
    assert st.log_lines("tasks.7") == ['{"a": 1}', '{"a": 2}']
    assert counter.take() == [("GET", False), ("GET", False)]  # the listing, one object (was one a line)
    monkeypatch.setattr(S, "LOG_LINES", 3)  # a long-lived worker starts another object now and then
    for i in range(3, 8):
        st.log("tasks.7.jsonl", f'{{"a": {i}}}')
    assert len(st.names("tasks.7.jsonl.")) == 3
    assert sorted(st.log_lines("tasks.7")) == sorted(f'{{"a": {i}}}' for i in range(1, 8))


def test_pruned_work_files_go_in_one_request(store):
    from lodbuilder.build.tiled.sums import prune

    st, counter = store
    for n in ("bucket.0.1.bin", "bucket.0.2.bin", "bucket.0.3.bin"):
        st.put(n, b"x")
    counter.take()
    prune(st, ["bucket.0.1.bin", "bucket.0.2.bin", "bucket.0.3.bin", "bucket.0.9.bin"])  # (one missing)
    assert counter.take() == [("POST", False)]  # (was a DELETE each)
    assert st.names("bucket.0.") == []


def test_a_later_build_logs_afresh(store):
    """A worker process that logged in one build (the same store URL, claimed again) does not write
    that build's lines into the next build's log."""
    st, _ = store
    st.claim()
    st.log("tasks.8.jsonl", "first build")
    st.clear()
    st.claim()
    st.log("tasks.8.jsonl", "second build")
    assert st.log_lines("tasks.8") == ["second build"]


def test_a_framed_files_index_is_one_suffix_read(store, monkeypatch):
    """A banded file's index and length are its last bytes: one GET of a suffix range (was a HEAD for
    the size, then two ranged GETs); an index longer than the first read takes a second one."""
    from lodbuilder.build.tiled import workdir as WD

    st, counter = store
    rec = np.dtype([("rank", "<i8"), ("v", "<f8")])
    recs = np.zeros(5000, rec)
    recs["rank"] = np.arange(5000)
    recs["v"] = np.arange(5000) * 0.5
    WD.put_banded(st, "b.bin", recs, 100)  # (50 frames)
    counter.take()
    got, before = WD.banded_slice(st, "b.bin", rec, 1234, 1240)
    np.testing.assert_array_equal(got, recs[1234:1240])
    assert before == recs[1233]
    assert counter.take() == [("GET", True), ("GET", True)]  # the index, then the frames
    monkeypatch.setattr(WD, "INDEX_READ", 64)  # an index longer than the first read: one more
    got, _ = WD.banded_slice(st, "b.bin", rec, 0, 3)
    np.testing.assert_array_equal(got, recs[:3])
    assert counter.take() == [("GET", True), ("GET", True), ("GET", True)]


def test_the_tail_of_an_object(store, tmp_path):
    """The last bytes of an object, all of it when it is shorter; the same from a local store."""
    from lodbuilder.build.tiled import workdir as WD
    from lodbuilder.build.tiled.store import LocalStore

    st, _ = store
    local = LocalStore(tmp_path)
    data = np.arange(1000, dtype=np.int64).tobytes()
    local.put("a.bin", data)
    for s in (st, local):
        assert s.tail("a.bin", 16) == data[-16:]
        assert s.tail("a.bin", 10 ** 6) == data
        with pytest.raises(FileNotFoundError, match=r"nothing\.bin is missing"):
            s.tail("nothing.bin", 8)
        s.put("short.bin", b"abc")  # not a framed file: too short, or an index longer than the file
        with pytest.raises(OSError, match=r"short\.bin: not a framed work file"):
            WD.banded_slice(s, "short.bin", np.dtype("<i8"), 0, 1)
        s.put("long.bin", np.array([7], "<i8").tobytes())
        with pytest.raises(OSError, match=r"long\.bin: not a framed work file"):
            WD.banded_slice(s, "long.bin", np.dtype("<i8"), 0, 1)
