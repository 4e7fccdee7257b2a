"""The lodbuilder command line: build, slice, info, validate, demo, and every bad input of issue 3."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import h5py
import numpy as np
import pytest
from clirun import run as run_cli

from lodbuilder.archive import layout as L
from lodbuilder.cli.main import main
from lodbuilder.io import read_scan


def files_in(d):
    return sorted(p.name for p in d.iterdir())


@pytest.fixture(scope="module")
def built(res3_cli_archive):
    """bun_zipper_res3 (1889 points, confidence + intensity) built through the CLI."""
    return res3_cli_archive


def test_build_info_validate(built, capsys, shared_data):
    rc, out, err = run_cli(capsys, "info", built, "--json")
    assert rc == 0
    info = json.loads(out)
    s = info["scans"][0]
    assert s["name"] == "bun_zipper_res3" and s["n_points"] == 1889
    assert s["provenance"]["source_sha256"] == (
        "d628625d14fbe5deecb123536b515405c522984d43488cc24f91980eb75edadc"
    )
    assert s["provenance"]["reader"] == "ply" and s["provenance"]["source_size"] > 0
    assert set(s["attributes"]) == {"confidence", "intensity"}
    assert [lv["size"] for lv in s["levels"]] == sorted(lv["size"] for lv in s["levels"])
    rc, out, _ = run_cli(capsys, "info", built)
    assert rc == 0 and "1,889 points" in out and "sha256 d628625d14fbe5de" in out
    rc, out, _ = run_cli(capsys, "validate", built)
    assert rc == 0 and "valid (1 scan(s), 1,889 points" in out


@pytest.mark.parametrize("suffix", [".ply", ".npy", ".csv"])
def test_slice_writes_level_with_attributes(built, capsys, tmp_path, shared_data, suffix):
    out_path = tmp_path / f"level{suffix}"
    rc, out, err = run_cli(capsys, "slice", built, "--rho", "0.01", "-o", out_path)
    assert rc == 0, err
    import lodbuilder

    with lodbuilder.open_archive(built) as arc:
        lev = arc.scan().level(rho=0.01)
    got = read_scan(out_path)
    assert len(got) == lev.size and f"wrote {lev.size:,} of 1,889 points" in out
    # float32 coordinates and attributes: CSV prints them as float32 (the source precision)
    np.testing.assert_array_equal(got.points.astype(np.float32), lev.points.astype(np.float32))
    for key in ("confidence", "intensity"):
        np.testing.assert_array_equal(
            np.asarray(got.attributes[key]).astype(np.float32), lev.attributes[key]
        )


def test_slice_size_fraction_box_viewpoint(built, capsys, tmp_path):
    rc, out, _ = run_cli(capsys, "slice", built, "--size", "100", "-o", tmp_path / "a.npy")
    assert rc == 0 and len(read_scan(tmp_path / "a.npy")) == 100
    rc, out, _ = run_cli(
        capsys, "slice", built, "--fraction", "0.5", "--extra", "-o", tmp_path / "b.ply"
    )
    got = read_scan(tmp_path / "b.ply")
    assert rc == 0 and len(got) == 945 and {"radius", "rank", "source_index"} <= set(got.attributes)
    rc, out, _ = run_cli(
        capsys,
        "slice",
        built,
        "--rho",
        "0.02",
        "--box",
        -0.1,
        0.05,
        -0.1,
        0.0,
        0.2,
        0.1,
        "--box-rho",
        "0.005",
        "-o",
        tmp_path / "c.ply",
    )
    n_box = len(read_scan(tmp_path / "c.ply"))
    run_cli(capsys, "slice", built, "--rho", "0.02", "-o", tmp_path / "d.ply")
    assert rc == 0 and n_box > len(read_scan(tmp_path / "d.ply"))
    rc, out, _ = run_cli(
        capsys,
        "slice",
        built,
        "--rho",
        "0.003",
        "--viewpoint",
        0,
        0.1,
        0,
        "--slope",
        "0.5",
        "-o",
        tmp_path / "e.ply",
    )
    assert rc == 0 and 1 < len(read_scan(tmp_path / "e.ply")) < 1889


def test_add_second_scan_duplicate_and_overwrite(built, capsys, tmp_path, shared_data):
    arc = tmp_path / "two.h5"
    arc.write_bytes(built.read_bytes())
    rc, out, err = run_cli(
        capsys, "build", shared_data / "bun_zipper_res4.ply", "-o", arc, "--no-progress"
    )
    assert rc == 0 and "holds 2 scan(s)" in out
    before = arc.read_bytes()
    # the same file with the same parameters: unchanged, nothing to do (one duplicate-name policy)
    rc, out, err = run_cli(
        capsys, "build", shared_data / "bun_zipper_res4.ply", "-o", arc, "--no-progress"
    )
    assert rc == 0 and out == (
        f"scan 'bun_zipper_res4' in {arc} is unchanged (same source, pose and parameters); nothing "
        "to do (pass --force to rebuild it)\n"
    )
    assert arc.read_bytes() == before
    # other parameters under the same name: refused without --overwrite
    rc, out, err = run_cli(
        capsys, "build", shared_data / "bun_zipper_res4.ply", "-o", arc, "--no-progress",
        "--voxel-size", "0.01",
    )
    assert rc == 2 and err == (
        f"lodbuilder build: error: archive {arc} already holds scan 'bun_zipper_res4' (built from "
        "bun_zipper_res4.ply with other contents, pose or parameters); pass --overwrite "
        "(overwrite=True) to replace it or choose another --name\n"
    )
    assert arc.read_bytes() == before
    rc, out, err = run_cli(
        capsys,
        "build",
        shared_data / "bun_zipper_res4.ply",
        "-o",
        arc,
        "--no-progress",
        "--voxel-size", "0.01",
        "--overwrite",
    )
    assert rc == 0
    rc, out, err = run_cli(
        capsys,
        "build",
        shared_data / "bun_zipper_res4.ply",
        "-o",
        arc,
        "--no-progress",
        "--name",
        "small",
    )
    assert rc == 0 and "holds 3 scan(s)" in out
    # several scans: --scan is required, and an unknown one is named
    rc, out, err = run_cli(capsys, "slice", arc, "--size", "10", "-o", tmp_path / "x.ply")
    assert rc == 2 and "holds 3 scans; choose one with --scan" in err
    rc, out, err = run_cli(
        capsys, "slice", arc, "--scan", "small", "--size", "10", "-o", tmp_path / "x.ply"
    )
    assert rc == 0
    rc, out, _ = run_cli(capsys, "validate", arc)
    assert rc == 0


def test_validate_reports_corruption(built, capsys, tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(built.read_bytes())
    with h5py.File(bad, "r+") as f:  # break an invariant without touching checksums
        g = f["scans/bun_zipper_res3"]
        r = g["radius"][:]
        r[10], r[11] = r[11] * 0.5, r[10] * 2
        del g["radius"]
        L.create_dataset(g, "radius", r)
    rc, out, err = run_cli(capsys, "validate", bad)
    assert rc == 1 and "radius increases at position 11" in err and "INVALID" in out
    flip = tmp_path / "flip.h5"
    flip.write_bytes(built.read_bytes())
    with h5py.File(flip, "r") as f:
        info = f["scans/bun_zipper_res3/source_index"].id.get_chunk_info(0)
    with open(flip, "r+b") as fh:
        fh.seek(info.byte_offset + 3)
        b = fh.read(1)
        fh.seek(info.byte_offset + 3)
        fh.write(bytes([b[0] ^ 0x5A]))
    rc, out, err = run_cli(capsys, "validate", flip)
    assert rc == 1 and "dataset /scans/bun_zipper_res3/source_index fails its checksum" in err
    rc, out, err = run_cli(capsys, "slice", flip, "--size", "5", "-o", tmp_path / "o.ply")
    assert (
        rc == 2 and "source_index fails its checksum" in err and not (tmp_path / "o.ply").exists()
    )


def test_demo(tmp_path, capsys):
    d = tmp_path / "demo"
    rc, out, err = run_cli(capsys, "demo", "-o", d, "--points", "3000", "--no-progress")
    assert rc == 0, err
    assert {"demo.h5", "level_30.ply", "level_150.ply", "level_750.ply"} <= set(files_in(d))
    assert "covering radius" in out and "level_750.ply" in out
    assert len(read_scan(d / "level_150.ply")) == 150
    rc, out, _ = run_cli(capsys, "validate", d / "demo.h5")
    assert rc == 0


def test_help_everywhere(capsys):
    for cmd in ("build", "slice", "info", "validate", "demo"):
        with pytest.raises(SystemExit) as e:
            main([cmd, "--help"])
        assert e.value.code == 0
        assert "usage: lodbuilder " + cmd in capsys.readouterr().out


def _subparsers():
    import argparse

    from lodbuilder.cli.main import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


@pytest.mark.parametrize("cmd", sorted(_subparsers()))
def test_help_lists_every_option(cmd, capsys):
    """Every option a command accepts (collected from its parser, so the shared ones from
    cli/level_options.py too) is named in its --help, and so is ARCHIVE where it takes one."""
    parser = _subparsers()[cmd]
    with pytest.raises(SystemExit):
        main([cmd, "--help"])
    out = capsys.readouterr().out
    assert out.startswith(f"usage: lodbuilder {cmd}")
    for action in parser._actions:
        for opt in action.option_strings:
            assert re.search(rf"(^|[\s\[(|,]){re.escape(opt)}\b", out), (cmd, opt)
        if not action.option_strings:
            assert (action.metavar or action.dest) in out, (cmd, action.dest)


def test_level_options_are_shared():
    """slice, export, view and evaluate take their level options from one place."""
    parsers = _subparsers()
    for cmd in ("slice", "export", "view"):
        opts = {o for a in parsers[cmd]._actions for o in a.option_strings}
        assert {"--scan", "--rho", "--size", "--fraction"} <= opts, cmd
    ev = {o for a in parsers["evaluate"]._actions for o in a.option_strings}
    assert {"--scan", "--rhos", "--sizes", "--fractions", "--ordering"} <= ev
    for cmd in ("slice", "view"):
        box = next(a for a in parsers[cmd]._actions if "--box" in a.option_strings)
        assert box.nargs == 6 and box.metavar == ("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX")


def test_slice_path_imports_nothing_heavy(built, tmp_path):
    code = (
        "import sys\n"
        "from lodbuilder.cli.main import main\n"
        f"rc = main(['slice', {str(built)!r}, '--fraction', '0.5', '-o', {str(tmp_path / 'h.ply')!r}])\n"
        "heavy = [m for m in ('numba', 'scipy', 'pyvista', 'dask', 'vtk') if m in sys.modules]\n"
        "print(rc, heavy)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "0 []"


def test_an_in_memory_build_does_not_load_the_tiled_driver(shared_data, tmp_path):
    # the tiled package's driver, phases and work store load only when a build is tiled (the plan
    # decides that; the work directory's URL is checked before it)
    code = (
        "import sys\n"
        "from lodbuilder.cli.main import main\n"
        f"rc = main(['build', {str(shared_data / 'bun_zipper_res4.ply')!r}, '-o', {str(tmp_path / 'a.h5')!r},"
        " '--no-progress'])\n"
        "print(rc, sorted(m for m in sys.modules if m.startswith('lodbuilder.build.tiled.')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "0 ['lodbuilder.build.tiled.plan', 'lodbuilder.build.tiled.urls']"


def test_entry_point_runs(built):
    out = subprocess.run(
        [sys.executable, "-m", "lodbuilder.cli.main", "info", str(built)],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0 and "bun_zipper_res3" in out.stdout
    assert os.path.exists(built)


def test_build_reports_the_name_the_reader_gave(tmp_path, capsys, shared_data):
    # an E57 scan is named by the file's own scan name, not the file stem
    arc = tmp_path / "e.h5"
    rc, out, err = run_cli(
        capsys, "build", shared_data / "bunnyDouble.e57", "-o", arc, "--no-progress"
    )
    assert rc == 0, err
    import lodbuilder

    with lodbuilder.open_archive(arc) as a:
        (name,) = a.scans
    assert f"added scan {name!r} (30,571 points" in out


def test_build_names_the_archive_as_the_user_gave_it(tmp_path, capsys, shared_data, monkeypatch):
    monkeypatch.chdir(tmp_path)
    src = shared_data / "bun_zipper_res4.ply"
    rc, out, err = run_cli(capsys, "build", src, "-o", "res4.h5", "--no-progress")
    assert rc == 0, err
    assert out.startswith("added scan 'bun_zipper_res4' (453 points, float32 coordinates) to res4.h5 in ")
    rc, out, err = run_cli(capsys, "build", src, "-o", "res4.h5", "--no-progress")
    assert out.startswith("scan 'bun_zipper_res4' in res4.h5 is unchanged")
    rc, out, err = run_cli(capsys, "build", src, shared_data / "bun_zipper_res3.ply", "-o", "two.h5",
                           "--no-progress")
    assert rc == 0, err
    assert out.startswith("2 built scan(s) into two.h5 on ")


def test_build_collects_garbage_less_often_while_building(capsys, tmp_path, shared_data, monkeypatch):
    # numba's import and kernel loading make many objects: the collector runs every 10,000
    # allocations during the build (0.15 -> 0.08 CPU-s of a small scan's build), as before after it
    import gc

    import lodbuilder.api as api

    real, seen = api.build_archive, []

    def spy(*a, **k):
        seen.append((gc.get_threshold(), gc.get_freeze_count() > 0))
        return real(*a, **k)

    monkeypatch.setattr(api, "build_archive", spy)
    before = gc.get_threshold(), gc.get_freeze_count()
    rc, out, err = run_cli(capsys, "build", shared_data / "bun_zipper_res4.ply", "-o", tmp_path / "a.h5",
                           "--no-progress")
    assert rc == 0, err
    assert seen == [((10_000, 10, 10), True)]
    assert (gc.get_threshold(), gc.get_freeze_count()) == before


def test_the_command_leaves_its_objects_to_the_shutdown_unwalked(tmp_path):
    """Run as the ``lodbuilder`` command (no argv: the process ends next), main() moves every
    object to the garbage collector's permanent generation, so that the interpreter's shutdown
    does not walk them all again; called from Python with an argv it leaves the collector alone."""
    code = (
        "import gc, sys\n"
        "from lodbuilder.cli.main import main\n"
        "sys.argv = ['lodbuilder', 'info', sys.argv[1]]\n"
        "called = main([*sys.argv[1:]])\n"
        "print(gc.get_freeze_count())\n"
        "status = main()\n"
        "print(gc.get_freeze_count() > 0, called, status)\n"
    )
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path / "missing.h5")], capture_output=True,
                         text=True, check=True)
    assert res.stdout.split() == ["0", "True", "2", "2"]
