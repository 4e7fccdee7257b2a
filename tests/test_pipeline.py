"""One build pipeline for one scan and many (issue 10.1) and the reliability findings on builds
(8: workers outlive a killed build; 12: singular/non-rigid poses; 13: messages)."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import lodbuilder
from lodbuilder.cli.main import main
from lodbuilder.collection import build_collection, read_manifest
from lodbuilder.errors import InputError
from lodbuilder.io import Scan, write_points


def _clouds(tmp_path, n=3, npts=600, seed=11):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        t = rng.random(npts) * 2 * np.pi
        pts = np.stack([np.cos(t), np.sin(t), rng.random(npts)], 1) + k
        out.append(write_points(tmp_path / f"s{k}.ply", pts))
    return out


def test_build_archive_returns_what_it_built(tmp_path):
    (f,) = _clouds(tmp_path, 1)
    out = tmp_path / "a.h5"
    res = lodbuilder.build_archive(f, out)
    assert isinstance(res, lodbuilder.BuildResult)
    (st,) = res.scans
    assert (st.name, st.status, st.n_points, st.n_ordered, st.encoding, st.method) == (
        "s0", "built", 600, 600, "float64", "in-memory")
    assert res.executor == "this process" and res.archive == out.resolve() and res.archive_scans == 1
    assert st.seconds > 0 and set(st.phases) == {"read", "order", "write"}
    with lodbuilder.open_archive(out) as arc:
        v = arc.scan("s0")
        assert v.n_points == 600 and v.build["collection_key"] and v.build["method"] == "in-memory"
        assert v.provenance["source_name"] == "s0.ply" and v.provenance["source_sha256"]
    # the same scan again: skipped, the same resume key as a collection build uses
    again = lodbuilder.build_archive(f, out)
    assert [s.status for s in again.scans] == ["skipped"] and again.archive_scans == 1
    many = build_collection(_clouds(tmp_path, 3), out, workers=1)
    assert [(s.name, s.status) for s in many.scans] == [("s0", "skipped"), ("s1", "built"), ("s2", "built")]
    assert many.archive_scans == 3 and many.executor == "process pool (1 worker)"
    doc = many.to_json()
    assert doc["built"] == 2 and doc["skipped"] == 1 and doc["n_points"] == 1200
    assert [s["name"] for s in doc["scans"]] == ["s0", "s1", "s2"]


def test_in_memory_scans_take_the_same_path(tmp_path):
    rng = np.random.default_rng(3)
    a = Scan(points=rng.random((300, 3)), name="a")
    b = Scan(points=rng.random((200, 3)), name="b")
    out = tmp_path / "m.h5"
    res = lodbuilder.build_archive([a, b], out)
    assert [(s.name, s.status, s.n_points) for s in res.scans] == [("a", "built", 300), ("b", "built", 200)]
    assert a.name == "a"  # the caller's Scan is not renamed
    assert [s.status for s in lodbuilder.build_archive([a, b], out).scans] == ["skipped", "skipped"]
    with pytest.raises(InputError, match="in-memory scans are built in this process"):
        lodbuilder.build_archive(a, out, workers=2)


@pytest.mark.parametrize("fn", [lodbuilder.build_archive, build_collection])
def test_unknown_keywords_name_the_valid_ones(tmp_path, fn):
    (f,) = _clouds(tmp_path, 1)
    with pytest.raises(InputError) as exc:
        fn(f, tmp_path / "a.h5", wokers=2)
    text = str(exc.value)
    assert text.startswith(f"{fn.__name__}() got an unknown keyword argument 'wokers' (did you mean 'workers'?); "
                           "its keywords are: ")
    for key in ("workers", "manifest", "overwrite", "importance", "adaptive", "density_floor"):
        assert key in text
    assert not (tmp_path / "a.h5").exists()


def test_cli_json_and_output_rules(tmp_path, capsys):
    files = _clouds(tmp_path, 2)
    out = tmp_path / "c.h5"
    assert main(["build", *map(str, files), "-o", str(out), "--workers", "1", "--json", "--no-progress"]) == 0
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert doc["built"] == 2 and doc["archive_scans"] == 2 and [s["name"] for s in doc["scans"]] == ["s0", "s1"]
    assert doc["scans"][0]["n_points"] == 600 and doc["executor"] == "process pool (1 worker)"
    for target, msg in [
        ("-", "-o -: an archive cannot be written to stdout (it is an HDF5 file, written beside its final name "
              "and renamed); give a file name ending in .h5"),
        (str(tmp_path / "x.ply"), f"-o {tmp_path / 'x.ply'} must end in .h5 or .hdf5"),
    ]:
        assert main(["build", str(files[0]), "-o", target]) == 2
        assert capsys.readouterr().err == f"lodbuilder build: error: {msg}\n"
    assert main(["build", str(files[0]), "-o", str(tmp_path / "ok.HDF5"), "--no-progress"]) == 0
    assert "added scan 's0' (600 points, float64 coordinates)" in capsys.readouterr().out


@pytest.mark.parametrize("value", ["0", "-3"])
def test_workers_below_one_are_refused_alike(tmp_path, capsys, value):
    """Finding 13: --workers 0 was accepted (silently: all cores) while -3 was refused."""
    files = _clouds(tmp_path, 2)
    assert main(["build", *map(str, files), "-o", str(tmp_path / "w.h5"), "--workers", value]) == 2
    assert capsys.readouterr().err == (
        f"lodbuilder build: error: workers must be a whole number of worker processes >= 1, got {value}\n")
    assert not (tmp_path / "w.h5").exists()


def test_zero_quaternion_names_the_manifest_line(tmp_path):
    """Finding 13: the zero-quaternion message named no manifest line."""
    m = tmp_path / "m.conf"
    m.write_text("camera 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 0\n")
    with pytest.raises(InputError) as exc:
        read_manifest(m)
    assert str(exc.value) == (f"manifest {m} line 2: quaternion (0 0 0 0) has zero or non-finite length; "
                              "give a unit quaternion qx qy qz qw")


@pytest.mark.parametrize("matrix", [
    "1 0 0 0  0 1 0 0  0 0 0 0  0 0 0 1",      # flattens z
    "0 0 0 5  0 0 0 6  0 0 0 7  0 0 0 1",      # every point onto (5, 6, 7)
    "1 2 3 0  2 4 6 0  0 0 1 0  0 0 0 1",      # rank 2
])
def test_singular_pose_is_refused(tmp_path, matrix):
    """Finding 12: a singular pose collapsed every point; it is refused with its line."""
    (f,) = _clouds(tmp_path, 1)
    m = tmp_path / "m.lst"
    m.write_text(f"# poses\n{f.name} {matrix}\n")
    with pytest.raises(InputError) as exc:
        lodbuilder.build_archive(m, tmp_path / "p.h5")
    assert str(exc.value) == (f"manifest {m} line 2: the 4x4 pose is singular (its 3x3 part has rank < 3) and "
                              "would collapse the scan; give an invertible pose (a rotation and a translation)")
    assert not (tmp_path / "p.h5").exists()


def test_non_rigid_pose_is_applied_and_said(tmp_path, caplog):
    (f,) = _clouds(tmp_path, 1)
    m = tmp_path / "m.lst"
    m.write_text(f"{f.name} 2 0 0 1  0 1 0 0  0 0 1 0  0 0 0 1\nother.ply 0 -1 0 0  1 0 0 0  0 0 1 0  0 0 0 1\n")
    (tmp_path / "other.ply").write_bytes(f.read_bytes())
    out = tmp_path / "p.h5"
    with caplog.at_level(logging.WARNING, logger="lodbuilder"):
        res = lodbuilder.build_archive(m, out, workers=1)
    assert res.ok
    assert [r.getMessage() for r in caplog.records] == [
        f"manifest {m} line 1: the pose is not rigid: it scales or shears the scan (scale factors 2 1 1); "
        "it is applied as given"]
    with lodbuilder.open_archive(out) as arc:
        assert arc.scan("s0").build["pose_kind"] == "affine"
        assert arc.scan("other").build["pose_kind"] == "rigid"
        x = arc.scan("s0").points()[:, 0]
    assert x.max() > 2.5  # scaled by 2 and moved by 1: applied as given


def test_a_manifest_that_builds_nothing_says_so(tmp_path, capsys):
    """Finding 13: '1 failed scan(s) into X.h5' was printed though no X.h5 existed."""
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nend_header\n1\n")
    (tmp_path / "bad2.ply").write_bytes(bad.read_bytes())
    one = tmp_path / "one.lst"
    one.write_text("bad.ply\n")
    out = tmp_path / "x.h5"
    assert main(["build", "--manifest", str(one), "-o", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lodbuilder build: error: ") and len(err.splitlines()) == 1 and "x.h5" not in err
    two = tmp_path / "two.lst"
    two.write_text("bad.ply\nbad2.ply\n")
    assert main(["build", "--manifest", str(two), "-o", str(out), "--no-progress", "--workers", "1"]) == 1
    captured = capsys.readouterr()
    assert captured.out == f"2 failed scan(s); no archive written ({out} does not exist)\n"
    assert not out.exists()


SERVER_SCRIPT = textwrap.dedent("""
    import sys
    from multiprocessing import forkserver
    from lodbuilder.build import runner
    seen = []
    plan = runner.plan_jobs
    def spy(*a, **k):
        seen.append(forkserver._forkserver._forkserver_pid is not None)
        return plan(*a, **k)
    runner.plan_jobs = spy
    if __name__ == "__main__":
        from lodbuilder.collection import build_collection
        build_collection(sys.argv[2:], sys.argv[1], workers=1)
        print(seen)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the forkserver start method")
def test_the_pool_server_starts_before_the_plan(tmp_path):
    """The forkserver that forks the pool's workers (its imports and kernels: about 1 CPU-s) starts
    when the build starts, while the parent reads the inputs' headers, not at the first task."""
    files = _clouds(tmp_path, 2)
    script = tmp_path / "run.py"
    script.write_text(SERVER_SCRIPT)
    out = subprocess.run([sys.executable, str(script), str(tmp_path / "s.h5"), *map(str, files)],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[-1] == "[True]"


KILL_SCRIPT = textwrap.dedent("""
    import sys
    from lodbuilder.collection import build_collection
    if __name__ == "__main__":
        build_collection(sys.argv[2:], sys.argv[1], workers=2)
""")


def _session_pids(sid: int) -> list[int]:
    pids = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":  # field 6 of stat: session id
            pids.append(int(entry))
    return pids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signals are Linux-only")
def test_workers_die_with_a_killed_build(tmp_path):
    """Finding 8: after kill -9 of a build, its pool workers and the forkserver lived on."""
    files = _clouds(tmp_path, 2, npts=1_000_000)  # each keeps a worker busy for seconds
    script = tmp_path / "run.py"
    script.write_text(KILL_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path / "k.h5"), *map(str, files)],
                            start_new_session=True, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 60
        while time.time() < deadline and len(_session_pids(proc.pid)) < 4:  # build, server, 2 workers
            time.sleep(0.05)
        assert len(_session_pids(proc.pid)) >= 4, "the workers never started"
        time.sleep(1.0)  # the workers are inside their scans now
        os.kill(proc.pid, signal.SIGKILL)  # the build alone, as a user's kill -9 would
        proc.wait()
        deadline = time.time() + 3  # a worker would otherwise finish its scan first (seconds)
        while time.time() < deadline and _session_pids(proc.pid):
            time.sleep(0.05)
        assert _session_pids(proc.pid) == []
    finally:
        for pid in _session_pids(proc.pid):
            os.kill(pid, signal.SIGKILL)
