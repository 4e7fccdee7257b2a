"""A missing optional dependency is one line naming the extra to install (issue 13.4), tested with
the package really absent: the command runs in a subprocess whose ``sys.meta_path`` refuses it.
And ``validate`` works with only what ``pip install -e ".[all]"`` installs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from lodbuilder.cli.main import main

ROOT = Path(__file__).resolve().parents[1]

RUNNER = r"""
import importlib.abc, sys
BLOCKED = set(filter(None, sys.argv[1].split(",")))

class Absent(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, Absent())
from lodbuilder.cli.main import main
sys.exit(main(sys.argv[2:]))
"""


def run_without(blocked, *argv, cwd=None):
    env = dict(os.environ, PYTHONPATH=str(ROOT), VTK_DEFAULT_OPENGL_WINDOW="vtkEGLRenderWindow")
    return subprocess.run(
        [sys.executable, "-c", RUNNER, ",".join(blocked), *map(str, argv)],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
        timeout=300,
    )


def one_error_line(proc, command):
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"lodbuilder {command}: error: ")
    return lines[0].split(": error: ", 1)[1]


@pytest.fixture(scope="module")
def archive(small_archive):
    return small_archive(600, seed=3, filename="a.h5")


VIZ = ("pyvista", "vtk", "vtkmodules")


def test_view_without_pyvista(archive, tmp_path):
    out = tmp_path / "shot.png"
    proc = run_without(VIZ, "view", archive, "--screenshot", out)
    assert one_error_line(proc, "view") == (
        "lodbuilder view needs pyvista, which is not installed; install it with: "
        "pip install 'lodbuilder[viz]'"
    )
    assert not out.exists()


def test_evaluate_plot_without_matplotlib(archive, tmp_path):
    js, png = tmp_path / "q.json", tmp_path / "q.png"
    proc = run_without(["matplotlib"], "evaluate", archive, "--plot", png, "--json", js)
    assert one_error_line(proc, "evaluate") == (
        "evaluate --plot needs matplotlib, which is not installed; install it with: "
        "pip install 'lodbuilder[viz]'"
    )
    assert not png.exists() and not js.exists()  # refused before any work


def test_animate_mp4_without_ffmpeg(archive, tmp_path):
    out = tmp_path / "a.mp4"
    proc = run_without(["imageio_ffmpeg"], "view", archive, "--animate", out)
    assert one_error_line(proc, "view") == (
        "writing a.mp4 (a .gif needs nothing more) needs imageio-ffmpeg, which is not installed; "
        "install it with: pip install 'lodbuilder[viz]'"
    )


@pytest.mark.parametrize(
    "blocked,argv,message",
    [
        (["laspy", "lazrs"], ["build", "{data}/autzen_trim.laz", "-o", "{tmp}/o.h5"],
         "{data}/autzen_trim.laz: LAS/LAZ needs laspy, which is not installed; install it with: "
         "pip install 'lodbuilder[las]'"),
        (["lazrs"], ["build", "{data}/autzen_trim.laz", "-o", "{tmp}/o.h5"],
         "{data}/autzen_trim.laz: LAZ needs lazrs, which is not installed; install it with: "
         "pip install 'lodbuilder[las]'"),
        (["pye57"], ["build", "{data}/bunnyDouble.e57", "-o", "{tmp}/o.h5"],
         "{data}/bunnyDouble.e57: E57 needs pye57, which is not installed; install it with: "
         "pip install 'lodbuilder[e57]'"),
        # the output named, not its temporary file (before: '.o.las.xxxx.part.las')
        (["laspy", "lazrs"], ["slice", "{arc}", "--size", "10", "-o", "{tmp}/o.las"],
         "{tmp}/o.las: LAS/LAZ needs laspy, which is not installed; install it with: "
         "pip install 'lodbuilder[las]'"),
        (["lazrs"], ["slice", "{arc}", "--size", "10", "-o", "{tmp}/o.laz"],
         "{tmp}/o.laz: LAZ needs lazrs, which is not installed; install it with: "
         "pip install 'lodbuilder[las]'"),
        (["lazrs"], ["export", "{arc}", "-o", "{tmp}/o.copc.laz"],
         "COPC export needs lazrs, which is not installed; install it with: "
         "pip install 'lodbuilder[las]'"),
    ],
)  # fmt: skip
def test_readers_and_writers_name_their_extra(archive, shared_data, tmp_path, blocked, argv, message):
    fill = {"data": shared_data, "tmp": tmp_path, "arc": archive}
    proc = run_without(blocked, *(a.format(**fill) for a in argv))
    assert one_error_line(proc, argv[0]) == message.format(**fill)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(("o.", ".o."))]


def test_level_to_polydata_without_pyvista(archive):
    code = (
        "import sys, importlib.abc\n"
        "class A(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, n, p=None, t=None):\n"
        "        if n.split('.')[0] == 'pyvista': raise ModuleNotFoundError(n, name=n)\n"
        "sys.meta_path.insert(0, A())\n"
        "import lodbuilder\n"
        f"lv = lodbuilder.open_archive({str(archive)!r}).scan().level(size=5)\n"
        "try:\n    lv.to_polydata()\n"
        "except lodbuilder.errors.MissingDependencyError as e:\n    print(e)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True,
        env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120,
    )  # fmt: skip
    assert proc.stdout.strip() == (
        "Level.to_polydata needs pyvista, which is not installed; install it with: "
        "pip install 'lodbuilder[viz]'"
    ), proc.stderr


def test_an_import_error_escaping_a_command_is_one_line(monkeypatch, capsys, tmp_path):
    """The safety net in main: an optional module missing deep inside a command."""
    from lodbuilder.cli import info

    def boom(args):
        raise ModuleNotFoundError("No module named 'dask'", name="dask")

    monkeypatch.setattr(info, "run", boom)
    assert main(["info", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert err == (
        "lodbuilder info: error: lodbuilder info needs dask, which is not installed; install it "
        "with: pip install 'lodbuilder[distributed]'\n"
    )

    def bug(args):
        raise ModuleNotFoundError("No module named 'lodbuilder.nothing'", name="lodbuilder.nothing")

    monkeypatch.setattr(info, "run", bug)
    with pytest.raises(ModuleNotFoundError):  # not an optional dependency: a real bug, shown
        main(["info", str(tmp_path / "x.h5")])


# -- what `pip install -e ".[all]"` installs -----------------------------------------------------


def pyproject():
    tomllib = pytest.importorskip("tomllib")
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def dist_name(req: str) -> str:
    import re

    return re.split(r"[\[<>=!~ ;]", req, maxsplit=1)[0].strip().lower().replace("_", "-")


def installed_by_all():
    proj = pyproject()["project"]
    extras = proj["optional-dependencies"]
    names = {dist_name(r) for r in proj["dependencies"]}
    todo = ["all"]
    while todo:
        for req in extras[todo.pop()]:
            if req.startswith("lodbuilder["):
                todo += req[len("lodbuilder[") : req.index("]")].split(",")
            else:
                names.add(dist_name(req))
    return names


def test_every_optional_module_is_in_its_extra_and_in_all():
    from lodbuilder._optional import EXTRAS

    extras = pyproject()["project"]["optional-dependencies"]
    every = installed_by_all()
    for module, (package, extra) in EXTRAS.items():
        in_extra = {dist_name(r) for r in extras[extra]}
        # vtk, lazrs and distributed come with pyvista, laspy[lazrs] and dask[distributed]
        assert package in in_extra or module in ("vtk", "vtkmodules", "lazrs", "distributed"), (
            module
        )
        assert extra in " ".join(extras["all"]), extra
    assert "jsonschema" in every  # lodbuilder validate


def test_validate_works_with_what_all_installs(archive):
    """Run validate with every dev-only package absent (jsonschema was dev-only before)."""
    dev = {dist_name(r) for r in pyproject()["project"]["optional-dependencies"]["dev"]}
    modules = {"point-cloud-utils": "point_cloud_utils"}
    blocked = sorted(modules.get(d, d.replace("-", "_")) for d in dev - installed_by_all())
    assert "hypothesis" in blocked
    proc = run_without(blocked, "validate", archive)
    assert proc.returncode == 0, proc.stderr
    assert "valid (1 scan(s), 600 points" in proc.stdout
