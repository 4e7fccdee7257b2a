"""Collection builds: the 10 bunny scans on a process pool and on Dask, failures, resume after kill.

The engine runs on decimated copies of the bunny scans (every 8th point, ~4-5k points each) so the
whole file stays fast; the registration itself is checked on the full scans in
test_collection_inputs.py.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from lodbuilder.archive.files import make_own_dir
from lodbuilder.build.inputs import expand_inputs
from lodbuilder.build.runner import parts_dir
from lodbuilder.collection import (
    build_collection,
    collection_level,
    list_scans,
    scan_level,
    total_points,
)
from lodbuilder.errors import BuildError, InputError, LevelBeyondOrderingError
from lodbuilder.io import read_scan, write_points
from lodbuilder.io.pose import apply_pose

STEP = 8


@pytest.fixture(scope="module")
def small_bunny(tmp_path_factory, shared_data) -> Path:
    """Decimated bunny scans beside a copy of bun.conf (same poses). Returns the manifest path."""
    d = tmp_path_factory.mktemp("bunny")
    conf = (shared_data / "bun.conf").read_text()
    for line in conf.splitlines():
        tok = line.split()
        if tok and tok[0] == "bmesh":
            scan = read_scan(shared_data / tok[1])
            write_points(d / tok[1], scan.points[::STEP])
    (d / "bun.conf").write_text(conf)
    return d / "bun.conf"


def _stored_world_points(archive, name):
    with __import__("lodbuilder").open_archive(archive) as arc:
        v = arc.scan(name)
        return v.points()[np.argsort(v.source_index)]


@pytest.mark.data
def test_pool_builds_the_ten_bunny_scans(small_bunny, tmp_path):
    from lodbuilder.archive.validate import validate_archive

    out = tmp_path / "bunny.h5"
    seen = []
    res = build_collection([], out, manifest=small_bunny, workers=2, on_status=seen.append)
    assert res.ok and len(res.by_status("built")) == 10, res.summary()
    assert res.executor == "process pool (2 workers)"
    assert sorted(s.name for s in seen) == sorted(s.name for s in res.scans)
    assert validate_archive(out) == []
    assert not parts_dir(out).exists()
    rows = list_scans(out)
    assert len(rows) == 10
    srcs = {s.name: s for s in expand_inputs([small_bunny])}
    n_total = 0
    for row in rows:
        src = srcs[row["name"]]
        world = apply_pose(read_scan(src.path).points, src.pose)
        n_total += len(world)
        assert row["n_points"] == len(world)
        np.testing.assert_allclose(_stored_world_points(out, row["name"]), world, rtol=0, atol=1e-12)
        assert row["collection_key"] and row["source"] == src.path.name
    assert total_points(out) == n_total
    # one level across every scan, with a scan id; it equals each scan's own level
    lvl = collection_level(out, rho=0.004)
    assert lvl.scans == sorted(srcs) and len(lvl) == sum(lvl.sizes)
    np.testing.assert_array_equal(np.bincount(lvl.attributes["scan_id"]), lvl.sizes)
    one = scan_level(out, "chin", rho=0.004)
    i = lvl.scans.index("chin")
    start = sum(lvl.sizes[:i])
    np.testing.assert_array_equal(lvl.points[start:start + len(one)], one.points)
    assert 10 < len(lvl) < n_total / 2
    # the merged level covers the registered bunny: it sits on bun_zipper within a few mm
    from scipy.spatial import cKDTree

    zipper = read_scan(small_bunny.parent / "bun000.ply")  # any scan: check the levels overlap
    assert np.median(cKDTree(lvl.points).query(apply_pose(zipper.points, srcs["bun000"].pose))[0]) < 0.006

    # a second run skips every scan; a changed pose rebuilds exactly that scan
    again = build_collection([], out, manifest=small_bunny, workers=2)
    assert len(again.by_status("skipped")) == 10
    conf = small_bunny.read_text().replace("bmesh bun090.ply", "bmesh bun090.ply", 1)
    lines = conf.splitlines()
    for j, line in enumerate(lines):
        if line.startswith("bmesh top3.ply"):
            tok = line.split()
            tok[2] = str(float(tok[2]) + 0.01)
            lines[j] = " ".join(tok)
    moved = small_bunny.with_name("moved.conf")
    moved.write_text("\n".join(lines) + "\n")
    # one duplicate-name policy: the same name with another pose is refused without overwrite
    refused = build_collection([], out, manifest=moved, workers=1)
    assert [s.name for s in refused.failed] == ["top3"] and len(refused.by_status("skipped")) == 9
    assert refused.failed[0].error == (
        f"archive {out} already holds scan 'top3' (built from top3.ply with other contents, pose or "
        "parameters); pass --overwrite (overwrite=True) to replace it or choose another --name")
    third = build_collection([], out, manifest=moved, workers=1, overwrite=True)
    assert [s.name for s in third.by_status("built")] == ["top3"]
    assert len(third.by_status("skipped")) == 9


@pytest.mark.data
@pytest.mark.dask
def test_dask_local_cluster_builds_the_bunny(small_bunny, tmp_path):
    out = tmp_path / "dask.h5"
    res = build_collection([], out, manifest=small_bunny, dask_local=2)
    assert res.ok and len(res.by_status("built")) == 10, res.summary()
    assert res.executor == "Dask LocalCluster (2 workers)"
    ref = tmp_path / "pool.h5"
    build_collection([], ref, manifest=small_bunny, workers=1, raise_on_failure=True)
    for name in ("bun000", "top2"):
        with __import__("lodbuilder").open_archive(out) as a, __import__("lodbuilder").open_archive(ref) as b:
            np.testing.assert_array_equal(a.scan(name).points(), b.scan(name).points())
            np.testing.assert_array_equal(a.scan(name).radius, b.scan(name).radius)


def _generated(tmp_path, n=3, npts=800):
    rng = np.random.default_rng(7)
    files = []
    for k in range(n):
        t = rng.random(npts) * 2 * np.pi
        pts = np.stack([np.cos(t), np.sin(t), rng.random(npts) * 0.5], 1) * (k + 1)
        files.append(write_points(tmp_path / f"good{k}.ply", pts,
                                  {"intensity": rng.random(npts).astype(np.float32)}))
    return files


def test_a_corrupted_file_does_not_stop_the_others(tmp_path):
    good = _generated(tmp_path)
    bad = tmp_path / "broken.ply"
    raw = good[0].read_bytes()
    bad.write_bytes(raw[: len(raw) // 2])
    garbage = tmp_path / "garbage.las"
    garbage.write_bytes(b"this is no las file" * 10)
    manifest = tmp_path / "list.lst"
    manifest.write_text("missing.ply\n")
    res = build_collection([tmp_path / "good*.ply", bad, garbage, manifest], tmp_path / "c.h5", workers=2)
    status = {s.name: s for s in res.scans}
    assert {n for n, s in status.items() if s.status == "built"} == {"good0", "good1", "good2"}
    assert not res.ok
    assert "declares 800 vertices" in status["broken"].error
    assert "garbage.las" in status["garbage"].error
    assert "missing.ply" in status["missing"].error
    assert [r["name"] for r in list_scans(tmp_path / "c.h5")] == ["good0", "good1", "good2"]
    with pytest.raises(BuildError, match=r"3 of 6 scan\(s\) failed: .*broken"):
        build_collection([tmp_path / "good*.ply", bad, garbage, manifest], tmp_path / "c.h5", workers=1,
                         raise_on_failure=True)


def test_merged_level_keeps_common_attributes(tmp_path):
    a = write_points(tmp_path / "a.npz", np.random.default_rng(1).random((300, 3)),
                     {"red": np.arange(300, dtype=np.uint16), "w": np.ones(300)})
    b = write_points(tmp_path / "b.npz", np.random.default_rng(2).random((200, 3)) + 2, {"w": np.zeros(200)})
    out = tmp_path / "ab.h5"
    build_collection([a, b], out, workers=1, size=50, raise_on_failure=True)
    with pytest.raises(LevelBeyondOrderingError, match="is ordered only down to covering radius"):
        collection_level(out, rho=0.2)  # finer than 50 points reach (0.27 and 0.22; it claimed any rho before issue 20)
    lvl = collection_level(out, rho=0.6)
    assert set(lvl.attributes) == {"w", "scan_id"}
    w = lvl.attributes["w"]
    np.testing.assert_array_equal(w, (lvl.attributes["scan_id"] == 0).astype(float))
    with pytest.raises(InputError, match="rho must be a finite number > 0"):
        collection_level(out, rho=0)
    # a partial ordering (size=50) still stores every point
    assert total_points(out) == 500


def test_bad_parameters(tmp_path):
    f = _generated(tmp_path, n=1)
    with pytest.raises(InputError, match="size must be a whole number"):
        build_collection(f, tmp_path / "x.h5", size=0)
    with pytest.raises(InputError, match="either a Dask scheduler address or dask_local"):
        build_collection(f, tmp_path / "x.h5", scheduler="tcp://127.0.0.1:1", dask_local=1)
    assert not (tmp_path / "x.h5").exists()


KILL_SCRIPT = textwrap.dedent("""
    import sys
    from lodbuilder.collection import build_collection
    if __name__ == "__main__":
        build_collection([], sys.argv[1], manifest=sys.argv[2], workers=1)
""")


@pytest.mark.data
@pytest.mark.slow
def test_resume_after_a_killed_build(shared_data, tmp_path):
    """The full-size scans (~0.5 s each with one worker) leave time to kill the build mid-way."""
    from lodbuilder import open_archive

    manifest = shared_data / "bun.conf"
    out = tmp_path / "k.h5"
    script = tmp_path / "run.py"
    script.write_text(KILL_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(out), str(manifest)],
                            start_new_session=True, stderr=subprocess.DEVNULL)
    merged: dict[str, tuple] = {}
    try:
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:
            if out.exists():
                try:
                    with open_archive(out) as arc:
                        if len(arc.scans) >= 3:
                            break
                except Exception:
                    pass
            time.sleep(0.02)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the build and its worker processes
        proc.wait()
    with open_archive(out) as arc:
        for n in arc.scans:
            v = arc.scan(n)
            merged[n] = (v.provenance["created_utc"], v.build["worker_pid"])
    assert 3 <= len(merged) < 10, f"kill came too late or too early: {len(merged)} scans merged"
    res = build_collection([], out, manifest=manifest, workers=2)
    assert res.ok
    redone = {s.name for s in res.scans if s.status in ("built", "recovered")}
    assert {s.name for s in res.by_status("skipped")} == set(merged)
    assert not (redone & set(merged))
    assert len(redone) + len(merged) == 10
    with open_archive(out) as arc:
        assert len(arc.scans) == 10
        for n, (created, pid) in merged.items():
            v = arc.scan(n)
            assert (v.provenance["created_utc"], v.build["worker_pid"]) == (created, pid)
    assert not parts_dir(out).exists()


def test_finished_part_of_a_killed_build_is_merged_not_rebuilt(tmp_path):
    from lodbuilder.build.jobs import build_one
    from lodbuilder.build.options import BuildOptions
    from lodbuilder.build.runner import plan_jobs

    files = _generated(tmp_path)
    out = tmp_path / "r.h5"
    build_collection(files[:2], out, workers=1, raise_on_failure=True)
    # what a worker of a killed build leaves behind: a finished part that was never merged
    jobs, recovered, skipped, failed = plan_jobs(expand_inputs(files), out, BuildOptions())
    assert [j.name for j in jobs] == ["good2"] and len(skipped) == 2 and not recovered and not failed
    make_own_dir(parts_dir(out), out.name)  # as the killed build made it, with its marker
    summary = build_one(jobs[0])
    stray = parts_dir(out) / ".good9.h5.tmp-999999999-dead"  # a temp of a killed writer
    stray.write_bytes(b"partial")
    res = build_collection(files, out, workers=1)
    assert [(s.name, s.status) for s in res.scans if s.status != "skipped"] == [("good2", "recovered")]
    with __import__("lodbuilder").open_archive(out) as arc:
        assert arc.scans == ["good0", "good1", "good2"]
        assert arc.scan("good2").build["worker_pid"] == summary["worker_pid"] == os.getpid()
    assert not parts_dir(out).exists()


def test_rebuilt_scan_replaces_the_old_one_without_dead_space(tmp_path):
    files = _generated(tmp_path)
    out = tmp_path / "g.h5"
    build_collection(files, out, workers=1, raise_on_failure=True)
    size0 = out.stat().st_size
    rng = np.random.default_rng(99)
    pts = rng.random((800, 3))
    write_points(files[1], pts, {"intensity": rng.random(800).astype(np.float32)})
    res = build_collection(files, out, workers=1, raise_on_failure=True, overwrite=True)
    assert [s.name for s in res.by_status("built")] == ["good1"]
    with __import__("lodbuilder").open_archive(out) as arc:
        np.testing.assert_array_equal(np.sort(arc.scan("good1").points(), axis=0), np.sort(pts, axis=0))
    assert abs(out.stat().st_size - size0) < 0.05 * size0


def test_interrupt_stops_queued_scans(tmp_path):
    files = _generated(tmp_path, n=5, npts=400)
    out = tmp_path / "i.h5"

    def stop(status):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_collection(files, out, workers=1, on_status=stop)
    with __import__("lodbuilder").open_archive(out) as arc:
        first = set(arc.scans)
    assert 1 <= len(first) < 5  # the first scan is merged; the queued ones never ran
    res = build_collection(files, out, workers=1)
    assert res.ok and {s.name for s in res.by_status("skipped")} == first
    with __import__("lodbuilder").open_archive(out) as arc:
        assert len(arc.scans) == 5


@pytest.mark.dask
def test_existing_dask_scheduler_address(tmp_path):
    import logging

    from dask.distributed import LocalCluster

    files = _generated(tmp_path, n=3, npts=500)
    # a threaded worker in this process: the scheduler-address path, cheaply
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None,
                      silence_logs=logging.WARNING) as cluster:
        res = build_collection(files, tmp_path / "s.h5", scheduler=cluster.scheduler_address)
    assert res.ok and len(res.by_status("built")) == 3
    assert res.executor == f"Dask scheduler {cluster.scheduler_address}"
    assert {s.worker_pid for s in res.scans} == {os.getpid()}


def test_unreachable_dask_scheduler(tmp_path, monkeypatch):
    import lodbuilder.build.runner as runner

    monkeypatch.setattr(runner, "DASK_CONNECT_TIMEOUT", "1s")
    files = _generated(tmp_path, n=1, npts=100)
    with pytest.raises(InputError, match=r"cannot reach Dask scheduler 'tcp://127\.0\.0\.1:9'"):
        build_collection(files, tmp_path / "u.h5", scheduler="tcp://127.0.0.1:9")
