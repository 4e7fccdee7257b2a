"""tools/simulate_schedule.py: list scheduling on hand-made task lists whose optimal makespans are
known, the stage model (serial parent work beside the tasks), and the model of a build record
(tile orderings wait for their neighbours of a smaller colour)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

from simulate_schedule import (  # noqa: E402
    Stage,
    Task,
    bounds,
    compare,
    critical_path,
    main,
    makespan,
    measured_idle,
    model_from_record,
    predict,
    reference_seconds,
    simulate,
)


def _tasks(*seconds: float) -> list[Task]:
    return [Task(f"t{i}", s) for i, s in enumerate(seconds)]


@pytest.mark.parametrize(("seconds", "workers", "optimal"), [
    ((4, 3, 3, 2), 2, 6.0),  # 4+2 | 3+3: largest first finds it
    ((5, 5, 4, 4, 3, 3), 3, 8.0),  # 5+3 | 5+3 | 4+4
    ((1,) * 8, 4, 2.0),
    ((7, 1, 1, 1), 4, 7.0),  # the largest task bounds it
    ((2, 2, 2), 1, 6.0),  # one worker: the sum
    ((3,), 16, 3.0),
])
def test_independent_tasks_reach_the_optimum(seconds, workers, optimal):
    assert makespan(_tasks(*seconds), workers) == pytest.approx(optimal)


def test_largest_first_is_within_grahams_bound_where_it_misses_the_optimum():
    # 3+3 | 2+2+2 = 6 is optimal; largest first puts 3 | 3, then 2 | 2, then 2: 7 <= 4/3 x 6
    assert makespan(_tasks(3, 3, 2, 2, 2), 2) == pytest.approx(7.0)


def test_dependencies_a_chain_and_a_diamond():
    chain = [Task("a", 1), Task("b", 2, ["a"]), Task("c", 3, ["b"])]
    assert makespan(chain, 1) == makespan(chain, 8) == pytest.approx(6.0)  # the critical path
    diamond = [Task("a", 1), Task("b", 2, ["a"]), Task("c", 3, ["a"]), Task("d", 1, ["b", "c"])]
    assert makespan(diamond, 2) == pytest.approx(5.0)  # a, then b || c, then d
    assert makespan(diamond, 1) == pytest.approx(7.0)
    # a dependency outside the list counts as done
    assert makespan([Task("x", 2, ["elsewhere"])], 1) == pytest.approx(2.0)


def test_priority_orders_the_ready_tasks():
    # largest first: A | B, then C, then D (C's follower) alone: 7; C first lets D start at 3: 6
    tasks = [Task("A", 3), Task("B", 3), Task("C", 1), Task("D", 3, ["C"])]
    assert makespan(tasks, 2) == pytest.approx(7.0)
    tasks[2].priority = 10
    assert makespan(tasks, 2) == pytest.approx(6.0)


def test_fifo_takes_the_ready_tasks_as_they_came():
    # as in test_priority_orders_the_ready_tasks, but a queue that ignores the priority (the order
    # phase before it followed the critical path): largest first among those ready at once
    tasks = [Task("A", 3), Task("B", 3), Task("C", 1, priority=10), Task("D", 3, ["C"])]
    assert makespan(tasks, 2, fifo=True) == pytest.approx(7.0)
    # a task that becomes ready later waits behind every task queued before it, whatever its size
    late = [Task("a", 1), Task("x", 1), Task("y", 1), Task("z", 1), Task("b", 9, ["a"])]
    assert makespan(late, 1, fifo=True) == makespan(late, 1) == pytest.approx(13.0)
    assert makespan(late, 2) == pytest.approx(10.0)  # a | x, then b (the largest ready) | y, z
    assert makespan(late, 2, fifo=True) == pytest.approx(11.0)  # a | x, y | z (queued before b), b


def test_refuses_cycles_duplicate_ids_and_no_workers():
    with pytest.raises(ValueError, match="cycle"):
        makespan([Task("a", 1, ["b"]), Task("b", 1, ["a"])], 2)
    with pytest.raises(ValueError, match="unique"):
        makespan([Task("a", 1), Task("a", 2)], 2)
    with pytest.raises(ValueError, match="workers must be >= 1, got 0"):
        makespan(_tasks(1), 0)


def test_stages_are_amdahl():
    stages = [Stage("read", 10.0), Stage("order", 0.5, _tasks(*[10.0] * 8)), Stage("write", 5.0)]
    assert simulate(stages, 1)["total"] == pytest.approx(95.0)
    assert simulate(stages, 8)["total"] == pytest.approx(25.0)
    # the parent's own work in a stage with tasks bounds that stage
    assert simulate([Stage("tiles", 7.0, _tasks(2.0))], 4)["total"] == pytest.approx(7.0)
    rows = predict({"stages": stages}, [1, 8])["predicted"]
    assert [r["speedup_over_1"] for r in rows] == [1.0, 3.8]


def _record() -> dict:
    """A build record of 3 tiles in a row (0 | 1 | 2; 1 touches both), colours 1, 0, 1."""
    rows = [["coarse_task", "coarse_task", None, None, 2.5, 3.0, 2.9, 11],
            ["order_tile", "order.1.1", 1, None, 6.0, 4.0, 3.9, 11],
            ["order_tile", "order.0.1", 0, None, 10.0, 2.0, 2.0, 11],
            ["order_tile", "order.2.1", 2, None, 10.0, 2.0, 2.0, 12],
            ["cover_tile", "cover_tile.0", 0, None, 12.5, 1.0, 1.0, 11],
            ["cover_tile", "cover_tile.1", 1, None, 12.5, 1.0, 1.0, 12],
            ["cover_tile", "cover_tile.2", 2, None, 13.5, 1.0, 1.0, 11],
            ["order_tile", "order.9.1", 9, None, -50.0, 1.0, 1.0, 10]]  # done before a resume
    return {"phase_seconds": {"cover": 3.0, "order": 6.0, "plan": 1.0, "read": 1.0, "tiles": 4.0},
            "phase_order": ["read", "plan", "tiles", "order", "cover"],
            "parent_cpu_seconds": {"read": 0.9, "plan": 1.0, "tiles": 3.5, "order": 0.1, "cover": 0.5},
            "tasks": {"columns": ["kind", "piece", "tile", "block", "start", "seconds", "cpu_seconds", "pid"],
                      "rows": rows},
            "tiled": {"tile_colours": [1, 0, 1], "halo": 0.1,
                      "tile_boxes": [[0, 0, 0, 1, 1, 1], [1, 0, 0, 2, 1, 1], [2, 0, 0, 3, 1, 1]]}}


def test_model_of_a_build_record():
    model = model_from_record(_record(), rest=2.0, measured={"workers": 2, "wall_seconds": 17.0})
    st = {s.name: s for s in model["stages"]}
    assert list(st) == ["read", "plan", "tiles", "order", "cover", "rest"]
    assert st["read"].parent_seconds == 1.0 and not st["read"].tasks  # a parent phase: its wall seconds
    assert st["tiles"].parent_seconds == 3.5  # beside tasks: the parent's CPU seconds
    assert [t.id for t in st["tiles"].tasks] == ["coarse_task"]
    order = {t.id: t.deps for t in st["order"].tasks}
    assert order == {"order.1.1": [], "order.0.1": ["order.1.1"], "order.2.1": ["order.1.1"]}
    assert len(st["cover"].tasks) == 3
    assert any("1 task(s) were done before a resume" in n for n in model["notes"])
    out = predict(model, [1, 2])
    # 1 worker: 1 + 1 + max(3.5, 3) + (4 + 2 + 2) + max(0.5, 3) + 2 = 18.5; 2 workers: order 4 + 2, cover 2
    assert [r["wall_seconds"] for r in out["predicted"]] == [18.5, 15.5]
    assert out["calibration"] == {"workers": 2, "measured_wall_seconds": 17.0, "predicted_wall_seconds": 15.5,
                                  "predicted_over_measured": 0.912}
    assert "not measured" in out["notes"][0]


def test_measured_idle_of_a_build_record():
    """Where the measured run's 2 workers waited, phase by phase (the resumed task left out)."""
    out = measured_idle(_record(), 2)
    ph = out["by_phase"]
    assert list(ph) == ["read", "plan", "tiles", "order", "cover"]
    # no task in read and plan: both workers idle throughout
    assert ph["read"] == {"wall": 1.0, "busy": 0.0, "idle": 2.0, "first_task_after": 1.0, "tail": 1.0, "waiting": 0.0}
    # the coarse task alone (2.5 .. 5.5 of 2 .. 6): one worker never ran a task in the phase
    assert ph["tiles"] == {"wall": 4.0, "busy": 3.0, "idle": 5.0, "first_task_after": 0.5, "tail": 4.0,
                           "waiting": 0.1}
    assert ph["order"] == {"wall": 6.0, "busy": 8.0, "idle": 4.0, "first_task_after": 0.0, "tail": 0.0,
                           "waiting": 0.1}
    # cover 12 .. 15: worker 12's last task ends at 13.5
    assert ph["cover"] == {"wall": 3.0, "busy": 3.0, "idle": 3.0, "first_task_after": 0.5, "tail": 1.5,
                           "waiting": 0.0}
    assert out["idle"] == 16.0 and out["waiting"] == 0.2


def test_orderings_start_by_their_bottom_level():
    """The driver starts the ready ordering with the longest chain of orderings waiting for it
    first: the model gives each its bottom level as priority (from the recorded seconds)."""
    st = {s.name: s for s in model_from_record(_record())["stages"]}
    assert {t.id: t.priority for t in st["order"].tasks} == {"order.1.1": 6.0, "order.0.1": 2.0, "order.2.1": 2.0}
    assert all(t.priority is None for t in st["cover"].tasks)


def test_cpu_durations_replay_cpu_seconds():
    model = model_from_record(_record(), rest=0.5, durations="cpu")
    st = {s.name: s for s in model["stages"]}
    assert st["read"].parent_seconds == 0.9  # the parent's CPU, not the phase's wall
    assert [t.seconds for t in st["order"].tasks] == [3.9, 2.0, 2.0]
    assert "task CPU seconds" in model["notes"][0]
    # 0.9 + 1.0 + max(3.5, 2.9) + (3.9 + 2.0) + max(0.5, 1 + 1) + 0.5 on 2 workers
    assert predict(model, [2])["predicted"][0]["wall_seconds"] == 13.8
    with pytest.raises(ValueError, match="durations must be wall or cpu, got 'gpu'"):
        model_from_record(_record(), durations="gpu")


def test_rounds_inside_a_phase_wait_for_the_earlier_round():
    """The seam links, the seam repair, the merge's bands, then the ranks' two rounds; the write's
    first band, then the others: on many workers each round waits for the one before (a phase is
    not one bag of independent tasks)."""
    cols = ["kind", "piece", "tile", "block", "start", "seconds", "cpu_seconds", "pid"]
    rows = [["seam_links", "links.0", None, None, 0.0, 0.5, 0.5, 1],
            ["seam_links", "links.1", None, None, 0.0, 0.5, 0.5, 2],
            ["seam_repair", "seam_repair", None, None, 0.5, 2.0, 2.0, 1],
            ["merge_band", "merge_band", None, None, 2.0, 1.0, 1.0, 1],
            ["merge_band", "merge_band#2", None, None, 2.0, 1.0, 1.0, 2],
            ["rank_band", "rank_band", None, None, 3.0, 1.0, 1.0, 1],
            ["rank_band", "rank_band#2", None, None, 3.0, 1.0, 1.0, 2],
            ["rank_block", "rank_block.0", None, 0, 4.0, 0.5, 0.5, 1],
            ["rank_block", "rank_block.1", None, 1, 4.0, 0.5, 0.5, 2],
            ["write_band", "write_band", None, None, 10.0, 2.0, 2.0, 1],
            ["write_band", "write_band#2", None, None, 12.0, 2.0, 2.0, 1],
            ["write_band", "write_band#3", None, None, 12.0, 2.0, 2.0, 2]]
    rec = {"phase_seconds": {"merge": 10.0, "write": 6.0}, "phase_order": ["merge", "write"],
           "parent_cpu_seconds": {"merge": 0.0, "write": 0.1}, "tasks": {"columns": cols, "rows": rows}}
    walls = predict(model_from_record(rec), [16])["predicted"][0]["stages"]
    assert walls == {"merge": 5.0, "write": 4.0}  # 0.5 + 2 + 1 + 1 + 0.5 and 2 + 2, not 2 and 2


def test_the_radii_and_the_join_wait_for_the_covering():
    """The radii's first round starts when every tile is covered; the join of the band pieces when
    every tile's pieces are written (by its covering task) (older records: one cover phase)."""
    cols = ["kind", "piece", "tile", "block", "start", "seconds", "cpu_seconds", "pid"]
    rows = [["cover_tile", "cover_tile.0", 0, None, 0.0, 4.0, 4.0, 1],
            ["bucket_block", "bucket_block.0", None, 0, 0.0, 1.0, 1.0, 2],
            ["join_task", "join_task", None, None, 4.0, 2.0, 2.0, 2],
            ["radii_band", "radii_band", None, None, 4.0, 1.0, 1.0, 1],
            ["finish_band", "finish_band", None, None, 5.0, 0.5, 0.5, 1]]
    rec = {"phase_seconds": {"cover": 6.0}, "phase_order": ["cover"], "parent_cpu_seconds": {"cover": 0.0},
           "tasks": {"columns": cols, "rows": rows}}
    walls = predict(model_from_record(rec), [16])["predicted"][0]["stages"]
    assert walls == {"cover": 6.0}  # 4 + max(2, 1 + 0.5), not max(4, 2, 1 + 0.5)


def test_the_join_of_the_pairs_waits_for_every_band_of_the_join():
    """The join runs in bands of input indices (join_band, on every free worker), then one short
    task joins their pairs (join_task): 2 bands of 2 s on 16 workers and the join's 0.5 s take
    2.5 s, not 2 (the join beside the bands) nor 4.5 (the bands one after the other)."""
    cols = ["kind", "piece", "tile", "block", "start", "seconds", "cpu_seconds", "pid"]
    rows = [["join_band", "join_band.0", None, None, 0.0, 2.0, 2.0, 1],
            ["join_band", "join_band.1", None, None, 2.0, 2.0, 2.0, 1],
            ["join_task", "join_task", None, None, 4.0, 0.5, 0.5, 1]]
    rec = {"phase_seconds": {"pieces": 4.5}, "phase_order": ["pieces"], "parent_cpu_seconds": {"pieces": 0.0},
           "tasks": {"columns": cols, "rows": rows}}
    assert predict(model_from_record(rec), [16])["predicted"][0]["stages"] == {"pieces": 2.5}


def test_the_radii_do_not_wait_for_the_buckets():
    """The buckets are written after the radii (phase permute): a radii task never waits for one
    (a record with both in one phase: the radii's 1 s after the covering's 4, beside the bucket's 6)."""
    cols = ["kind", "piece", "tile", "block", "start", "seconds", "cpu_seconds", "pid"]
    rows = [["cover_tile", "cover_tile.0", 0, None, 0.0, 4.0, 4.0, 1],
            ["bucket_block", "bucket_block.0", None, 0, 0.0, 6.0, 6.0, 2],
            ["radii_band", "radii_band", None, None, 4.0, 1.0, 1.0, 1]]
    rec = {"phase_seconds": {"cover": 7.0}, "phase_order": ["cover"], "parent_cpu_seconds": {"cover": 0.0},
           "tasks": {"columns": cols, "rows": rows}}
    assert predict(model_from_record(rec), [16])["predicted"][0]["stages"] == {"cover": 6.0}


def test_bounds_name_the_work_and_the_chain_of_each_stage():
    """A stage's lower bounds: its work over the workers and its longest chain; the order of a
    chain of 3 + 3 beside four 1 s tasks is bound by the chain on 4 workers, by the work on 1."""
    tasks = [Task("a", 3.0), Task("b", 3.0, ["a"]), *_tasks(1, 1, 1, 1)]
    assert critical_path(tasks) == 6.0 and critical_path([]) == 0.0
    stages = [Stage("read", 2.0), Stage("order", 0.5, tasks)]
    assert bounds(stages, 4) == {"order": {"work": 2.5, "path": 6.0, "parent": 0.5}}
    assert bounds(stages, 1)["order"]["work"] == 10.0
    assert simulate(stages, 4)["order"] == pytest.approx(6.0)


def test_slowdown_scales_the_tasks_not_the_parent():
    stages = [Stage("read", 2.0), Stage("order", 3.0, _tasks(*[4.0] * 4))]
    assert simulate(stages, 4)["total"] == pytest.approx(6.0)  # 2 + max(3, 4)
    assert simulate(stages, 4, slowdown=1.5)["total"] == pytest.approx(8.0)  # 2 + 6
    rows = predict({"stages": stages}, [1, 4], slowdown={4: 1.5})["predicted"]
    assert [r["wall_seconds"] for r in rows] == [18.0, 8.0]
    assert rows[1]["slowdown"] == 1.5 and "slowdown" not in rows[0]


def test_compare_predicts_each_record_at_its_own_worker_count():
    """Two plans (few large tiles for 2 workers, more smaller ones for 4): each predicted at its own
    count, the speed-up over the first."""
    few = {"stages": [Stage("read", 1.0), Stage("order", 0.0, _tasks(4.0, 4.0))]}
    many = {"stages": [Stage("read", 1.0), Stage("order", 0.0, _tasks(*[2.0] * 4))]}
    out = compare([few, many], [2, 4])
    assert [r["predicted"][0]["wall_seconds"] for r in out["runs"]] == [5.0, 3.0]
    assert [r["speedup_over_first"] for r in out["runs"]] == [1.0, 1.667]
    with pytest.raises(ValueError, match=r"2 record\(s\) need as many worker counts, got 1"):
        compare([few, many], [2])


def test_main_compares_archives(tmp_path, monkeypatch, capsys):
    import json

    import simulate_schedule

    monkeypatch.setattr(simulate_schedule, "_record", lambda path, scan: _record())
    assert main([str(tmp_path / "a.h5"), str(tmp_path / "b.h5"), "--workers", "1,2", "--slowdown", "2:1.1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["workers"] for r in out["runs"]] == [1, 2]
    assert out["runs"][1]["predicted"][0]["slowdown"] == 1.1
    assert out["command"].startswith("python tools/simulate_schedule.py ") and out["commit"] and out["date"]
    assert out["kind"] == "prediction (not measured)"


def test_compare_normalises_records_of_different_loads():
    """The second record's plan-independent tasks took twice the CPU (a loaded machine): its tasks
    count half."""
    a = {"stages": [Stage("order", 0.0, _tasks(4.0, 4.0))]}
    b = {"stages": [Stage("order", 0.0, _tasks(*[4.0] * 4))]}
    out = compare([a, b], [2, 4], references=[10.0, 20.0])
    assert [r["predicted"][0]["wall_seconds"] for r in out["runs"]] == [4.0, 2.0]
    assert [r["load_scale"] for r in out["runs"]] == [1.0, 0.5]
    with pytest.raises(ValueError, match="every record needs tasks of read_block"):
        compare([a, b], [2, 4], references=[10.0, 0.0])
    rec = _record()
    rec["tasks"]["rows"] += [["read_block", "read_block.0", None, 0, 0.1, 1.5, 1.25, 11],
                             ["write_band", "write_band", None, None, 20.0, 2.0, 2.0, 11],
                             ["read_block", "read_block.9", None, 9, -9.0, 1.0, 1.0, 11]]  # before a resume
    assert reference_seconds(rec) == 3.25
