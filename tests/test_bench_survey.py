"""tools/make_survey.py (one file, or one file per copy) and tools/bench_survey.py on a tiny survey:
the JSON's keys and invariants, never its times."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import make_survey  # noqa: E402


def test_make_survey_files_are_shifted_copies_with_the_source_crs(tmp_path):
    import laspy

    doc = make_survey.make_files(tmp_path / "s", 3, 2, thin=100)
    files = sorted((tmp_path / "s").glob("*.laz"))
    assert [f.name for f in files] == [f"survey_{j}_{i}.laz" for j in range(2) for i in range(3)]
    assert doc["files"] == 6 and doc["points"] == 6 * 1_100 and doc["bytes"] == sum(f.stat().st_size for f in files)
    assert not list((tmp_path / "s").glob("*.part"))
    src = laspy.read(str(make_survey.SOURCE))
    x0, y0 = np.asarray(src.points.X)[::100], np.asarray(src.points.Y)[::100]
    one = make_survey.make(tmp_path / "one.laz", 3, 2, thin=100)
    whole = laspy.read(str(tmp_path / "one.laz"))
    assert one["points"] == len(whole) == doc["points"]
    boxes = []
    for k, f in enumerate(files):
        las = laspy.read(str(f))
        assert las.header.parse_crs() == src.header.parse_crs() is not None
        dx, dy = np.asarray(las.points.X) - x0, np.asarray(las.points.Y) - y0
        assert np.ptp(dx) == 0 and np.ptp(dy) == 0  # the source, shifted as a whole
        np.testing.assert_array_equal(las.intensity, src.intensity[::100])
        # the one-file mode holds the same copies in the same order
        np.testing.assert_array_equal(las.points.X, whole.points.X[k * 1_100:(k + 1) * 1_100])
        boxes.append((las.header.mins, las.header.maxs))
    for a in range(len(boxes)):
        for b in range(a):  # the copies do not touch
            assert np.any(boxes[a][0][:2] > boxes[b][1][:2]) or np.any(boxes[b][0][:2] > boxes[a][1][:2])


def test_make_survey_refuses_bad_counts(capsys):
    with pytest.raises(SystemExit):
        make_survey.main(["--nx", "0", "--files", "x"])
    assert "--nx, --ny and --thin must be >= 1, got 0, 14 and 1" in capsys.readouterr().err


@pytest.fixture(scope="module")
def bench_doc(tmp_path_factory):
    import bench_survey

    d = tmp_path_factory.mktemp("bench")
    make_survey.make_files(d / "files", 2, 1, thin=50)
    make_survey.make(d / "one.laz", 2, 1, thin=50)
    out = d / "bench.json"
    rc = bench_survey.main([str(d / "one.laz"), str(d / "files"), "--workers", "1,2", "--max-memory", "2GB",
                            "--tile-points", "700", "--no-warm-up", "--work", str(d / "runs"), "--out", str(out),
                            "--interval", "0.05", "--plan-workers", "16"])
    return rc, json.loads(out.read_text()), d


def test_bench_survey_document(bench_doc, capsys):
    rc, doc, d = bench_doc
    assert rc == 0
    assert {"benchmark", "date", "commit", "command", "cpus", "surveys"} <= set(doc)
    assert doc["benchmark"] == "bench_survey" and "bench_survey.py" in doc["command"]
    single, joint = doc["surveys"]
    assert single["joint"] is None and single["input"]["files"] == 1
    assert joint["joint"] == "survey" and joint["input"]["files"] == 2
    assert not any((d / "runs").iterdir())  # every run cleans up after itself
    for sv in doc["surveys"]:
        assert [(r["executor"], r["workers"], r["plan_workers"]) for r in sv["runs"]] == [("pool", 1, 16), ("pool", 2, 16)]
        for r in sv["runs"]:
            assert r["rc"] == 0 and r["method"] == "tiled" and r["n_points"] == 4_400
            assert r["points_per_second"] == pytest.approx(4_400 / r["wall_seconds"], rel=0.01, abs=1)
            assert 0 < r["cpu_parent_seconds"] < r["cpu_tree_seconds"]
            assert r["parent_cpu_share"] == pytest.approx(r["cpu_parent_seconds"] / r["cpu_tree_seconds"], abs=0.01)
            assert r["processes_seen"] >= 1 + r["workers"]  # the parent and its workers, at least
            assert r["peak_rss_tree_bytes"] > 0 and r["peak_rss_parent_bytes"] > 0
            assert r["rss_over_max_memory"] == pytest.approx(r["peak_rss_tree_bytes"] / 2e9, abs=1e-3)
            assert r["worker_share_bytes"] == int((2e9 - 600 * 2**20) / r["workers"])
            assert 0 < r["peak_work_dir_bytes"] <= r["peak_written_bytes"]
            assert r["work_over_archive"] == pytest.approx(r["peak_work_dir_bytes"] / r["archive_bytes"], abs=1e-3)
            # (the write is the record's last phase: its bands are tasks in the table)
            assert list(r["phase_seconds"]) == ["read", "plan", "tiles", "order", "merge", "cover", "pieces", "radii",
                                                "permute", "write"]
            # (the work directory's bytes per kind of file at its peak, over the archive's)
            assert sum(r["peak_work_over_archive_by_kind"].values()) == pytest.approx(r["work_over_archive"], abs=0.05)
            assert 0 < r["peak_work_seconds"] <= r["wall_seconds"]
            # (its largest size in each phase: the largest of them is the peak, bar the samples between phases)
            by_phase = r["peak_work_by_phase"]
            assert set(by_phase) <= set(r["phase_seconds"]) and len(by_phase) >= 5
            assert max(p["over_archive"] for p in by_phase.values()) <= r["work_over_archive"]
            assert all(sum(p["largest"].values()) <= p["over_archive"] + 1e-3 for p in by_phase.values())
            assert set(r["cpu_parent_by_phase"]) == set(r["phase_seconds"])
            kinds = r["tasks"]["by_kind"]
            assert kinds["coarse_task"]["tasks"] == 1
            assert 0 < r["head_points"] < r["coarse_points"] < r["n_points"]
            assert kinds["order_tile"]["tasks"] == kinds["cover_tile"]["tasks"] == r["tiles"] >= 4
            for kind in ("read_block", "survey_block", "distribute_block", "bucket_block", "rank_band", "rank_block",
                         "write_band"):
                assert kinds[kind]["tasks"] >= 1, kind
            assert 1 <= r["tasks"]["workers_seen"] <= r["workers"]
            # every task's worker peak, the largest per kind (a worker holds Python and NumPy at least)
            peaks = r["tasks"]["peak_rss_by_kind"]
            assert set(peaks) == set(kinds) and all(v == kinds[k]["peak_rss_max"] > 20e6 for k, v in peaks.items())
            assert list(peaks.values()) == sorted(peaks.values(), reverse=True)
            sim = r["simulation"]
            assert [p["workers"] for p in sim["predicted"]] == [1, 2, 4, 8, 16]
            assert sim["predicted"][0]["speedup_over_1"] == 1.0
            assert all(p["wall_seconds"] >= sim["serial_parent_seconds"] for p in sim["predicted"])
            assert sim["calibration"]["workers"] == r["workers"]
            assert "not measured" in sim["notes"][0]
            assert "task CPU seconds" in r["simulation_cpu"]["notes"][0]
            idle = r["measured_idle"]  # (measured: where the workers waited, phase by phase)
            assert list(idle["by_phase"]) == list(r["phase_seconds"])
            assert idle["idle"] == pytest.approx(sum(p["idle"] for p in idle["by_phase"].values()), abs=0.05)
        one, two = sv["runs"]
        assert sv["speedup_over_1_worker"] == {"pool 2": round(one["wall_seconds"] / two["wall_seconds"], 3)}
        t = sv["targets"]
        assert t["parent_cpu_share"]["worst"] == max(r["parent_cpu_share"] for r in sv["runs"])
        assert t["parent_cpu_share"]["met"] == (t["parent_cpu_share"]["worst"] <= 0.03)
        assert t["speedup_2_over_1"]["met"] == (t["speedup_2_over_1"]["value"] >= 1.9)
        assert t["work_over_archive"]["target_max"] == 2.0
        assert t["rss_over_max_memory"]["worst"] == max(r["rss_over_max_memory"] for r in sv["runs"])
        assert t["rss_over_max_memory"]["target_max"] == 1.1


def test_append_replaces_the_runs_of_a_survey_measured_again(tmp_path, monkeypatch):
    """--append keeps the other surveys of the document and replaces those of the same files (by
    name and size, wherever they lie) with the new runs."""
    import bench_survey

    run = {"rc": 0, "executor": "pool", "workers": 1, "wall_seconds": 1.0, "parent_cpu_share": 0.01,
           "work_over_archive": 1.0, "rss_over_max_memory": 0.5}
    monkeypatch.setattr(bench_survey, "run_build", lambda *a, **k: dict(run))
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for d, size in (("a", 10), ("b", 10)):
        (tmp_path / d / "s.laz").write_bytes(bytes(size))
    (tmp_path / "other.laz").write_bytes(bytes(7))
    out = tmp_path / "doc.json"
    args = ["--workers", "1", "--no-warm-up", "--out", str(out), "--append"]
    assert bench_survey.main([str(tmp_path / "a" / "s.laz"), str(tmp_path / "other.laz"), *args]) == 0
    assert bench_survey.main([str(tmp_path / "b" / "s.laz"), *args]) == 0
    doc = json.loads(out.read_text())
    assert [sv["input"]["paths"] for sv in doc["surveys"]] == [[str(tmp_path / "other.laz")],
                                                               [str(tmp_path / "b" / "s.laz")]]
    assert len(doc["earlier"]) == 1
    # the same files at other settings (a budget, a plan for other workers) are another record
    assert bench_survey.main([str(tmp_path / "a" / "s.laz"), *args, "--max-memory", "16GB", "--plan-workers", "16"]) == 0
    assert bench_survey.main([str(tmp_path / "b" / "s.laz"), *args, "--max-memory", "16GB", "--plan-workers", "16"]) == 0
    doc = json.loads(out.read_text())
    assert [(sv["input"]["paths"], sv["settings"]["max_memory"]) for sv in doc["surveys"]] == [
        ([str(tmp_path / "other.laz")], "3GB"), ([str(tmp_path / "b" / "s.laz")], "3GB"),
        ([str(tmp_path / "b" / "s.laz")], "16GB")]
    assert doc["surveys"][-1]["settings"] == {"max_memory": "16GB", "plan_workers": 16, "tile_points": None,
                                              "seam_rounds": False}
    # ... and so is a record of other executors (a pool-only run keeps the pool-against-Dask record)
    monkeypatch.setattr(bench_survey, "run_build", lambda *a, **k: {**run, "executor": a[2]})
    assert bench_survey.main([str(tmp_path / "b" / "s.laz"), *args, "--executor", "pool,dask"]) == 0
    doc = json.loads(out.read_text())
    assert [[r["executor"] for r in sv["runs"]] for sv in doc["surveys"]] == [["pool"], ["pool"], ["pool"],
                                                                             ["pool", "dask"]]


def test_the_sampler_walks_a_dear_directory_less_often(tmp_path, monkeypatch):
    """The walk of a survey's work directory (thousands of files) is the sampler's dearest part, and
    its CPU competes with the build's workers: one walk gives both sizes, and the next waits until
    the walks have taken at most DISK_SHARE of the time (the process tree at every sample)."""
    import os
    import time

    import bench_survey

    (tmp_path / "scan.work").mkdir()
    (tmp_path / "scan.work" / "raw.0.bin").write_bytes(bytes(10_000))
    (tmp_path / "out.h5").write_bytes(bytes(5_000))
    walks = []
    real = bench_survey.disk_bytes

    def dear(*a, **k):  # a walk of 50 ms at least: the next one 1 s later at the earliest
        walks.append(1)
        time.sleep(0.05)
        return real(*a, **k)

    monkeypatch.setattr(bench_survey, "disk_bytes", dear)
    s = bench_survey.Sampler(os.getpid(), tmp_path, 0.01)
    before = time.perf_counter()
    for _ in range(5):
        s.sample()
    assert s.samples == 5 and len(walks) == 1
    assert s.disk_next >= before + 0.05 / s.DISK_SHARE  # (however long the samples took)
    work, total = real(tmp_path)
    assert s.peak_work == work >= 10_000 and s.peak_all == total >= work + 5_000
    assert set(s.peak_work_by_kind) == {"raw"} and len(s.timeline) == 1
    s.disk_next = time.perf_counter()  # the time has come: walked again
    s.sample()
    assert len(walks) == 2 and len(s.timeline) == 2


def test_the_sampler_finds_the_process_tree_by_its_children(monkeypatch):
    """The tree is walked from the root's children files (not every process of the machine); where
    the kernel has none, every process's parent gives the same tree."""
    import os
    import subprocess

    import bench_survey

    kids = [subprocess.Popen(["sleep", "30"]) for _ in range(2)]
    try:
        cpu, rss = bench_survey.tree(os.getpid())
        assert {p for p, _ in cpu} >= {os.getpid(), *(k.pid for k in kids)}
        assert rss > 20e6 and all(v >= 0 for v in cpu.values())
        monkeypatch.setattr(bench_survey, "_children", lambda pid: None)
        again, _ = bench_survey.tree(os.getpid())
        assert set(again) == set(cpu)
    finally:
        for k in kids:
            k.kill()
            k.wait()


def test_bench_inputs_writes_one_synthetic_input_and_refuses_other_files(tmp_path, capsys):
    """tools/bench_inputs.py writes one input of the set as .npy (an input of bench_survey and of any
    build), through a temporary name; another suffix is refused and nothing is written."""
    import bench_inputs

    out = tmp_path / "uneven.npy"
    assert bench_inputs.main(["uneven", "5000", "-o", str(out)]) == 0
    pts = np.load(out)
    assert pts.shape == (5000, 3) and pts.dtype == np.float64
    np.testing.assert_array_equal(pts, bench_inputs.synthetic("uneven", 5000))
    assert capsys.readouterr().out == f"wrote 5,000 points (uneven, synthetic) to {out}\n"
    with pytest.raises(SystemExit) as e:
        bench_inputs.main(["uneven", "5000", "-o", str(tmp_path / "u.ply")])
    assert e.value.code == 2 and "--output must end in .npy, got" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["uneven.npy"]


def test_between_plans_takes_each_worker_count_from_the_record_planned_for_it():
    """The 16-worker figure comes from the build planned for 16 workers, the 4-worker one from the
    build planned for 4 (not from either record's replay at the other count); records with a forced
    tile size, other inputs or another budget stay apart."""
    import bench_survey

    def survey(plan, budget="16GB", tile_points=None, paths=("/x/s",), sec=None):
        sec = sec or {}
        sim = {w: {"workers": w, "wall_seconds": s} for w, s in sec.items()}
        run = {"rc": 0, "n_points": 1_600_000, "tiles": 8 * plan,
               "simulation": {"predicted": [dict(p, wall_seconds=p["wall_seconds"] + 1.0) for p in sim.values()]},
               "simulation_cpu": {"predicted": list(sim.values())}}
        return {"input": {"paths": list(paths), "files": 1, "bytes": 10}, "runs": [run],
                "settings": {"max_memory": budget, "plan_workers": plan, "tile_points": tile_points,
                             "seam_rounds": False}}

    surveys = [survey(4, sec={4: 4.0, 16: 2.0}), survey(16, sec={4: 3.0, 16: 1.0}),
               survey(16, tile_points=5, sec={16: 0.5}), survey(16, budget="3GB", sec={16: 0.5}),
               survey(4, paths=("/y/other",), sec={4: 9.0})]
    (doc,) = bench_survey.between_plans(surveys)
    assert doc["max_memory"] == "16GB" and sorted(doc["plans"]) == ["16", "4"]
    assert doc["plans"]["16"]["predicted_seconds"] == {"wall_durations": 2.0, "cpu_durations": 1.0}
    assert doc["plans"]["16"]["tiles"] == 128
    assert doc["plans"]["16"]["speedup_over_4"] == {"wall_durations": 2.5, "cpu_durations": 4.0}
    assert doc["plans"]["16"]["points_per_second"] == {"wall_durations": 800_000, "cpu_durations": 1_600_000}
    t = doc["targets"]
    assert t["speedup_16_over_4"] == {"worst": 2.5, "target_min": 3.4, "met": False}
    assert t["points_per_second_16"] == {"worst": 800_000, "target_min": 1.5e6, "met": False}
    assert bench_survey.between_plans(surveys[1:]) == []  # one plan of those inputs: nothing to compare
