"""``--json``, ``-q`` and ``-v`` on every command that reports something, and the findings of
reliability-2.md item 13 that belong to the command line: one-line errors whatever the names they
quote, ``--rho-max`` without ``--viewpoint`` refused, one output-path rule for every command."""

from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import clirun
import numpy as np
import pytest
from clirun import run

import lodbuilder
from lodbuilder.cli.main import main
from lodbuilder.datasets import demo_scan

ROOT = Path(__file__).resolve().parents[1]




def one_line_error(capsys, argv, cmd):
    assert argv[0] == cmd
    return clirun.one_line_error(capsys, cmd, *argv[1:])


@pytest.fixture(scope="module")
def arc(small_archive):
    return small_archive(800, seed=5, scan="sheet", filename="a.h5")


@pytest.fixture(scope="module")
def odd_names(tmp_path_factory):
    """An archive whose scan names hold a newline and a tab."""
    path = tmp_path_factory.mktemp("odd") / "odd.h5"
    for name in ("a\nb", "c\td"):
        lodbuilder.build_archive(demo_scan(300, seed=1, name=name), path)
    return path


# --- --json ---------------------------------------------------------------------------------


def test_slice_json_matches_the_text(arc, tmp_path, capsys):
    out = tmp_path / "l.ply"
    rc, text, _ = run(capsys, "slice", arc, "--fraction", "0.25", "-o", out)
    assert rc == 0 and text.startswith("wrote 200 of 800 points of scan 'sheet' to ")
    rc, js, _ = run(capsys, "slice", arc, "--fraction", "0.25", "-o", out, "--json")
    doc = json.loads(js)
    with lodbuilder.open_archive(arc) as a:
        lev = a.scan().level(fraction=0.25)
    assert doc == {
        "archive": str(arc),
        "scan": "sheet",
        "output": str(out),
        "size": 200,
        "n_points": 800,
        "rho": lev.rho,
        "ordering": "uniform",
        "bound": f"covering radius <= {lev.rho:.6g}",
        "region": {},
        "attributes": sorted(lev.attributes),
        "crs": None,
        "units": None,
        "changes": [],
        "pieces": 1,
        "pieces_reached": 1,
        "first_point_only": False,
    }
    rc, js, _ = run(capsys, "slice", arc, "--rho", "0.05", "--box", 0, 0, -1, 0.3, 0.3, 1,
                    "--box-rho", "0.02", "-o", out, "--json")  # fmt: skip
    assert json.loads(js)["region"] == {
        "box": [[0.0, 0.0, -1.0], [0.3, 0.3, 1.0]],
        "rho_inner": 0.02,
        "rho_outer": 0.05,
    }


def test_info_validate_evaluate_demo_json(arc, tmp_path, capsys):
    rc, js, _ = run(capsys, "info", arc, "--json")
    info = json.loads(js)
    assert rc == 0 and info["scans"][0]["name"] == "sheet" and info["scans"][0]["n_points"] == 800
    rc, js, _ = run(capsys, "validate", arc, "--json")
    assert rc == 0 and json.loads(js) == {
        "archive": str(arc),
        "valid": True,
        "faults": [],
        "scans": 1,
        "points": 800,
        "schema_version": info["schema_version"],
    }
    rc, js, _ = run(capsys, "evaluate", arc, "--sizes", "8", "80", "--json", "-")
    assert rc == 0 and [lv["size"] for lv in json.loads(js)["levels"]] == [8, 80]
    rc, js, _ = run(capsys, "demo", "-o", tmp_path / "demo", "--points", "300", "--json")
    doc = json.loads(js)
    assert (
        rc == 0 and doc["n_points"] == 300 and [lv["size"] for lv in doc["levels"]] == [3, 15, 75]
    )
    assert all(Path(lv["output"]).is_file() for lv in doc["levels"])


def test_validate_json_lists_faults(arc, tmp_path, capsys):
    import shutil

    import h5py

    bad = tmp_path / "bad.h5"
    shutil.copy(arc, bad)
    with h5py.File(bad, "r+") as f:
        r = f["scans/sheet/radius"]
        r[10] = r[5] * 10  # radii must not increase
    rc, js, err = run(capsys, "validate", bad, "--json")
    doc = json.loads(js)
    assert rc == 1 and doc["valid"] is False and doc["faults"] and err == ""
    rc, text, err = run(capsys, "validate", bad)
    assert rc == 1 and text == f"{bad}: INVALID ({len(doc['faults'])} fault(s))\n"
    assert err.splitlines() == [f"lodbuilder validate: {bad}: {f}" for f in doc["faults"]]


# --- -q and -v --------------------------------------------------------------------------------


def test_quiet_prints_nothing_but_errors(arc, tmp_path, capsys):
    src = tmp_path / "in.npy"
    np.save(src, demo_scan(300, seed=2).points)
    for argv in (
        ["build", src, "-o", tmp_path / "b.h5"],
        ["build", src, "-o", tmp_path / "c.h5", "--workers", "1"],  # a collection build
        ["slice", arc, "--size", "5", "-o", tmp_path / "q.ply"],
        ["info", arc],
        ["validate", arc],
        ["evaluate", arc, "--sizes", "8"],
        ["demo", "-o", tmp_path / "d", "--points", "200"],
    ):
        rc, out, err = run(capsys, *argv, "-q")
        assert (rc, out, err) == (0, "", ""), argv
    assert (tmp_path / "q.ply").is_file()
    rc, out, err = run(capsys, "-q", "info", tmp_path / "none.h5")  # before the command too
    assert rc == 2 and out == "" and "none.h5 does not exist" in err
    rc, out, _ = run(capsys, "evaluate", arc, "--sizes", "8", "--json", "-", "-q")
    assert json.loads(out)["levels"][0]["size"] == 8  # the report asked for is still given


def test_verbose_shows_the_library_log(arc, tmp_path, caplog, capsys):
    out = tmp_path / "v.ply"
    with caplog.at_level(logging.DEBUG):
        main(["slice", str(arc), "--size", "5", "-o", str(out)])
        assert not [r for r in caplog.records if r.name.startswith("lodbuilder")]
        main(["slice", str(arc), "--size", "5", "-o", str(out), "-v"])
        assert [r.getMessage() for r in caplog.records if r.name == "lodbuilder.io.api"] == [
            f"wrote 5 points to {out} (ply)"
        ]
    assert logging.getLogger("lodbuilder").level == logging.NOTSET  # left as it was


def test_verbose_log_lines_reach_stderr(arc, tmp_path):
    out = tmp_path / "v.ply"
    proc = subprocess.run(
        [sys.executable, "-m", "lodbuilder.cli.main", "-v", "slice", str(arc), "--size", "5",
         "-o", str(out)],
        capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == f"INFO lodbuilder.io.api: wrote 5 points to {out} (ply)\n"
    assert re.fullmatch(r"read the level in \d+\.\d ms\nwrote 5 of 800 points .*\n", proc.stdout)


# --- finding 13: one line whatever the names ------------------------------------------------


def test_scan_names_with_newlines_stay_on_one_line(odd_names, tmp_path, capsys):
    out = tmp_path / "o.ply"
    msg = one_line_error(capsys, ["slice", odd_names, "--size", "3", "-o", out], "slice")
    assert msg == (
        f"archive {odd_names} holds 2 scans; choose one with --scan (one of 'a\\nb', 'c\\td')"
    )
    msg = one_line_error(
        capsys, ["slice", odd_names, "--scan", "x\ny", "--size", "3", "-o", out], "slice"
    )
    assert msg == f"archive {odd_names} has no scan 'x\\ny'; it holds 'a\\nb', 'c\\td'"
    msg = one_line_error(capsys, ["info", odd_names, "--scan", "nope"], "info")
    assert msg == f"archive {odd_names} has no scan 'nope'; it holds 'a\\nb', 'c\\td'"
    rc, text, _ = run(capsys, "info", odd_names)
    assert rc == 0 and "scan 'a\\nb': 300 points" in text and "\nb" not in text


def test_paths_with_newlines_stay_on_one_line(arc, tmp_path, capsys):
    out = tmp_path / "no\ndir" / "x.ply"
    msg = one_line_error(capsys, ["slice", arc, "--size", "3", "-o", out], "slice")
    d = str(tmp_path).replace("\n", "\\n")
    assert (
        msg
        == f"-o {d}/no\\ndir/x.ply: output directory {d}/no\\ndir does not exist; create it first"
    )


# --- finding 13: --rho-max without --viewpoint -------------------------------------------------


def test_rho_max_needs_a_viewpoint(arc, tmp_path, capsys):
    out = tmp_path / "o.ply"
    msg = one_line_error(
        capsys, ["slice", arc, "--rho", "0.05", "--rho-max", "0.2", "-o", out], "slice"
    )
    assert msg == "--rho-max caps rho far from --viewpoint: give --viewpoint X Y Z and --slope"
    assert not out.exists()
    rc, _, err = run(capsys, "slice", arc, "--rho", "0.02", "--viewpoint", 0, 0, 0, "--slope", "0.5",
                     "--rho-max", "0.1", "-o", out)  # fmt: skip
    assert rc == 0, err


# --- finding 13: one output-path rule ---------------------------------------------------------


@pytest.mark.parametrize(
    "cmd,argv,opt",
    [
        ("slice", ["--size", "3", "-o", "{missing}/o.ply"], "-o"),
        ("evaluate", ["--sizes", "5", "--json", "{missing}/q.json"], "--json"),
        ("evaluate", ["--sizes", "5", "--plot", "{missing}/q.png"], "--plot"),
        ("view", ["--screenshot", "{missing}/s.png"], "--screenshot"),
        ("view", ["--animate", "{missing}/a.gif"], "--animate"),
    ],
)
def test_no_command_creates_a_missing_directory(arc, tmp_path, capsys, cmd, argv, opt):
    missing = tmp_path / "not" / "there"
    args = [a.format(missing=missing) for a in argv]
    msg = one_line_error(capsys, [cmd, arc, *args], cmd)
    target = args[args.index(opt) + 1]
    assert msg == f"{opt} {target}: output directory {missing} does not exist; create it first"
    assert list(tmp_path.iterdir()) == []


def test_demo_output_directory_rule(tmp_path, capsys):
    msg = one_line_error(capsys, ["demo", "-o", tmp_path / "a" / "b"], "demo")
    assert msg == f"output directory {tmp_path / 'a'} does not exist; create it first"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "cmd,argv,opt",
    [
        ("slice", ["--size", "3", "-o", "{arc}"], "-o"),
        ("evaluate", ["--json", "{arc}"], "--json"),
        ("view", ["--screenshot", "{arc}"], "--screenshot"),
    ],
)
def test_no_command_overwrites_its_archive(arc, capsys, cmd, argv, opt):
    before = arc.read_bytes()
    msg = one_line_error(capsys, [cmd, arc, *[a.format(arc=arc) for a in argv]], cmd)
    if opt == "--screenshot":
        assert msg == f"--screenshot {arc} must end in .png"
    else:
        assert msg == f"{opt} {arc} is the input archive; choose another output"
    assert arc.read_bytes() == before


def test_slice_to_stdout_is_refused(arc, capsys):
    msg = one_line_error(capsys, ["slice", arc, "--size", "3", "-o", "-"], "slice")
    assert msg == "-o - (stdout) is not possible here; give a file name"


def test_library_writers_do_not_create_directories(tmp_path):
    from lodbuilder.errors import ScanFileError
    from lodbuilder.quality.plots import plot_quality
    from lodbuilder.quality.report import evaluate_level

    pts = np.random.default_rng(0).random((50, 3))
    rep = evaluate_level(pts, pts[:10])
    with pytest.raises(ScanFileError, match="does not exist; create it first"):
        plot_quality([rep], tmp_path / "new" / "q.png")
    assert list(tmp_path.iterdir()) == []


# --- what a writer changed: reported once, the same way by slice and export -----------------


def _changes(out):
    return [
        f"{out}: coordinates quantised to scale 0.0001 (error <= 5e-05) with offset 0, 0, -0.1",
        f"{out}: blue: 8-bit values scaled x 257 into the 16-bit LAS field",
        f"{out}: green: 8-bit values scaled x 257 into the 16-bit LAS field",
        f"{out}: red: 8-bit values scaled x 257 into the 16-bit LAS field",
    ]


@pytest.mark.parametrize("cmd, name", [("slice", "c.las"), ("export", "c.copc.laz")])
def test_changes_are_printed_once(arc, tmp_path, cmd, name):
    """Before: slice printed every change twice, as 'changed:' on stdout and as a WARNING log
    line on stderr (export once)."""
    if cmd == "export":
        pytest.importorskip("copclib")
    out = tmp_path / name
    proc = subprocess.run(
        [sys.executable, "-m", "lodbuilder.cli.main", cmd, str(arc), "--size", "100", "-o", str(out)],
        capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].startswith(f"wrote 100 of 800 points of scan 'sheet' to {out} (")
    assert [x for x in lines if "changed" in x] == [f"  changed: {c}" for c in _changes(out)]


@pytest.mark.parametrize("cmd, name", [("slice", "j.las"), ("export", "j.copc.laz")])
def test_json_lists_the_changes_even_when_quiet(arc, tmp_path, capsys, cmd, name):
    """Before: 'slice -q --json' reported "changes": [] (the warnings were below the log level)."""
    if cmd == "export":
        pytest.importorskip("copclib")
    out = tmp_path / name
    for quiet in ([], ["-q"]):
        rc, js, err = run(capsys, cmd, arc, "--size", "100", "-o", out, "--json", *quiet)
        assert rc == 0 and err == ""
        assert json.loads(js)["changes"] == _changes(out)
