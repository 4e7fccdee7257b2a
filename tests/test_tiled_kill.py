"""kill -9 of a tiled build while it orders tiles, merges them and appends the scan; then the same
build again: nothing lost (the archive's other scan, every point), nothing built twice (finished
tiles and finished parts are reused)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive.validate import validate_archive
from lodbuilder.io import Scan, write_points

TILE_POINTS = 12_000

SCRIPT = textwrap.dedent("""
    import sys
    import lodbuilder
    if __name__ == "__main__":
        passes = int(sys.argv[4]) if len(sys.argv) > 4 else None
        lodbuilder.build_archive(sys.argv[1], sys.argv[2], workers=2, _tile_points=int(sys.argv[3]),
                                 _tile_passes=passes)
""")


def _sheet(n, seed=0):
    rng = np.random.default_rng(seed)
    side = int(np.sqrt(n))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2).astype(float)
    g = (g + rng.uniform(-0.3, 0.3, g.shape)) / side
    return np.c_[g, 0.08 * np.sin(4 * np.pi * g[:, 0]) * np.cos(4 * np.pi * g[:, 1])]


def _work_dir(archive):
    parts = archive.with_name(f".{archive.name}.parts")
    return next(parts.glob("*.work"), None) if parts.is_dir() else None


def _when(archive, moment):
    """True once the build has reached ``moment``."""
    w = _work_dir(archive)
    parts = archive.with_name(f".{archive.name}.parts")
    if moment == "append":
        return parts.is_dir() and any(p.suffix == ".h5" for p in parts.iterdir())
    if w is None or not (w / "distribute.json").exists() or (w / "merge.json").exists():
        return False
    n_tiles = len(json.loads((w / "plan.json").read_text())["tiles"])
    done = len(list(w.glob("order.*.json")))
    if moment == "tiling":
        return 2 <= done < n_tiles
    return done == n_tiles  # merging


@pytest.mark.parametrize("moment", ["tiling", "merge", "append"])
def test_kill_and_resume(tmp_path, moment):
    pts = _sheet(160_000)
    src = write_points(tmp_path / "sheet.npy", pts)
    archive = tmp_path / "site.h5"
    lodbuilder.build_archive(Scan(points=np.random.default_rng(1).random((500, 3)), name="other"), archive)
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(src), str(archive), str(TILE_POINTS)],
                            start_new_session=True, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None and not _when(archive, moment):
            time.sleep(0.005)
        assert proc.poll() is None, f"the build finished before the kill at {moment}"
        os.kill(proc.pid, signal.SIGKILL)  # the build alone: its workers die with it (finding 8)
        proc.wait()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    time.sleep(0.5)  # the workers' parent-death signals
    w = _work_dir(archive)
    ordered = len(list(w.glob("order.*.json"))) if w is not None else 0
    with lodbuilder.open_archive(archive) as arc:  # nothing lost: the previous archive is whole
        before = set(arc.scans)
        assert "other" in before
    res = lodbuilder.build_archive(src, archive, workers=2, _tile_points=TILE_POINTS)
    (st,) = res.scans
    assert st.status in {"built", "recovered", "skipped"}
    if moment == "append":
        assert st.status in {"recovered", "skipped"}  # the written part is reused, never rebuilt
    else:
        assert st.status == "built"
    assert validate_archive(archive) == []
    with lodbuilder.open_archive(archive) as arc:
        assert arc.scans == ["other", "sheet"]
        v = arc.scan("sheet")
        assert np.array_equal(np.sort(v.source_index[:]), np.arange(len(pts)))
        np.testing.assert_array_equal(v.points(), pts[v.source_index[:]])
        if st.status == "built":
            resumed = v.build["tiled"]["resumed"]
            assert resumed["tiles_ordered_before"] >= ordered  # finished tiles are not ordered again
            if moment == "merge":
                assert resumed["tiles_ordered_before"] == v.build["tiled"]["tiles"]
    assert not archive.with_name(f".{archive.name}.parts").exists()


def test_a_kill_in_the_second_pass_resumes_to_the_same_order(tmp_path):
    """Two passes: killed once some tiles finished their second ordering, the resumed build orders
    only what was left and stores exactly the order of a build that was never interrupted (each
    ordering reads the face files of the passes it depends on, which stay in the work directory)."""
    pts = _sheet(90_000, seed=2)
    src = write_points(tmp_path / "sheet.npy", pts)
    clean = tmp_path / "clean.h5"
    lodbuilder.build_archive(src, clean, workers=2, _tile_points=9_000, _tile_passes=2)
    archive = tmp_path / "site.h5"
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(src), str(archive), "9000", "2"],
                            start_new_session=True, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None:
            w = _work_dir(archive)
            if w is not None and (w / "plan.json").exists():
                n_tiles = len(json.loads((w / "plan.json").read_text())["tiles"])
                if 1 <= len(list(w.glob("order.*.2.json"))) < n_tiles:
                    break
            time.sleep(0.005)
        assert proc.poll() is None, "the build finished before the kill in its second pass"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    time.sleep(0.5)
    w = _work_dir(archive)
    done = len(list(w.glob("order.*.json")))
    second = len(list(w.glob("order.*.2.json")))
    res = lodbuilder.build_archive(src, archive, workers=2, _tile_points=9_000, _tile_passes=2)
    assert res.scans[0].status == "built"
    with lodbuilder.open_archive(archive) as a, lodbuilder.open_archive(clean) as b:
        va, vb = a.scan("sheet"), b.scan("sheet")
        # a tile's second ordering may start before every first one is done (it waits only for its
        # neighbours): count the second orderings, not the total against the tile count
        assert va.build["tiled"]["resumed"]["tiles_ordered_before"] == done and second >= 1
        np.testing.assert_array_equal(va.source_index[:], vb.source_index[:])
        np.testing.assert_array_equal(va.radius[:], vb.radius[:])


@pytest.mark.slow
def test_named_moments_kill_the_build_and_the_resume_gives_the_same_order(tmp_path):
    """The work directory's named moments (lodbuilder.build.tiled.layout.moment): a build that kills
    itself right after a phase's marker (or the first tile ordering's) is resumed to exactly the
    order, radii and parents of an uninterrupted build."""
    from lodbuilder.build.tiled import layout as WL

    pts = _sheet(40_000, seed=3)
    src = write_points(tmp_path / "sheet.npy", pts)
    ref = tmp_path / "ref.h5"
    lodbuilder.build_archive(src, ref, workers=2, _tile_points=TILE_POINTS)
    with lodbuilder.open_archive(ref) as arc:
        want = arc.scan().source_index[:], arc.scan().radius[:], arc.scan().parent[:]
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    for moment in ("inputs", "read", "spill", "split", "coarse", "tile", "order", "links", "seams", "merged", "merge", "ranks",
                   "rank", "band", "radii", "permute", "buckets", "chunks"):
        archive = tmp_path / f"{moment}.h5"
        env = dict(os.environ, **{WL.FAULT_ENV: moment})
        proc = subprocess.run([sys.executable, str(script), str(src), str(archive), str(TILE_POINTS)], env=env,
                              stderr=subprocess.DEVNULL, timeout=600)
        assert proc.returncode == -signal.SIGKILL, (moment, proc.returncode)
        assert not archive.exists() and _work_dir(archive) is not None  # killed mid-build, work kept
        time.sleep(0.3)  # the workers' parent-death signals
        res = lodbuilder.build_archive(src, archive, workers=2, _tile_points=TILE_POINTS)
        assert [s.status for s in res.scans] == ["built"]
        with lodbuilder.open_archive(archive) as arc:
            v = arc.scan()
            got = v.source_index[:], v.radius[:], v.parent[:]
        for a, b in zip(want, got, strict=True):
            np.testing.assert_array_equal(a, b, err_msg=moment)


def _running_in_group(pgid):
    """The processes of process group ``pgid`` that are not zombies (dead, not yet reaped by init)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


ROUNDS_SCRIPT = textwrap.dedent("""
    import sys
    import lodbuilder
    if __name__ == "__main__":
        lodbuilder.build_archive(sys.argv[1], sys.argv[2], workers=2, _tile_points=int(sys.argv[3]), seam_rounds=True)
""")


def test_a_kill_in_the_seam_rounds_resumes_to_the_same_order(tmp_path):
    """kill -9 of the build while its tiles are in radius rounds (their states on the owners, no
    ordering marked done): the owners die with it, and the resumed build does the rounds again and
    stores exactly the order and radii of a build that was never interrupted."""
    pts = _sheet(90_000, seed=4)
    src = write_points(tmp_path / "sheet.npy", pts)
    clean = tmp_path / "clean.h5"
    lodbuilder.build_archive(src, clean, workers=2, _tile_points=9_000, seam_rounds=True)
    archive = tmp_path / "site.h5"
    script = tmp_path / "run.py"
    script.write_text(ROUNDS_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(src), str(archive), "9000"],
                            start_new_session=True, stderr=subprocess.DEVNULL)
    try:
        deadline, seen = time.time() + 300, None
        while time.time() < deadline and proc.poll() is None:
            w = _work_dir(archive)
            if w is not None and (w / "distribute.json").exists():
                seen = seen or time.time()
                if time.time() - seen > 0.3:  # (the rounds have started: their owners hold the states)
                    break
            time.sleep(0.005)
        w = _work_dir(archive)
        assert proc.poll() is None and not (w / "order.json").exists(), "the rounds ended before the kill"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    time.sleep(0.5)  # the workers' and owners' parent-death signals
    assert _running_in_group(proc.pid) == []  # nothing of the build is left running (zombies aside)
    assert list(w.glob("order*.json")) == []
    res = lodbuilder.build_archive(src, archive, workers=2, _tile_points=9_000, seam_rounds=True)
    assert res.scans[0].status == "built"
    with lodbuilder.open_archive(archive) as a, lodbuilder.open_archive(clean) as b:
        va, vb = a.scan("sheet"), b.scan("sheet")
        assert va.build["tiled"]["rounds"]["rounds"] == vb.build["tiled"]["rounds"]["rounds"] >= 1
        np.testing.assert_array_equal(va.source_index[:], vb.source_index[:])
        np.testing.assert_array_equal(va.radius[:], vb.radius[:])
