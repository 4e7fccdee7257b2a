"""Shared fixtures: paths to the real scans and generated surfaces."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The directory of real scans; tests that need it are skipped when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real scans not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def _slow_tests() -> set[str]:
    """The tests listed in tests/slow_tests.txt (written by tools/slow_tests.py from a full run)."""
    path = Path(__file__).with_name("slow_tests.txt")
    if not path.exists():
        return set()
    return {ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark the listed slow tests ``slow``: ``pytest -m "not slow"`` is the fast lane."""
    slow = _slow_tests()
    for item in items:
        if item.nodeid in slow:
            item.add_marker(pytest.mark.slow)


@contextlib.contextmanager
def mounted_tmpfs(directory: Path, covered_by: str) -> Iterator[Path]:
    """A 3 MB tmpfs mounted on ``directory`` (created), unmounted afterwards; the test is skipped,
    naming ``covered_by`` (what covers the same paths), where this process may not mount one."""
    import subprocess

    directory.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(directory)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or r.returncode}); {covered_by}")
    try:
        yield directory
    finally:
        subprocess.run(["umount", "-l", str(directory)], capture_output=True)


@pytest.fixture(scope="session")
def autzen_archive_full(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An archive of the whole autzen_trim.laz (LAS 1.2 point format 3, CRS in a WKT VLR, feet),
    scan name 'autzen', built once for the export tests."""
    import lodbuilder

    out = tmp_path_factory.mktemp("autzen") / "autzen.h5"
    lodbuilder.build_archive(shared_data / "autzen_trim.laz", out, name="autzen")
    return out


@pytest.fixture(scope="session")
def small_archive(tmp_path_factory: pytest.TempPathFactory):
    """``small_archive(n, seed=7, scan="demo", filename="demo.h5", **options) -> Path``: an archive
    of the generated scan ``lodbuilder.datasets.demo_scan(n, seed=seed, name=scan)`` built with
    ``lodbuilder.build_archive(..., **options)``, once per session for each set of arguments.
    Shared: copy it before changing it."""
    import lodbuilder
    from lodbuilder.datasets import demo_scan

    made: dict[tuple, Path] = {}

    def make(n: int, *, seed: int = 7, scan: str = "demo", filename: str = "demo.h5", **options) -> Path:
        key = (n, seed, scan, filename, tuple(sorted(options.items())))
        if key not in made:
            path = tmp_path_factory.mktemp("small") / filename
            lodbuilder.build_archive(demo_scan(n, seed=seed, name=scan), path, **options)
            made[key] = path
        return made[key]

    return make


@pytest.fixture(scope="session")
def res3_cli_archive(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """bun_zipper_res3.ply (1,889 points, confidence + intensity) built through the command line
    with its defaults (scan 'bun_zipper_res3'). Shared: copy it before changing it."""
    from lodbuilder.cli.main import main

    arc = tmp_path_factory.mktemp("res3") / "bunny.h5"
    assert main(["build", str(shared_data / "bun_zipper_res3.ply"), "-o", str(arc), "--no-progress"]) == 0
    return arc
