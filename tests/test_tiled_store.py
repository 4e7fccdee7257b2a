"""The work store of a tiled build (lodbuilder.build.tiled.store): a local directory and an fsspec
object store behave alike (whole objects, ranged reads, listing, deletion), and the resume rules of
lodbuilder.build.tiled.sums (a marker trusted only when it and every object it lists check out)
hold on both."""

from __future__ import annotations

import logging
import pickle
import uuid

import numpy as np
import pytest

from lodbuilder.build.tiled import sums
from lodbuilder.build.tiled.store import FsspecStore, LocalStore, as_store
from lodbuilder.build.tiled.urls import check_work_url
from lodbuilder.build.tiled.workdir import MAX_RUN_ROWS, RUN_BYTES, blocks, gather, read_runs
from lodbuilder.errors import InputError

pytest.importorskip("fsspec")


@pytest.fixture(params=["local", "memory"])
def store(request, tmp_path):
    if request.param == "local":
        return LocalStore(tmp_path)
    return FsspecStore(f"memory://lodbuilder-test-{uuid.uuid4().hex}/work")


def test_an_object_is_written_whole_with_its_size_and_checksum(store):
    a = np.arange(1000, dtype="<i8")
    with store.writer("a.i8") as w:
        w.write(a[:400])
        assert store.size("a.i8") is None  # not there until committed
        w.write(a[400:])
    assert w.sum == sums.sum_array(a) == store.sum("a.i8")
    assert store.size("a.i8") == 8000
    np.testing.assert_array_equal(store.read_array("a.i8", "<i8"), a)
    np.testing.assert_array_equal(store.read_array("a.i8", "<i8", 10, 5), a[10:15])
    assert store.get("a.i8") == a.tobytes()
    assert store.read_ranges("a.i8", [8, 80], [16, 96]) == [a[1:2].tobytes(), a[10:12].tobytes()]
    out = store.read_array("a.i8", "<i8")
    out[0] = 5  # a writable array


def test_a_failed_writer_leaves_no_object(store):
    with pytest.raises(RuntimeError), store.writer("b.bin") as w:
        w.write(b"half")
        raise RuntimeError("task died")
    assert store.size("b.bin") is None
    assert store.names() == []


def test_local_work_files_are_renamed_into_place_without_the_fsyncs_of_an_archive(tmp_path, monkeypatch):
    """A work file is atomic but not flushed (its checksum stands in for a power cut: see
    lodbuilder._atomic); every other file lodbuilder replaces still gets both fsyncs."""
    import os

    from lodbuilder._atomic import write_bytes

    synced = []
    monkeypatch.setattr(os, "fsync", synced.append)
    store = LocalStore(tmp_path)
    store.put("a.bin", np.arange(3))
    with store.writer("b.bin") as w:
        w.write(b"abc")
    sums.put_json(store, "c.json", {"files": {}})
    assert synced == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.bin", "c.json"]  # (no temporaries)
    assert sums.get_json(store, "c.json") == {"files": {}} and store.get("b.bin") == b"abc"
    write_bytes(tmp_path / "d.txt", b"x")
    assert len(synced) == 2  # (the file, then its directory)


def test_put_list_delete_and_read_past_the_end(store):
    assert store.put("x.bin", b"12345678") == [8, sums.sum_array(np.frombuffer(b"12345678", np.uint8))[1]]
    store.put("y.bin", np.zeros(3))
    assert store.names() == ["x.bin", "y.bin"]
    assert store.names("y") == ["y.bin"]
    with pytest.raises(OSError, match="truncated"):
        store.read_array("x.bin", "<i8", 0, 2)
    store.delete("x.bin")
    store.delete("x.bin")  # (nothing to do)
    assert store.names() == ["y.bin"]
    store.clear()
    assert store.names() == []


def test_gather_and_blocks_read_rows_of_an_object(store):
    rng = np.random.default_rng(1)
    a = rng.integers(0, 1 << 40, 50_000).astype("<i8")
    store.put("r.i8", a)
    idx = rng.choice(a.shape[0], 3000, replace=False)
    np.testing.assert_array_equal(gather((store, "r.i8"), "<i8", (), idx), a[idx])
    xyz = rng.random((700, 3))
    store.put("p.f8", xyz)
    got = np.concatenate([b.reshape(-1, 3) for _, b in blocks((store, "p.f8"), "<f8", None, 3 * 128)])
    np.testing.assert_array_equal(got, xyz)


def _runs_row_by_row(srt, gap, width):
    """The reference of read_runs: the row-by-row loop it replaced."""
    runs, i, m = [], 0, srt.shape[0]
    while i < m:
        j = i + 1
        while (j < m and srt[j] - srt[j - 1] <= gap and j - i < MAX_RUN_ROWS
               and (srt[j] - srt[i]) * width < RUN_BYTES):
            j += 1
        runs.append((i, j))
        i = j
    return runs


@pytest.mark.parametrize("seed", range(4))
def test_read_runs_split_sorted_rows_as_the_row_by_row_loop(seed):
    rng = np.random.default_rng(seed)
    for n, top, gap, width in [(0, 10, 4, 8), (1, 10, 0, 8), (5000, 6000, 0, 8), (5000, 10**6, 300, 24),
                               (200_000, 250_000, 3, 8), (200_000, 10**7, 5000, 1 << 12), (3000, 3000, 10**9, 8)]:
        srt = np.sort(rng.integers(0, top, n))
        got = read_runs(srt, gap, width)
        assert got == _runs_row_by_row(srt, gap, width)
        if n:
            assert got[0][0] == 0 and got[-1][1] == n and all(a[1] == b[0] for a, b in zip(got[:-1], got[1:], strict=True))


def test_the_task_log_collects_lines_from_every_worker(store):
    store.log("tasks.1.jsonl", '{"a": 1}')
    store.log("tasks.2.jsonl", '{"a": 2}')
    store.log("tasks.1.jsonl", '{"a": 3}')
    assert sorted(store.log_lines("tasks.")) == ['{"a": 1}', '{"a": 2}', '{"a": 3}']


@pytest.mark.parametrize("how", ["flip", "truncate", "missing", "marker"])
def test_a_damaged_object_makes_its_piece_be_done_again(store, how, caplog):
    a = np.arange(5000, dtype="<f8")
    files = {"raw.0.xyz": store.put("raw.0.xyz", a)}
    sums.mark(store, "read.0", {"n": 5000, "files": files})
    assert sums.done(store, "read.0") == {"n": 5000, "files": files}
    if how == "flip":
        raw = bytearray(store.get("raw.0.xyz"))
        raw[1234] ^= 0x5A
        store.put("raw.0.xyz", bytes(raw))
        problem = "raw.0.xyz does not match its checksum"
    elif how == "truncate":
        store.put("raw.0.xyz", store.get("raw.0.xyz")[:400])
        problem = "raw.0.xyz has 400 bytes, 40000 were written"
    elif how == "missing":
        store.delete("raw.0.xyz")
        problem = "raw.0.xyz is missing"
    else:
        text = store.get("read.0.json").replace(b"5000", b"5001")
        store.put("read.0.json", text)
        problem = "its record is damaged"
    with caplog.at_level(logging.WARNING, logger="lodbuilder.build.tiled.sums"):
        assert sums.done(store, "read.0") is None
    assert [r.getMessage() for r in caplog.records] == [
        f"tiled build in {store.url}: the read.0 phase ({problem}); doing it again"]
    assert store.size("read.0.json") is None  # the marker is gone: the piece is done again


def test_a_store_travels_to_workers_by_pickle(tmp_path):
    local = LocalStore(tmp_path)
    assert pickle.loads(pickle.dumps(local)) == local
    remote = FsspecStore("memory://lodbuilder-pickle/work")
    remote.put("a", b"1")
    back = pickle.loads(pickle.dumps(remote))
    assert back == remote and back.get("a") == b"1"  # (the memory file system is this process's)


def test_as_store_and_the_work_url_check(tmp_path):
    assert as_store(tmp_path) == LocalStore(tmp_path)
    assert as_store(str(tmp_path)) == LocalStore(tmp_path)
    assert as_store(f"file://{tmp_path}") == LocalStore(tmp_path)
    assert isinstance(as_store("memory://bucket/x"), FsspecStore)
    assert check_work_url(None) is None
    assert check_work_url("s3://bucket/prefix") == "s3://bucket/prefix"
    with pytest.raises(InputError) as e:
        check_work_url("nosuchfs://bucket/prefix")
    assert str(e.value) == ("work_dir 'nosuchfs://bucket/prefix': fsspec knows no file system 'nosuchfs'; give a "
                            "directory or a URL like s3://BUCKET/PREFIX")
    with pytest.raises(InputError) as e:
        check_work_url("  ")
    assert str(e.value) == "work_dir must be a directory or an fsspec URL like s3://BUCKET/PREFIX, got '  '"


def test_the_cli_refuses_a_work_dir_fsspec_does_not_know(tmp_path, capsys):
    from lodbuilder.cli.main import main

    src = tmp_path / "p.xyz"
    src.write_text("0 0 0\n1 0 0\n0 1 0\n")
    rc = main(["build", str(src), "-o", str(tmp_path / "a.h5"), "--work-dir", "nosuchfs://b/p"])
    assert rc != 0
    assert capsys.readouterr().err.strip().endswith(
        "work_dir 'nosuchfs://b/p': fsspec knows no file system 'nosuchfs'; give a directory or a URL like "
        "s3://BUCKET/PREFIX")
    assert not (tmp_path / "a.h5").exists()


def test_a_local_work_dir_holds_the_work_files_of_a_stopped_build(tmp_path, monkeypatch):
    """--work-dir DIR: the work files go to DIR/ARCHIVE/PART.work (not beside the archive), a
    stopped build resumes from them, and they are gone once the scan is in."""
    import lodbuilder
    from lodbuilder.build.tiled import driver as D

    rng = np.random.default_rng(3)
    xy = rng.random((6000, 2))
    scan = lodbuilder.Scan(points=np.c_[xy, 0.05 * np.sin(6 * xy[:, 0])], name="s")
    with monkeypatch.context() as mp:
        mp.setattr(D, "_merge", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
        with pytest.raises(KeyboardInterrupt):
            lodbuilder.build_archive(scan, tmp_path / "a.h5", work_dir=tmp_path / "w", _tile_points=2000)
    (work,) = (tmp_path / "w" / "a.h5").glob("s.*.work")
    assert (work / "distribute.json").is_file()
    assert not list((tmp_path / ".a.h5.parts").glob("*.work"))
    res = lodbuilder.build_archive(scan, tmp_path / "a.h5", work_dir=tmp_path / "w", _tile_points=2000)
    assert res.scans[0].status == "built"
    assert not work.exists()
    with lodbuilder.open_archive(tmp_path / "a.h5") as arc:
        tiled = arc.scan("s").build["tiled"]
        assert tiled["resumed"]["tiles_ordered_before"] == tiled["tiles"] > 1  # every tile taken from DIR


def test_zipped_work_files_read_back_in_blocks(tmp_path):
    """The raw blocks' attributes and the buckets are written compressed (workdir.Zipped) and read
    back whole or block by block, whatever the blocks they were written in."""
    import numpy as np

    from lodbuilder.build.tiled.store import LocalStore
    from lodbuilder.build.tiled.workdir import Zipped, unzipped, zipped_blocks
    from lodbuilder.errors import InputError

    store = LocalStore(tmp_path)
    dt = np.dtype([("a", "<u2"), ("b", "<f8")])
    rec = np.zeros(10_000, dt)
    rec["a"], rec["b"] = np.arange(10_000) % 7, np.arange(10_000) // 16
    z = Zipped(store.writer("x.attr"))
    for a in range(0, 10_000, 3_000):
        z.write(rec[a:a + 3_000])
    size, _ = z.commit()
    assert size < rec.nbytes / 2
    np.testing.assert_array_equal(unzipped(store.get("x.attr"), dt, "x.attr"), rec)
    for rows in (1, 777, 10_000, 20_000):
        got = list(zipped_blocks((store, "x.attr"), dt, 10_000, rows))
        assert [lo for lo, _ in got] == list(range(0, 10_000, rows))
        np.testing.assert_array_equal(np.concatenate([r for _, r in got]), rec)
    raw = store.get("x.attr")
    store.put("x.attr", raw[: len(raw) // 2])
    with pytest.raises(OSError, match="x.attr: truncated"):
        list(zipped_blocks((store, "x.attr"), dt, 10_000, 4_000))
    with pytest.raises(InputError, match=r"^x.attr is not a file of records \("):
        unzipped(b"not zstandard", dt, "x.attr")
