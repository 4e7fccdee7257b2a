"""The pieces every command shares (lodbuilder/cli/output.py): levels, JSON, one-line errors and
the output-path rule."""

from __future__ import annotations

import argparse
import json
import logging

import numpy as np
import pytest

from lodbuilder.cli import output as O
from lodbuilder.cli.main import COMMANDS, build_parser
from lodbuilder.errors import InputError, ScanFileError


def ns(**kw):
    return argparse.Namespace(**kw)


def test_every_command_has_quiet_and_verbose_levels():
    parser = build_parser()
    for cmd in COMMANDS:
        p = parser._subparsers._group_actions[0].choices[cmd]  # type: ignore[union-attr]
        opts = {s for a in p._actions for s in a.option_strings}
        assert {"-q", "--quiet", "-v", "--verbose"} <= opts, cmd


@pytest.mark.parametrize(
    "argv,level",
    [
        ([], O.NORMAL),
        (["-q"], O.QUIET),
        (["-v"], O.VERBOSE),
        (["-vv"], O.DEBUG),
        (["-v", "-v", "-v"], O.DEBUG),
        (["-q", "-v"], O.QUIET),
    ],
)
def test_verbosity_levels(argv, level):
    args = build_parser().parse_args(["info", "a.h5", *argv])
    assert O.verbosity(args) == level


def test_logging_follows_the_level():
    log = logging.getLogger("lodbuilder")
    before = log.level
    try:
        for q, v, want in [
            (True, 0, logging.ERROR),
            (False, 0, logging.WARNING),
            (False, 1, logging.INFO),
            (False, 2, logging.DEBUG),
        ]:
            O.setup_logging(ns(quiet=q, verbose=v))
            assert log.level == want
    finally:
        log.setLevel(before)


def test_emit_text_json_quiet(capsys, tmp_path):
    doc = {"size": np.int64(3), "rho": np.float64(0.5), "radius": np.array([np.inf, 1.0])}
    O.emit(ns(json=False, quiet=False, verbose=0), doc, "three points")
    assert capsys.readouterr().out == "three points\n"
    O.emit(ns(json=False, quiet=True, verbose=0), doc, "three points")
    assert capsys.readouterr().out == ""
    O.emit(ns(json=True, quiet=True, verbose=0), doc, "three points")
    assert json.loads(capsys.readouterr().out) == {"size": 3, "rho": 0.5, "radius": ["inf", 1.0]}
    out = tmp_path / "r.json"
    O.emit(ns(json=str(out), quiet=False, verbose=0), doc, lambda: "text too")
    assert capsys.readouterr().out == "text too\n" and json.loads(out.read_text())["size"] == 3
    O.say(ns(json=True, quiet=False, verbose=0), "hidden: stdout holds JSON")
    O.say(ns(json=False, quiet=False, verbose=0), "detail", O.VERBOSE)
    O.say(ns(json=False, quiet=False, verbose=1), "detail shown", O.VERBOSE)
    assert capsys.readouterr().out == "detail shown\n"


def test_jsonable_is_standard_json():
    doc = {1: (1, 2), "nan": float("nan"), "p": np.float32(0.25), "b": np.bool_(True), "s": {3}}
    text = O.dumps(doc)
    assert json.loads(text) == {"1": [1, 2], "nan": "nan", "p": 0.25, "b": True, "s": [3]}


@pytest.mark.parametrize(
    "text,expected",
    [
        ("plain message", "plain message"),
        ("scan 'a\nb' and /tmp/x\ny.ply", "scan 'a\\nb' and /tmp/x\\ny.ply"),
        ("tab\there\r", "tab\\there\\r"),
        ("ünïcode names stay", "ünïcode names stay"),
        ("bell\x07", "bell\\x07"),
    ],
)
def test_one_line(text, expected):
    assert O.one_line(text) == expected
    assert "\n" not in O.error_line("slice", InputError(text))


def test_error_line():
    assert O.error_line("info", InputError("x\ny")) == "lodbuilder info: error: x\\ny"
    assert O.error_line(None, "bad") == "lodbuilder: error: bad"


def test_names_are_quoted_and_cut():
    from lodbuilder._validate import quoted_names

    assert quoted_names([]) == "none"
    assert quoted_names(["a\nb", "c"]) == "'a\\nb', 'c'"
    assert quoted_names([str(i) for i in range(12)], limit=2) == "'0', '1', ..."


def test_check_output_rule(tmp_path):
    arc = tmp_path / "a.h5"
    arc.write_bytes(b"x")
    assert O.check_output(tmp_path / "o.ply", "-o") == tmp_path / "o.ply"
    with pytest.raises(ScanFileError) as e:
        O.check_output(tmp_path / "new" / "o.ply", "-o")
    assert str(e.value) == (
        f"-o {tmp_path / 'new' / 'o.ply'}: output directory {tmp_path / 'new'} does not exist; "
        "create it first"
    )
    assert not (tmp_path / "new").exists()
    with pytest.raises(
        InputError, match=r"^--json .*a\.h5 is the input archive; choose another output$"
    ):
        O.check_output(tmp_path / "." / "a.h5", "--json", inputs={"archive": arc})
    with pytest.raises(InputError, match=r"^--plot .*q\.pdf must end in \.png$"):
        O.check_output(tmp_path / "q.pdf", "--plot", suffixes=(".png",))
    assert O.check_output(tmp_path / "Q.PNG", "--plot", suffixes=(".png",))
    with pytest.raises(
        InputError, match=r"^-o - \(stdout\) is not possible here; give a file name$"
    ):
        O.check_output("-", "-o")
    assert str(O.check_output("-", "--json", stdout=True)) == "-"
    with pytest.raises(ScanFileError, match="is a directory"):
        O.check_output(tmp_path, "-o")


@pytest.mark.parametrize(
    "argv,line",
    [
        (
            ["slice", "a.h5", "--size", "x", "-o", "o.ply"],
            "lodbuilder slice: error: argument --size: invalid int value: 'x' "
            "(see 'lodbuilder slice --help')",
        ),
        (
            ["slice", "a.h5", "-o", "o.ply"],
            "lodbuilder slice: error: one of the arguments --rho --size --fraction is required "
            "(see 'lodbuilder slice --help')",
        ),
        (
            ["info"],
            "lodbuilder info: error: the following arguments are required: ARCHIVE "
            "(see 'lodbuilder info --help')",
        ),
        (
            [],
            "lodbuilder: error: the following arguments are required: COMMAND "
            "(see 'lodbuilder --help')",
        ),
    ],
)
def test_argument_errors_are_one_line(capsys, argv, line):
    from lodbuilder.cli.main import main

    with pytest.raises(SystemExit) as e:
        main(argv)
    out, err = capsys.readouterr()
    assert e.value.code == 2 and out == "" and err == line + "\n"
