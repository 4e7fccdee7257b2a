"""slice and evaluate say what a level is: the pieces of the scan it reaches, and a rho so coarse
that the level is the first point only (issue 20 item 5, finding 21 of reliability-3)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from clirun import run as run_cli

import lodbuilder
from lodbuilder.cli.main import main

REPO = Path(__file__).resolve().parents[1]



@pytest.fixture(scope="module")
def fragmented(tmp_path_factory):
    spec = importlib.util.spec_from_file_location("make_fragmented", REPO / "tools" / "make_fragmented.py")
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(mod)
    d = tmp_path_factory.mktemp("facts")
    np.save(d / "fr.npy", mod.fragmented_scene(2, 100, 20_000))
    assert main(["build", str(d / "fr.npy"), "-o", str(d / "fr.h5"), "--no-progress"]) == 0
    with lodbuilder.open_archive(d / "fr.h5") as arc:
        scan = arc.scan()
        stats = scan.build["engine_stats"]
        entries, total = stats["piece_entries"], stats["pieces"]
        order = np.asarray(scan.source_index[:])
    return d / "fr.h5", entries, total, order


def test_piece_entries_are_the_first_rank_of_each_piece(fragmented):
    _, entries, total, _ = fragmented
    assert total > 20 and len(entries) == total
    assert entries == sorted(entries) and entries[0] == 0 and len(set(entries)) == total


def test_slice_says_how_many_pieces_a_level_reaches(fragmented, tmp_path, capsys):
    arc, entries, total, _ = fragmented
    k = 50
    reached = sum(e < k for e in entries)
    rc, out, err = run_cli(capsys, "slice", arc, "--size", k, "-o", tmp_path / "x.ply")
    assert rc == 0, err
    assert out.strip().endswith(f"; reaches {reached} of the scan's {total} pieces)")
    rc, out, err = run_cli(capsys, "slice", arc, "--size", k, "-o", tmp_path / "y.ply", "--json")
    doc = json.loads(out)
    assert doc["pieces_reached"] == reached and doc["pieces"] == total and doc["first_point_only"] is False


def test_slice_above_the_largest_radius_says_first_point(tmp_path, capsys, shared_data):
    arc = tmp_path / "b.h5"
    assert main(["build", str(shared_data / "bun_zipper_res3.ply"), "-o", str(arc), "--no-progress"]) == 0
    capsys.readouterr()
    with lodbuilder.open_archive(arc) as a:
        top = float(a.scan().radius[1])
    rc, out, err = run_cli(capsys, "slice", arc, "--rho", "100", "-o", tmp_path / "x.ply")
    assert rc == 0, err
    assert out.strip() == (
        f"wrote 1 of 1,889 points of scan 'bun_zipper_res3' to {tmp_path / 'x.ply'} (covering radius <= "
        f"{top:.6g}; rho 100 is at least the scan's largest finite radius {top:.4g}: the level is the first "
        "point only; ask for a smaller rho for more)"
    )
    rc, out, err = run_cli(capsys, "slice", arc, "--rho", f"{top / 2}", "-o", tmp_path / "y.ply")
    assert "first point only" not in out and "pieces" not in out  # one piece: nothing to say
    rc, out, err = run_cli(capsys, "evaluate", arc, "--rhos", "100")
    assert (f"level rho=100: rho is at least the scan's largest finite radius {top:.4g}: the level is the "
            "first point only; ask for a smaller rho for more") in out


def test_evaluate_lists_the_pieces(fragmented, capsys):
    arc, entries, total, _ = fragmented
    rc, out, err = run_cli(capsys, "evaluate", arc, "--sizes", "1", "50")
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[1].rstrip().endswith("pieces")
    assert lines[2].rstrip().endswith(f"1/{total}")
    assert lines[3].rstrip().endswith(f"{sum(e < 50 for e in entries)}/{total}")
