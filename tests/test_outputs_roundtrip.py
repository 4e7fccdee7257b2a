"""Outputs that round-trip (reliability-3 items 9 and 10): CSV header names are quoted as RFC 4180
says (a name 'a,b' gave 22 names over 21 columns, which lodbuilder could not read back) and
formula-like names are made safe; PLY property names with spaces or characters PLY forbids are
renamed (a ValueError traceback before), said on a `changed:` line; every format lodbuilder
writes reads back with the same columns and values."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from lodbuilder.io import collect_notes, read_scan, write_points

HOSTILE = ("a,b", "\"quote'", "=cmd|calc!A0", "my attr", "+sum", "@at", "-neg", "é")


@pytest.fixture
def cloud():
    rng = np.random.default_rng(0)
    pts = rng.random((50, 3))
    attrs = {name: rng.random(50) for name in HOSTILE}
    return pts, attrs


def test_csv_header_is_quoted_and_safe(tmp_path, cloud):
    pts, attrs = cloud
    out = tmp_path / "x.csv"
    with collect_notes() as notes:
        write_points(out, pts, attrs)
    header = out.read_text(encoding="utf-8").splitlines()[0]
    assert header == ("x,y,z,\"a,b\",\"\"\"quote'\",'=cmd|calc!A0,my attr,'+sum,'@at,'-neg,é")
    assert notes == [
        f"{out}: attribute {name!r} written as {chr(39) + name!r}: a name starting with = + - or "
        "@ reads as a formula in spreadsheets" for name in ("=cmd|calc!A0", "+sum", "@at", "-neg")
    ]
    back = read_scan(out)
    assert list(back.attributes) == ["a,b", "\"quote'", "'=cmd|calc!A0", "my attr", "'+sum",
                                     "'@at", "'-neg", "é"]
    assert np.array_equal(back.points, pts)
    for name in HOSTILE:
        key = "'" + name if name[0] in "=+-@" else name
        assert np.array_equal(back.attributes[key], attrs[name]), name


def test_xyz_header_quotes_names_with_spaces(tmp_path, cloud):
    pts, attrs = cloud
    out = tmp_path / "x.xyz"
    write_points(out, pts, {"my attr": attrs["my attr"], "plain": attrs["a,b"]})
    assert out.read_text().splitlines()[0] == 'x y z "my attr" plain'
    back = read_scan(out)
    assert list(back.attributes) == ["my attr", "plain"]
    assert np.array_equal(back.attributes["my attr"], attrs["my attr"])


def test_ply_names_are_renamed(tmp_path, cloud):
    pts, attrs = cloud
    out = tmp_path / "x.ply"
    with collect_notes() as notes:
        write_points(out, pts, {"my attr": attrs["my attr"], "é": attrs["é"], "my_attr": attrs["a,b"]})
    assert notes == [
        f"{out}: attribute 'my attr' written as 'my_attr_2': PLY property names are printable "
        "ASCII without spaces",
        f"{out}: attribute 'é' written as '_': PLY property names are printable ASCII without spaces",
    ]
    back = read_scan(out)
    assert sorted(back.attributes) == ["_", "my_attr", "my_attr_2"]
    assert np.array_equal(back.attributes["my_attr_2"], attrs["my attr"])
    assert np.array_equal(back.attributes["my_attr"], attrs["a,b"])


@pytest.mark.parametrize("suffix", [".ply", ".las", ".laz", ".csv", ".xyz", ".npy", ".npz"])
def test_every_format_reads_back(tmp_path, cloud, suffix):
    """Whatever the names, what lodbuilder writes it reads: the same number of points and one
    column per attribute (renamed as noted)."""
    pts, attrs = cloud
    out = tmp_path / f"x{suffix}"
    with collect_notes():
        write_points(out, pts, attrs)
    back = read_scan(out)
    assert back.points.shape == pts.shape
    np.testing.assert_allclose(back.points, pts, atol=1e-3)
    extra = {"intensity"} if suffix in (".las", ".laz") else set()  # (LAS standard fields)
    assert len(set(back.attributes) - extra) >= len(HOSTILE) or suffix in (".las", ".laz")


def test_slice_says_the_ply_rename(tmp_path):
    src = tmp_path / "s.csv"
    rng = np.random.default_rng(1)
    rows = np.column_stack([rng.random((300, 3)), rng.random(300)])
    src.write_text("x,y,z,my attr\n" + "\n".join(",".join(f"{v:.6f}" for v in r) for r in rows) + "\n")

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "lodbuilder.cli.main", *map(str, args)],
                              capture_output=True, text=True, timeout=300)

    r = cli("build", src, "-o", tmp_path / "a.h5", "--no-progress")
    assert r.returncode == 0, r.stderr
    out = tmp_path / "x.ply"
    r = cli("slice", tmp_path / "a.h5", "--fraction", "1", "-o", out)
    assert r.returncode == 0, r.stderr
    assert (f"  changed: {out}: attribute 'my attr' written as 'my_attr': PLY property names are "
            "printable ASCII without spaces") in r.stdout.splitlines(), r.stdout
    assert "my_attr" in read_scan(out).attributes
