"""One level arithmetic: every caller that turns a rho, a size or a fraction into a level gives
the same size on the same archive (issue 13.3; before, ``--fraction 0.5`` on the bunny gave 945
points from ``slice`` and 944 from ``view``)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

import lodbuilder
from lodbuilder.cli.main import main
from lodbuilder.collection import collection_level, scan_level
from lodbuilder.errors import InputError
from lodbuilder.levels import covering_bound
from lodbuilder.quality import prefix_sizes
from lodbuilder.sampling.ordering import Ordering
from lodbuilder.viewer.source import load_view_data

N = 1889  # bun_zipper_res3


@pytest.fixture(scope="module")
def archive(tmp_path_factory, shared_data):
    path = tmp_path_factory.mktemp("callers") / "bunny.h5"
    argv = ["build", str(shared_data / "bun_zipper_res3.ply"), "-o", str(path), "--no-progress"]
    assert main(argv + ["--adaptive", "0.5"]) == 0
    with lodbuilder.open_archive(path) as arc:
        radius = np.array(arc.scan().radius)
    return path, radius


def queries(radius):
    """Sizes, fractions (0.5 of 1889 is the tie 944.5; 0.35 is below 0.35 in binary) and rhos
    (between radii, and exactly on stored radii, ties included)."""
    tie = (
        float(radius[np.flatnonzero(radius[1:] == radius[:-1])[0] + 1])
        if (radius[1:] == radius[:-1]).any()
        else float(radius[500])
    )
    return (
        [("size", s) for s in (1, 2, 100, 945, N)]
        + [("fraction", f) for f in (0.5, 0.35, 0.001, 0.0002, 0.1, 1.0)]
        + [("rho", r) for r in (0.05, 0.01, 0.0031, float(radius[7]), float(radius[1200]), tie)]
    )


def api_sizes(path, qs):
    with lodbuilder.open_archive(path) as arc:
        view = arc.scan()
        return [view.level(**{kind: v}, attributes=False).size for kind, v in qs]


def test_every_caller_gives_the_same_size(archive, tmp_path, capsys):
    path, radius = archive
    qs = queries(radius)
    want = api_sizes(path, qs)  # the Python API: ScanView.level
    assert want[5] == 945  # fraction 0.5: 944.5 rounds up
    capsys.readouterr()

    # slice (the CLI)
    for (kind, v), size in zip(qs, want, strict=True):
        out = tmp_path / "lvl.npy"
        assert main(["slice", str(path), f"--{kind}", repr(v), "-o", str(out)]) == 0
        line = capsys.readouterr().out
        assert re.search(rf"^wrote {size:,} of {N:,} points", line), (kind, v, line)

    # view: the viewer's level list (what `lodbuilder view --size/--rho/--fraction` shows)
    data = load_view_data(path)
    assert [data.resolve_size(**{kind: v}) for kind, v in qs] == want

    # evaluate (the CLI, one run per kind) and the quality API on the stored radii
    for kind in ("size", "fraction", "rho"):
        values = [v for k, v in qs if k == kind]
        assert main(["evaluate", str(path), f"--{kind}s", *map(repr, values), "--json", "-"]) == 0
        got = [lv["size"] for lv in json.loads(capsys.readouterr().out)["levels"]]
        assert got == [s for (k, _), s in zip(qs, want, strict=True) if k == kind], kind
        api = prefix_sizes(radius, N, **{f"{kind}s": values})
        assert [s for s, _ in api] == got, kind

    # the collection queries
    assert [scan_level(path, **{kind: v}, attributes=False).size for kind, v in qs] == want
    for (kind, v), size in zip(qs, want, strict=True):
        if kind == "rho":
            assert collection_level(path, v, attributes=False).sizes == [size]

    # an Ordering of the same radii (the engine's result type)
    o = Ordering(np.arange(N), radius, np.full(N, -1), 1.0, 1.0, np.zeros(1, np.int64), N)
    for (kind, v), size in zip(qs, want, strict=True):
        if kind == "rho":
            assert max(1, o.size_for_rho(v)) == size


def test_floor_query_uses_the_same_rho_level(archive, tmp_path, capsys):
    """The density-floor query keeps the uniform level of its rho: with exactly that many points
    it is that level; one point fewer is refused naming the size."""
    from lodbuilder.query import floor_level

    path, radius = archive
    with lodbuilder.open_archive(path) as arc:
        view = arc.scan()
        for rho in (0.01, float(radius[300])):
            k = view.level(rho=rho).size
            lvl = floor_level(view, rho, k)
            np.testing.assert_array_equal(np.sort(lvl.rank), np.arange(k))
            assert lvl.rho == covering_bound(k, N, radius.__getitem__)
            with pytest.raises(
                InputError, match=f"the uniform prefix covering within rho has {k} points"
            ):
                floor_level(view, rho, k - 1)
    out = tmp_path / "floor.npy"
    k = api_sizes(path, [("rho", 0.01)])[0]
    argv = ["slice", str(path), "--floor-rho", "0.01", "--size", str(k + 10), "-o", str(out)]
    assert main(argv + ["--ordering", "weighted"]) == 0
    assert f"wrote {k + 10:,} of {N:,} points" in capsys.readouterr().out


def test_info_levels_are_api_levels(archive, capsys):
    path, _ = archive
    assert main(["info", str(path), "--json"]) == 0
    levels = json.loads(capsys.readouterr().out)["scans"][0]["levels"]
    assert levels and [lv["size"] for lv in levels] == api_sizes(
        path, [("rho", lv["rho"]) for lv in levels]
    )


def test_extra_ordering_levels_agree(archive, tmp_path, capsys):
    """The same for a prefix of the stored weighted ordering."""
    path, _ = archive
    qs = [("size", 10), ("fraction", 0.5), ("fraction", 0.35), ("fraction", 0.0002)]
    with lodbuilder.open_archive(path) as arc:
        view = arc.scan()
        want = [view.level(**{k: v}, ordering="weighted", attributes=False).size for k, v in qs]
        w_radius = np.asarray(view.dataset("orderings/weighted/radius")[:])
        qs.append(("rho", float(w_radius[100])))
        want.append(view.level(rho=float(w_radius[100]), ordering="weighted").size)
    assert want[1] == 945
    capsys.readouterr()
    for (kind, v), size in zip(qs, want, strict=True):
        argv = ["slice", str(path), f"--{kind}", repr(v), "--ordering", "weighted"]
        assert main(argv + ["-o", str(tmp_path / "w.npy"), "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["size"] == size, (kind, v)
    data = load_view_data(path, ordering="weighted")
    assert [data.resolve_size(**{k: v}) for k, v in qs] == want
    fr = [v for k, v in qs if k == "fraction"]
    argv = ["evaluate", str(path), "--ordering", "weighted", "--fractions", *map(repr, fr)]
    assert main(argv + ["--json", "-"]) == 0
    got = [lv["size"] for lv in json.loads(capsys.readouterr().out)["levels"]]
    assert got == [s for (k, _), s in zip(qs, want, strict=True) if k == "fraction"]


def test_merged_scans_in_the_viewer_are_the_collection_level(tmp_path):
    """view of a multi-scan archive merges the scans by radius: its level at rho is the union of
    every scan's level at rho, as collection_level (slice --all-scans) gives it."""
    from lodbuilder.datasets import demo_scan

    path = tmp_path / "two.h5"
    for name, kind in (("wavy", "wavy"), ("ball", "sphere")):
        lodbuilder.build_archive(demo_scan(700, kind=kind, seed=2, name=name), path)
    data = load_view_data(path)
    for rho in (0.3, 0.05, 0.02, 0.004):
        lvl = collection_level(path, rho, attributes=False)
        assert data.size_for_rho(rho) == sum(lvl.sizes) == len(lvl)


def test_the_level_query_gives_the_same_levels_as_the_scan_view(archive):
    # LevelQuery -> read_level is the one front of every query kind; a plain prefix is exactly the
    # ScanView's level and says its covering radius
    from lodbuilder.levels import LevelQuery
    from lodbuilder.query import read_level

    path, radius = archive
    with lodbuilder.open_archive(path) as arc:
        view = arc.scan()
        for kind, v in queries(radius):
            q = LevelQuery(**{kind: v})
            ans = read_level(view, q)
            assert q.kind == "prefix" and ans.filled is None
            assert ans.level.size == view.level(**{kind: v}).size == q.prefix_size(view.n_ordered, view.size_for_rho)
            assert ans.guarantee == f"covering radius <= {ans.level.rho:.6g}"
        box = (-1.0, -1.0, -1.0, 0.0, 1.0, 1.0)
        refined = read_level(view, LevelQuery(rho=0.01, box=box, box_rho=0.004)).level
        np.testing.assert_array_equal(refined.source_index, view.refine_box(box, 0.004, 0.01).source_index)
        weighted = read_level(view, LevelQuery(size=100, ordering="weighted"))
        assert weighted.guarantee.endswith("not a Euclidean covering radius")
        assert LevelQuery().prefix_size(view.n_ordered, view.size_for_rho) == view.n_ordered
        bare = read_level(view, LevelQuery(size=50), attributes=False).level  # (as evaluate reads)
        assert bare.attributes == {} and bare.size == 50
        with pytest.raises(InputError) as exc:
            read_level(view, LevelQuery(rho=0.01, box=box, box_rho=0.004), attributes=False)
        assert str(exc.value) == "attributes= applies to a prefix level, not to a box level"


@pytest.mark.parametrize(("kw", "message"), [
    ({"rho": 0.01, "box": (0, 0, 0, 1, 1, 1)}, "--box needs --box-rho (the finer rho inside the box)"),
    ({"rho": 0.01, "box_rho": 0.1}, "--box-rho needs --box XMIN YMIN ZMIN XMAX YMAX ZMAX"),
    ({"rho": 0.01, "viewpoint": (0, 0, 0)}, "--viewpoint and --slope go together"),
    ({"size": 5, "floor_rho": 0.1, "fill": 12.0}, "--fill needs --rho R (the density the filled level meets)"),
    ({"floor_rho": 0.1}, "--floor-rho needs --size N (the exact number of points)"),
    ({"viewpoint": (0, 0, 0), "slope": 0.1}, "--box / --viewpoint need --rho (the coarse rho, or rho at the viewpoint)"),
])
def test_a_level_query_is_checked_once_with_exact_messages(kw, message):
    from lodbuilder.levels import LevelQuery

    with pytest.raises(InputError) as exc:
        LevelQuery(**kw)
    assert str(exc.value) == message
