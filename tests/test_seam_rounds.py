"""The build option ``seam_rounds`` (``--seam-rounds``): the tiles of a tiled or joint build ordered
in radius rounds (lodbuilder.build.tiled.rounds). The rounds' orders, guarantees and parallel
schedule are tested in test_rounds_parallel.py and test_resume_tiled.py; here the option itself."""

from __future__ import annotations

import itertools
import re

import numpy as np
import pytest
from clirun import one_line_error, run
from naive import prefix_covering_radii
from test_tiled import wavy

import lodbuilder
from lodbuilder.build.options import BuildOptions
from lodbuilder.build.tiled import affinity, rounds
from lodbuilder.errors import InputError
from lodbuilder.io import write_points


def test_the_option_is_checked_and_enters_the_key_only_when_on():
    assert BuildOptions.make().seam_rounds is False
    assert "seam_rounds" not in BuildOptions.make().key_params  # (a default never changes a key)
    assert BuildOptions.make(seam_rounds=True).key_params["seam_rounds"] is True
    with pytest.raises(InputError, match=r"^seam_rounds must be True or False, got 'yes'$"):
        BuildOptions.make(seam_rounds="yes")
    with pytest.raises(InputError, match=r"^seam_rounds order the tiles in one pass of rounds; drop _tile_passes "
                                         r"or seam_rounds$"):
        BuildOptions.make(seam_rounds=True, tile_passes=2)


def test_the_rounds_go_down_to_about_the_level_of_depth_points(monkeypatch):
    # R = ln(DEPTH n / head) / (2 ln q), rounded up: a level's radius falls as the square root of its size
    assert rounds.schedule(200_000, 256) == (38, 1.05)
    assert rounds.schedule(21_560_000, 3_493) == (59, 1.05)
    n, head = 1_000_000, 725
    r, q = rounds.schedule(n, head)
    assert q ** (2 * (r - 1)) < rounds.DEPTH * n / head <= q ** (2 * r)
    assert rounds.schedule(100, 50) == (1, 1.05)  # (a head of more than DEPTH x n points: one round)
    monkeypatch.setattr(rounds, "TILE_ROUNDS", (6, 1.25))  # (the private override of the benchmarks)
    assert rounds.schedule(n, head) == (6, 1.25)


@pytest.fixture
def halves(tmp_path):
    p = wavy(6000, np.random.default_rng(5))
    left = p[:, 0] < np.median(p[:, 0])
    return write_points(tmp_path / "a.npy", p[left]), write_points(tmp_path / "b.npy", p[~left]), p[left], p[~left]


def test_a_joint_build_with_seam_rounds_records_them_and_keeps_the_guarantees(tmp_path, capsys, halves):
    a, b, pa, pb = halves
    seen = []

    class Progress:
        def __call__(self, *a):
            pass

        def tasks(self, stage, counts):
            if stage == "tiles":
                seen.append(counts)

    lodbuilder.build_archive([a, b], tmp_path / "j.h5", joint="j", seam_rounds=True, workers=2, _tile_points=700,
                             progress=Progress())
    with lodbuilder.open_archive(tmp_path / "j.h5") as arc:
        v = arc.scan("j")
        tiled, stored, radius, rows = v.build["tiled"], v.points(), v.radius[:], v.build["tasks"]["rows"]
    info = tiled["rounds"]
    assert tiled["tiles"] >= 4, tiled["tiles"]
    assert info["owners"] == 2
    assert (info["rounds"], info["q"]) == rounds.schedule(len(stored), tiled["head_points"])
    assert {r[0] for r in rows if r[0].startswith(("order_", "round_"))} == {"round_steps", "round_finish"}
    # the order phase tells its tile rounds and the tiles' points ordered so far, to the end
    n_rounds = tiled["tiles"] * (info["rounds"] + 1)
    assert {c.unit for c in seen} == {"tile round"} and {c.total for c in seen} == {n_rounds}
    assert seen[0].done == seen[0].points_done == 0 and seen[-1].done == n_rounds
    assert seen[-1].points_done == seen[-1].points_total == len(stored)
    assert all(x.points_done <= y.points_done for x, y in itertools.pairwise(seen))
    rc, out, _ = run(capsys, "info", tmp_path / "j.h5")
    assert rc == 0 and (f"tiled ({tiled['tiles']} tiles, in {info['rounds']} seam rounds of ratio 1.05, seam spacing "
                        "0.25: points of different tiles at least 0.2 x the level's radius apart)") in out
    # every point once, every stored radius a true covering radius of the whole survey (brute force)
    pts = np.concatenate([pa, pb])
    n = len(pts)
    assert np.array_equal(np.unique(stored, axis=0), np.unique(pts, axis=0)) and len(stored) == n
    cr = prefix_covering_radii(stored, np.arange(n))
    assert np.all(cr[1:n] <= radius[1:n] * (1 + 1e-12))


def test_seam_rounds_the_workers_cannot_hold_are_refused_on_the_command_line(tmp_path, capsys, halves,
                                                                             monkeypatch):
    a, b, _, _ = halves
    monkeypatch.setattr(affinity, "STATE_BYTES_PER_POINT", 10**7)
    msg = one_line_error(capsys, "build", a, b, "--joint", "j", "--seam-rounds", "--workers", "2", "--max-memory",
                         "2GiB", "-o", tmp_path / "j.h5", "--no-progress")
    least = 10**7 * -(-(len(halves[2]) + len(halves[3])) // 2) / 2**30  # (half the points' states)
    assert re.fullmatch(rf"seam rounds need at least {least:.2f} GiB in each of 2 worker\(s\) for the tiles' ordering "
                        r"states, over the 0\.39 GiB each has of max_memory=2\.00 GiB; give max_memory of at least "
                        r"\d+ GiB, or build without seam rounds", msg), msg
    assert not (tmp_path / "j.h5").exists()
