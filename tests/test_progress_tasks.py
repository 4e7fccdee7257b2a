"""Progress of a phase of tasks (tiles on workers): counts and points per second summed over the
workers, the time left, the lines without a terminal, the bar; and a failed task named with its
tile, its source files and its worker."""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from lodbuilder.progress import Rate, TaskCounts, report_tasks, task_line

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_task_lines_exact_text():
    clock = FakeClock()
    rate = Rate(clock=clock)
    c = TaskCounts(0, 16, 0, 1_760_000, running=2)
    rate.add(0)
    assert task_line("tiles", c, rate) == "tiles: 0 of 16 tiles, 0 of 1.76 M points, 2 queued or running"
    clock.now = 10.0
    rate.add(440_000)
    c = TaskCounts(4, 16, 440_000, 1_760_000, running=2)
    assert task_line("tiles", c, rate) == ("tiles: 4 of 16 tiles, 0.44 M of 1.76 M points, 2 queued or running, "
                                           "44,000 points/s, about 30 s left")
    clock.now = 40.0
    rate.add(1_760_000)
    c = TaskCounts(16, 16, 1_760_000, 1_760_000)
    assert task_line("tiles", c, rate) == "tiles: 16 of 16 tiles, 1.76 M of 1.76 M points in 40 s (44,000 points/s)"
    one = Rate(clock=clock)
    clock.now = 100.0
    one.add(1_000)
    assert task_line("coarse", TaskCounts(0, 1, 1_000, 4_000_000, unit="task"), one) == (
        "coarse: 0 of 1 task, 1,000 of 4.00 M points, 17 points/s, about 66 h 39 min left")


def test_the_rate_follows_the_last_window():
    clock = FakeClock()
    rate = Rate(window=60.0, clock=clock)
    for t, p in ((30, 300), (60, 600), (90, 3_600), (120, 6_600)):  # 10/s, then 100/s
        clock.now = t
        rate.add(p)
    assert rate.per_second() == pytest.approx(100.0)  # from 60 s on
    assert rate.seconds_left(16_600) == pytest.approx(100.0)
    assert Rate(clock=clock).per_second() is None


def test_report_tasks_reaches_both_kinds_of_callback():
    seen = []
    report_tasks(lambda *a: seen.append(a), "tiles", TaskCounts(3, 8, 10, 80))
    assert seen == [("tiles", 3, 8)]  # a plain callback counts tasks, as before

    class WithTasks:
        def __call__(self, *a):
            seen.append(("call", *a))

        def tasks(self, stage, counts):
            seen.append(("tasks", stage, counts))

    report_tasks(WithTasks(), "covering", TaskCounts(1, 2, 5, 9))
    assert seen[-1] == ("tasks", "covering", TaskCounts(1, 2, 5, 9))
    report_tasks(None, "tiles", TaskCounts(1, 2, 5, 9))  # silent


def test_lines_without_a_terminal_are_throttled(capsys):
    from lodbuilder.cli.progressbar import LINE_SECONDS, ProgressBars

    bars = ProgressBars(stage_lines=True)  # stderr is no terminal under pytest
    bars.clock = clock = FakeClock()
    for t, done in ((0, 0), (1, 1), (LINE_SECONDS + 1, 2), (LINE_SECONDS + 2, 3), (LINE_SECONDS + 3, 4)):
        clock.now = t
        bars.tasks("tiles", TaskCounts(done, 4, done * 1000, 4000))
    bars.tasks("tiles", TaskCounts(4, 4, 4000, 4000))  # the end is said once
    assert capsys.readouterr().err.splitlines() == [
        "tiles: 0 of 4 tiles, 0 of 4,000 points",
        "tiles: 2 of 4 tiles, 2,000 of 4,000 points, 65 points/s, about 31 s left",
        "tiles: 4 of 4 tiles, 4,000 of 4,000 points in 33 s (121 points/s)",
    ]
    quiet = ProgressBars(enabled=False, stage_lines=True)  # --no-progress, --json, -q: nothing
    quiet.tasks("tiles", TaskCounts(4, 4, 4000, 4000))
    assert capsys.readouterr().err == ""


def test_the_bar_counts_points_with_the_tasks_beside(capsys):
    from lodbuilder.cli.progressbar import ProgressBars

    with ProgressBars(enabled=True) as bars:
        bars.tasks("tiles", TaskCounts(0, 16, 0, 1_760_000))
        bars.tasks("tiles", TaskCounts(4, 16, 440_000, 1_760_000))
        bar = bars._bars["tiles"]  # (tqdm redraws at most every 0.1 s: the second state is in the bar)
        assert (bar.n, bar.total, bar.postfix) == (440_000, 1_760_000, "4/16 tiles")
    err = capsys.readouterr().err
    assert "tiles:   0%|          | 0.00/1.76M [00:00<?, ?pt/s, 0/16 tiles]" in err


# ------------------------------------------------------------------------------------ failures

def _small_survey(tmp_path: Path) -> list[Path]:
    """autzen_trim.laz thinned to 2,200 points, copied 2 x 1 side by side as 2 LAZ files."""
    from make_survey import make_files

    make_files(tmp_path / "survey", 2, 1, thin=50)
    return sorted((tmp_path / "survey").glob("*.laz"))


def _build_inline(tmp_path, files, monkeypatch, fail_tile=None):
    """The tiled driver on the files as one joint scan, its tasks in this process."""
    from lodbuilder.build.executors import InlineExecutor
    from lodbuilder.build.tiled.driver import build_tiled
    from lodbuilder.io.stream import open_stream

    if fail_tile is not None:
        import lodbuilder.sampling.fastfps as ff

        real, calls = ff.fastfps, {"n": 0}

        def fastfps(pts, **kw):
            if kw.get("voxel_size") is not None:  # a tile ordering (the coarse level has none)
                calls["n"] += 1
                if calls["n"] == fail_tile:
                    raise MemoryError("no room for this tile")
            return real(pts, **kw)

        monkeypatch.setattr(ff, "fastfps", fastfps)
    from lodbuilder.build.jobs import TiledInput

    sources = [(open_stream(f), None, i, TiledInput(str(f), None, None, False, None, None)) for i, f in enumerate(files)]
    work = tmp_path / "s.work"
    return build_tiled(sources, tmp_path / "s.h5", "survey", work, InlineExecutor(), tile_points=700), work


def _files_of_box(files, lo, hi):
    import laspy

    out = []
    for f in files:
        h = laspy.open(str(f)).header
        if np.all(np.asarray(h.mins) <= hi) and np.all(np.asarray(h.maxs) >= lo):
            out.append(f.name)
    return out


def test_a_failed_tile_is_named_with_its_files_and_worker(tmp_path, monkeypatch):
    from lodbuilder.build.tiled.workdir import read_json
    from lodbuilder.errors import BuildError

    files = _small_survey(tmp_path)
    with pytest.raises(BuildError) as exc:
        _build_inline(tmp_path, files, monkeypatch, fail_tile=1)
    msg = str(exc.value)
    work = tmp_path / "s.work"
    tiles = read_json(work / "plan.json")["tiles"]
    m = re.fullmatch(r"scan 'survey': ordering of tile (\d+) of (\d+) failed: MemoryError: no room for this tile \((.*)\)",
                     msg)
    assert m, msg
    t = int(m.group(1)) - 1
    assert int(m.group(2)) == len(tiles) >= 4
    names = _files_of_box(files, np.asarray(tiles[t]["lo"]), np.asarray(tiles[t]["hi"]))
    what = f"{'file' if len(names) == 1 else 'files'} {', '.join(names)}"
    assert m.group(3) == f"{what}; worker {os.getpid()}"


def test_tile_files_name_the_files_of_every_tile(tmp_path, monkeypatch):
    import lodbuilder.build.tiled.driver as driver
    from lodbuilder.build.tiled.timing import tile_files
    from lodbuilder.build.tiled.workdir import read_json

    files = _small_survey(tmp_path)

    def stop(*a, **k):
        raise KeyboardInterrupt  # after the order phase: the work directory stays

    monkeypatch.setattr(driver, "_merge", stop)
    with pytest.raises(KeyboardInterrupt):
        _build_inline(tmp_path, files, monkeypatch)
    work = tmp_path / "s.work"
    tiles = read_json(work / "plan.json")["tiles"]
    got = [tile_files(work, t["index"]) for t in tiles]
    assert got == [_files_of_box(files, np.asarray(t["lo"]), np.asarray(t["hi"])) for t in tiles]
    assert {f for g in got for f in g or []} == {f.name for f in files}
    assert tile_files(tmp_path / "elsewhere", 0) is None


def test_failure_note_names_at_most_four_files():
    from lodbuilder.build.tiled.timing import failure_note

    exc = ValueError("x")
    assert failure_note(exc) == ""  # no task marked it
    exc.lodbuilder_task = {"pid": 77, "files": [f"f{i}.laz" for i in range(6)]}
    assert failure_note(exc, "ordering of tile 2 of 9") == " (files f0.laz, f1.laz, f2.laz, f3.laz and 2 more; worker 77)"
    exc.lodbuilder_task = {"pid": 77, "files": None}
    assert failure_note(exc, "covering of tile 1 of 9") == " (worker 77)"
    exc.lodbuilder_task = {"pid": 77, "files": ["a.laz"]}
    assert failure_note(exc, "reading /data/a.laz") == " (worker 77)"  # the file is named already


def test_timed_tasks_log_their_timing_and_the_table_names_them(tmp_path):
    from lodbuilder.build.tiled.timing import TASK_COLUMNS, task_table, timed_task

    @timed_task
    def order_tile(work, t):
        return {"tile": t}

    @timed_task
    def survey_block(work, b, boom=False):
        if boom:
            raise ValueError("bad block")
        return {}

    started = __import__("time").time()
    res = order_tile(str(tmp_path), 3)
    assert res["tile"] == 3 and set(res["timing"]) == {"kind", "start", "seconds", "cpu_seconds", "pid", "peak_rss"}
    assert res["timing"]["kind"] == "order_tile" and res["timing"]["pid"] == os.getpid()
    order_tile(str(tmp_path), 3)  # its second pass
    survey_block(str(tmp_path), 0)
    survey_block(str(tmp_path), 0)  # the plan's second pass over the blocks
    with pytest.raises(ValueError, match="bad block") as exc:
        survey_block(str(tmp_path), 1, boom=True)
    assert exc.value.lodbuilder_task["kind"] == "survey_block" and exc.value.lodbuilder_task["block"] == 1
    assert exc.value.lodbuilder_task["files"] is None  # no read phase here: not known
    table = task_table(tmp_path, started)
    assert table["columns"] == list(TASK_COLUMNS)
    rows = [dict(zip(TASK_COLUMNS, r, strict=True)) for r in table["rows"]]
    assert sorted(r["piece"] for r in rows) == ["order.3.1", "order.3.2", "survey_block.0", "survey_block.0#2"]
    assert all(r["pid"] == os.getpid() and r["start"] >= 0 and r["cpu_seconds"] >= 0 for r in rows)
    assert [r["tile"] for r in rows if r["kind"] == "order_tile"] == [3, 3]


@pytest.mark.skipif(not os.path.exists("/proc/self/clear_refs"), reason="Linux's per-process peak reset")
def test_timed_tasks_record_their_own_peak_resident_memory(tmp_path):
    import numpy as np

    from lodbuilder.build.tiled.timing import TASK_COLUMNS, peak_rss, task_table, timed_task

    block = 200 << 20

    @timed_task
    def big_task(work, t):
        a = np.ones(block // 8)  # touched: resident
        return {"sum": float(a[::4096].sum())}

    @timed_task
    def small_task(work, t):
        return {}

    started = __import__("time").time()
    big = big_task(str(tmp_path), 0)["timing"]["peak_rss"]
    small = small_task(str(tmp_path), 1)["timing"]["peak_rss"]
    now = peak_rss()
    assert big >= block  # the task's block, at least
    # the peak was reset when the next task started: it holds the process's own footprint, not the block
    assert small < big - block // 2 and now is not None
    rows = [dict(zip(TASK_COLUMNS, r, strict=True)) for r in task_table(tmp_path, started)["rows"]]
    assert {r["kind"]: r["peak_rss"] for r in rows} == {"big_task": big, "small_task": small}


#: a task that frees COUNT small arrays of 64 kB (glibc's heap) between every 100th, which it keeps
HEAP_TASK = """
import sys
import numpy as np
from lodbuilder.build.tiled.timing import timed_task

def rss():
    with open("/proc/self/status") as f:
        return next(int(x.split()[1]) * 1024 for x in f if x.startswith("VmRSS:"))

pinned = []

@timed_task
def many_small(work, t):
    parts = [np.ones(8_000) for _ in range(int(sys.argv[2]))]
    pinned.extend(parts[99::100])  # every 100th kept: the freed ones lie between kept blocks
    del parts
    return {}

before = rss()
many_small(sys.argv[1], 0)
print(rss() - before)
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="Linux's /proc")
@pytest.mark.parametrize("count, trimmed", [(5_000, True), (1_500, False)])
def test_a_worker_gives_back_what_a_large_task_freed(tmp_path, count, trimmed):
    """Small arrays come from glibc's heap, which keeps them once freed while blocks after them
    are in use: a worker would hold a large task's peak through its next tasks (a fresh process:
    the heap's layout is this script's own). A task that grew less than TRIM_GROWTH (1,500 arrays:
    96 MB) leaves its heap for the next task to reuse."""
    import subprocess
    import sys

    from lodbuilder.build.tiled.timing import TRIM_GROWTH

    assert 1_500 * 64_000 < TRIM_GROWTH < 5_000 * 64_000
    out = subprocess.run([sys.executable, "-c", HEAP_TASK, str(tmp_path), str(count)], capture_output=True,
                         text=True, check=True)
    if trimmed:
        assert int(out.stdout) < 64 << 20
    else:
        assert int(out.stdout) > 64 << 20


def test_the_cli_prints_task_lines_of_a_joint_build_without_a_terminal(tmp_path, monkeypatch, capsys):
    from lodbuilder.build.tiled import plan
    from lodbuilder.cli.main import main

    files = _small_survey(tmp_path)
    monkeypatch.setattr(plan, "needs_tiling", lambda *a, **k: True)  # (the survey is tiny: tiles anyway)
    monkeypatch.setattr(plan, "tile_capacity", lambda *a, **k: 700)
    rc = main(["build", str(files[0].parent), "--joint", "s", "-o", str(tmp_path / "s.h5"), "--workers", "1",
               "--max-memory", "2GB"])
    assert rc == 0
    err = capsys.readouterr().err.splitlines()
    for stage in ("tiles", "covering"):
        lines = [x for x in err if x.startswith(f"{stage}: ")]
        assert re.fullmatch(rf"{stage}: 0 of (\d+) tiles, 0 of 4,400 points(, \d+ queued or running)?", lines[0]), lines
        n = int(re.match(rf"{stage}: 0 of (\d+)", lines[0]).group(1))
        assert re.fullmatch(rf"{stage}: {n} of {n} tiles, 4,400 of 4,400 points in \d+ s \(([\d,]+|\d+\.\d\d M) points/s\)",
                            lines[-1]), lines
    rc = main(["build", str(files[0].parent), "--joint", "s2", "-o", str(tmp_path / "s.h5"), "--workers", "1",
               "--max-memory", "2GB", "--json"])
    assert rc == 0 and not [x for x in capsys.readouterr().err.splitlines() if x.startswith(("tiles: ", "covering: "))]
