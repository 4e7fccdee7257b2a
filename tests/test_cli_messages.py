"""CLI messages (reliability-3 items 21 and 22): a typo'd option is named with the closest valid
one (`slice A --rhoo 0.002` said "one of the arguments --rho --size --fraction is required");
errors point to the subcommand's help (`--extar` pointed to `lodbuilder --help`); `depths 0..d`
says the number; one thousands-separator style; the 16-bit PLY colour caveat in --help."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from clirun import run

from lodbuilder.cli.main import main


@pytest.mark.parametrize(
    "argv,line",
    [
        (["slice", "A.h5", "--rhoo", "0.002", "-o", "x.ply"],
         "lodbuilder slice: error: unknown option --rhoo: did you mean --rho? "
         "(see 'lodbuilder slice --help')"),
        (["slice", "A.h5", "--rho", "0.002", "--extar", "-o", "x.ply"],
         "lodbuilder slice: error: unknown option --extar: did you mean --extra? "
         "(see 'lodbuilder slice --help')"),
        (["build", "F.ply", "-0", "x.h5"],
         "lodbuilder build: error: unknown option -0: did you mean -o? "
         "(see 'lodbuilder build --help')"),
        (["info", "A.h5", "--jsn"],
         "lodbuilder info: error: unknown option --jsn: did you mean --json? "
         "(see 'lodbuilder info --help')"),
        (["slice", "A.h5", "--rho", "1", "-o", "x.ply", "--zzzzzz"],
         "lodbuilder slice: error: unknown option --zzzzzz (see 'lodbuilder slice --help')"),
        (["info", "A.h5", "B.h5"],
         "lodbuilder info: error: unrecognized arguments: B.h5 (see 'lodbuilder info --help')"),
        (["-v", "slice", "A.h5", "--rhoo=1", "-o", "x.ply"],
         "lodbuilder slice: error: unknown option --rhoo: did you mean --rho? "
         "(see 'lodbuilder slice --help')"),
    ],
)
def test_a_typo_is_named(capsys, argv, line):
    with pytest.raises(SystemExit) as e:
        main(argv)
    out, err = capsys.readouterr()
    assert e.value.code == 2 and out == "" and err == line + "\n"


@pytest.mark.parametrize(
    "argv",
    [
        ["slice", "A.h5", "--rho", "-1", "-o", "x.ply"],  # a negative value, not an option
        ["slice", "A.h5", "--box", "-1", "-1", "-1", "1", "1", "1", "--box-rho", "0.1", "--rho",
         "0.2", "-o", "x.ply"],
        ["slice", "A.h5", "--fr", "0.5", "-o", "x.ply"],  # an abbreviation argparse accepts
        ["info", "--", "--odd-name.h5"],
    ],
)
def test_values_and_abbreviations_are_not_typos(capsys, argv):
    try:  # the archive does not exist: a later, other error
        code = main(argv)
    except SystemExit as e:
        code = e.code
    err = capsys.readouterr().err
    assert "unknown option" not in err and "unrecognized" not in err, err
    assert code == 2 and "A.h5" in err or "odd-name" in err, err


def test_colour_depth_help_says_cloudcompare(capsys):
    with pytest.raises(SystemExit):
        main(["slice", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert ("--colour-depth {8,16} PLY colour: 8 (uchar, the default: every viewer reads it) or "
            "16 (ushort; CloudCompare 2.11 shows 16-bit PLY colour as black)") in text



def test_a_rerun_demo_says_it_reused_the_archive(tmp_path, capsys):
    d = tmp_path / "demo"
    code, out, _ = run(capsys, "demo", "-o", d, "--points", "2000", "--no-progress")
    assert code == 0 and out.splitlines()[0].startswith(f"built {d / 'demo.h5'} from a generated wavy ")
    code, out, _ = run(capsys, "demo", "-o", d, "--points", "2000", "--no-progress")
    assert code == 0
    assert out.splitlines()[0] == (
        f"reused {d / 'demo.h5'}: it already holds the generated wavy surface of 2,000 points "
        "(same seed and parameters); the levels were written again")


def test_one_thousands_separator_style(tmp_path, capsys):
    pts = np.random.default_rng(0).random((1500, 3))
    src = tmp_path / "s.npy"
    np.save(src, pts)
    a = tmp_path / "a.h5"
    code, out, _ = run(capsys, "build", src, "-o", a, "--no-progress")
    assert code == 0 and "(1,500 points, float64 coordinates)" in out, out
    code, out, _ = run(capsys, "slice", a, "--size", "1200", "-o", tmp_path / "x.ply")
    assert code == 0 and out.startswith("wrote 1,200 of 1,500 points of scan 's'"), out
    code, out, _ = run(capsys, "validate", a)
    assert code == 0 and "valid (1 scan(s), 1,500 points" in out, out


def test_copc_depths_say_their_number(tmp_path, capsys):
    pytest.importorskip("copclib")
    pts = np.random.default_rng(0).random((3000, 3))
    src = tmp_path / "s.npy"
    np.save(src, pts)
    a = tmp_path / "a.h5"
    assert run(capsys, "build", src, "-o", a, "--no-progress")[0] == 0
    code, out, _ = run(capsys, "export", a, "-o", tmp_path / "x.copc.laz")
    assert code == 0
    line = next(ln for ln in out.splitlines() if "depths 0.." in ln)
    depths = int(out.split(" depth(s)")[0].rsplit("(", 1)[1].split(", ")[-1])
    assert line.startswith(f"  depths 0..{depths - 1} hold "), line


@pytest.mark.data
def test_the_readme_igea_build_warns_nothing(shared_data, tmp_path, capsys, caplog):
    """The README's Igea build printed 'WARNING lodbuilder.sampling.adaptive: density floor: 1
    weighted radii above the floor's last radius, capped', which nobody could act on."""
    code, out, err = run(capsys, "build", shared_data / "igea.ply", "-o", tmp_path / "igea.h5",
                         "--importance", "curvature", "--adaptive", "0.5", "--density-floor",
                         "0.002", "--no-progress")
    assert code == 0 and err == "", err
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []


def test_a_joint_build_shows_its_stages_without_a_terminal(tmp_path):
    """A collection build prints a line per scan; a joint build (one long scan) printed nothing
    until its end. Without a terminal each of its stages now says it started."""
    import subprocess
    import sys

    rng = np.random.default_rng(0)
    for i in range(2):
        np.save(tmp_path / f"s{i}.npy", rng.random((800, 3)) + i)
    r = subprocess.run([sys.executable, "-m", "lodbuilder.cli.main", "build", tmp_path / "s0.npy",
                        tmp_path / "s1.npy", "--joint", "-o", tmp_path / "j.h5"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln != "compiling kernels, first run only ..."]
    assert lines[0] == "read ..." and lines[-1].startswith("write: 1 of 1 band, 1,600 of 1,600 points in "), lines
    # a stage line each; the task phases (tiles, covering, the write's bands) count their tasks and
    # points instead
    stages = [ln for ln in lines if not ln.startswith(("tiles: ", "covering: ", "write: "))]
    assert len(stages) >= 4 and all(ln.endswith(" ...") for ln in stages), lines
    assert any(ln.startswith("tiles: 1 of 1 tile, 1,600 of 1,600 points in ") for ln in lines), lines
    r = subprocess.run([sys.executable, "-m", "lodbuilder.cli.main", "build", tmp_path / "s0.npy",
                        tmp_path / "s1.npy", "--joint", "-o", tmp_path / "k.h5", "--no-progress"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stderr == "", r.stderr


def test_info_counts_bytes_with_commas(tmp_path, capsys):
    pts = np.random.default_rng(0).random((1500, 3))
    src = tmp_path / "s.npy"
    np.save(src, pts)
    a = tmp_path / "a.h5"
    assert run(capsys, "build", src, "-o", a, "--no-progress")[0] == 0
    code, out, _ = run(capsys, "info", a)
    assert code == 0
    size = src.stat().st_size
    assert f"  source     s.npy ({size:,} bytes, sha256 " in out, out
