"""Round-trip matrix: every source format written as PLY, LAS, LAZ, CSV and NPY and read back.

Equality rules (the documented quantisation) are in ``tests/roundtrip.py``. The default run
takes small files and subsets; the full matrix over every PLY, LAS, LAZ, E57 file of
../shared/data (plus generated XYZ and NPY files) is marked ``slow`` and ``data``.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from roundtrip import assert_same

from lodbuilder.io import Scan, read_scan, write_scan

pytest.importorskip("laspy")
TARGETS = ("ply", "las", "laz", "csv", "npy")
SUBSET = 3000


def _subset(scan: Scan, n: int = SUBSET) -> Scan:
    s = copy.deepcopy(scan)
    keep = np.linspace(0, len(s) - 1, min(n, len(s))).astype(np.int64)
    s.points = np.ascontiguousarray(s.points[keep])
    s.attributes = {k: np.ascontiguousarray(v[keep]) for k, v in s.attributes.items()}
    return s


@pytest.fixture(scope="session")
def generated(shared_data, tmp_path_factory) -> dict[str, Path]:
    """XYZ and NPY scans made from the real data without lodbuilder's writers."""
    import laspy
    from plyfile import PlyData

    d = tmp_path_factory.mktemp("generated")
    las = laspy.read(str(shared_data / "simple.las"))
    table = np.stack([las.x, las.y, las.z, np.asarray(las.intensity, dtype=np.float64)], axis=1)
    np.savetxt(d / "simple.xyz", table, fmt=["%.2f", "%.2f", "%.2f", "%d"])
    v = PlyData.read(str(shared_data / "frag_115.ply"))["vertex"].data
    np.save(d / "frag_115.npy", np.asarray(v))
    small = np.asarray(v)[::20]
    np.save(d / "frag_small.npy", small)
    return {"simple.xyz": d / "simple.xyz", "frag_115.npy": d / "frag_115.npy", "frag_small.npy": d / "frag_small.npy"}


def _source(shared_data: Path, generated: dict[str, Path], name: str) -> Path:
    return generated[name] if name in generated else shared_data / name


def _check(tmp_path: Path, scan: Scan, fmt: str) -> None:
    out = write_scan(tmp_path / f"out.{fmt}", scan)
    back = read_scan(out)
    assert_same(scan, back, fmt)


# small files whole, larger ones as subsets: the fast default
FAST = ["bun_zipper_res4.ply", "simple.las", "simple.xyz", "frag_small.npy"]
FAST_SUBSETS = ["autzen_trim.laz", "pumpAVisualReferenceImage.e57", "frag_115.ply", "bunnyDouble.e57", "bun000.ply"]


@pytest.mark.data
@pytest.mark.parametrize("fmt", TARGETS)
@pytest.mark.parametrize("name", FAST)
def test_round_trip_small(shared_data, generated, tmp_path, name, fmt):
    _check(tmp_path, read_scan(_source(shared_data, generated, name)), fmt)


@pytest.fixture(scope="module")
def subsets(shared_data) -> dict[str, Scan]:
    return {n: _subset(read_scan(shared_data / n)) for n in FAST_SUBSETS}


@pytest.mark.data
@pytest.mark.parametrize("fmt", TARGETS)
@pytest.mark.parametrize("name", FAST_SUBSETS)
def test_round_trip_subset(subsets, tmp_path, name, fmt):
    _check(tmp_path, subsets[name], fmt)


@pytest.mark.data
@pytest.mark.parametrize("fmt", TARGETS)
def test_round_trip_keeps_assigned_crs(shared_data, tmp_path, fmt):
    """A CRS given to a PLY scan (build --crs) survives every format."""
    pytest.importorskip("pyproj")
    scan = read_scan(shared_data / "bun_zipper_res4.ply", crs="EPSG:32633")
    assert scan.metadata["crs_wkt"].startswith('PROJCS["WGS 84 / UTM zone 33N"')
    _check(tmp_path, scan, fmt)


def _all_sources(data: Path) -> list[str]:
    if not data.is_dir():
        return []
    return sorted(p.name for p in data.iterdir() if p.suffix.lower() in (".ply", ".las", ".laz", ".e57"))


@pytest.mark.slow
@pytest.mark.data
@pytest.mark.parametrize("fmt", TARGETS)
@pytest.mark.parametrize("name", _all_sources(Path(__file__).resolve().parents[2] / "shared" / "data")
                         + ["simple.xyz", "frag_115.npy"])
def test_round_trip_full_matrix(shared_data, generated, tmp_path, name, fmt):
    _check(tmp_path, read_scan(_source(shared_data, generated, name)), fmt)


# ------------------------------------------------------------------------ through the archive

def _through_archive(tmp_path: Path, scan: Scan) -> None:
    """Build, take the full level, compare with the source, and write it to every format."""
    from lodbuilder import build_archive, open_archive
    from lodbuilder.io import write_points

    arc = build_archive(copy.deepcopy(scan), tmp_path / "a.h5")
    with open_archive(arc) as a:
        view = a.scan()
        level = view.level(fraction=1.0)
        meta = view.format_metadata
        assert view.crs == scan.metadata.get("crs_wkt")
        assert level.crs == view.crs and level.units == view.units
    inv = np.argsort(level.source_index)
    np.testing.assert_array_equal(level.points[inv], scan.points)
    assert sorted(level.attributes) == sorted(scan.attributes)
    for k, v in scan.attributes.items():
        np.testing.assert_array_equal(level.attributes[k][inv], v, err_msg=k)
        assert level.attributes[k].dtype == v.dtype
    # write the level itself (stored order): the CRS comes with it, no extra arguments
    src = copy.deepcopy(scan)
    src.points = level.points
    src.attributes = level.attributes
    for fmt in TARGETS:
        back = read_scan(write_points(tmp_path / f"level.{fmt}", level, metadata=meta))
        assert_same(src, back, fmt)


@pytest.mark.data
@pytest.mark.parametrize("name", ["bun_zipper_res4.ply", "simple.las"])
def test_archive_round_trip_small(shared_data, tmp_path, name):
    _through_archive(tmp_path, read_scan(shared_data / name))


@pytest.mark.data
def test_archive_round_trip_las_subset_with_crs(subsets, tmp_path):
    scan = subsets["autzen_trim.laz"]
    assert scan.metadata["crs_wkt"].startswith('PROJCS["NAD_1983_HARN_Lambert_Conformal_Conic"')
    _through_archive(tmp_path, scan)


@pytest.mark.slow
@pytest.mark.data
@pytest.mark.parametrize("name", _all_sources(Path(__file__).resolve().parents[2] / "shared" / "data")
                         + ["simple.xyz", "frag_115.npy"])
def test_archive_round_trip_full(shared_data, generated, tmp_path, name):
    _through_archive(tmp_path, read_scan(_source(shared_data, generated, name)))
