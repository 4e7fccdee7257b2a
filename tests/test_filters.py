"""Survey filters (lodbuilder.filters): one LevelFilter against numpy masks written out by hand,
its parsers with their exact messages, the covering bounds of a filtered level against brute
force, and the filters of slice, export and view end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lodbuilder.errors import InputError
from lodbuilder.filters import (
    LevelFilter,
    in_polygon,
    parse_classes,
    parse_polygon,
    parse_range,
    parse_returns,
    prefix_bounds,
)

SQUARE_WITH_HOLE = "POLYGON((0 0, 10 0, 10 10, 0 10, 0 0), (4 4, 6 4, 6 6, 4 6, 4 4))"


def survey_like(n=5000, seed=0):
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.random(n) * 20 - 5, rng.random(n) * 20 - 5, rng.random(n) * 3])
    nret = rng.integers(1, 4, n)
    attrs = {
        "classification": rng.choice([1, 2, 5, 6], n).astype(np.uint8),
        "return_number": np.minimum(rng.integers(1, 4, n), nret).astype(np.uint8),
        "number_of_returns": nret.astype(np.uint8),
        "intensity": rng.integers(0, 4000, n).astype(np.uint16),
    }
    return pts, attrs


def test_every_part_against_a_numpy_mask():
    pts, a = survey_like()
    x, y, z = pts.T
    cases = [
        (LevelFilter(classes=(2, 6)), np.isin(a["classification"], [2, 6])),
        (LevelFilter(returns=("first",)), a["return_number"] == 1),
        (LevelFilter(returns=("last",)), a["return_number"] == a["number_of_returns"]),
        (LevelFilter(returns=("only",)), a["number_of_returns"] == 1),
        (LevelFilter(returns=(2, "only")), (a["return_number"] == 2) | (a["number_of_returns"] == 1)),
        (LevelFilter(ranges=(("intensity", 100.0, 2000.0),)), (a["intensity"] >= 100) & (a["intensity"] <= 2000)),
        (LevelFilter(ranges=(("intensity", -np.inf, 50.0),)), a["intensity"] <= 50),
        (LevelFilter(box=(0, 0, 10, 10)), (x >= 0) & (x <= 10) & (y >= 0) & (y <= 10)),
        (LevelFilter(box=(0, 0, 1, 10, 10, 2)),
         (x >= 0) & (x <= 10) & (y >= 0) & (y <= 10) & (z >= 1) & (z <= 2)),
        (LevelFilter(polygons=parse_polygon(SQUARE_WITH_HOLE)),
         (x > 0) & (x < 10) & (y > 0) & (y < 10) & ~((x > 4) & (x < 6) & (y > 4) & (y < 6))),
        (LevelFilter(classes=(2,), returns=("first",), box=(0, 0, 10, 10)),
         (a["classification"] == 2) & (a["return_number"] == 1) & (x >= 0) & (x <= 10) & (y >= 0) & (y <= 10)),
    ]
    for flt, want in cases:
        got = flt.mask(pts, a, "s")
        assert got.sum() > 0 and not got.all(), flt.describe()
        np.testing.assert_array_equal(got, want, flt.describe())


def test_polygons_from_wkt_geojson_and_files_agree(tmp_path):
    ring = [[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]]
    hole = [[4, 4], [6, 4], [6, 6], [4, 6], [4, 4]]
    far = [[20, 20], [30, 20], [25, 30], [20, 20]]
    multi_wkt = ("MULTIPOLYGON(((0 0, 10 0, 10 10, 0 10, 0 0), (4 4, 6 4, 6 6, 4 6, 4 4)), "
                 "((20 20, 30 20, 25 30, 20 20)))")
    gj = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [ring, hole]}},
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [far]}},
    ]}
    f = tmp_path / "area.geojson"
    f.write_text(json.dumps(gj))
    w = tmp_path / "area.wkt"
    w.write_text(multi_wkt)
    want = parse_polygon(multi_wkt)
    assert len(want) == 2 and len(want[0]) == 2 and len(want[0][0]) == 4
    assert parse_polygon(json.dumps(gj)) == want == parse_polygon(str(f)) == parse_polygon(str(w))
    mp = {"type": "MultiPolygon", "coordinates": [[ring, hole], [far]]}
    assert parse_polygon(json.dumps(mp)) == want


def test_in_polygon_against_a_naive_ray_cast():
    rng = np.random.default_rng(2)
    poly = ((tuple(map(tuple, rng.random((9, 2)) * 10)),))  # a self-crossing star is fine too
    x, y = rng.random(3000) * 12 - 1, rng.random(3000) * 12 - 1
    got = in_polygon(x, y, poly)
    ring = np.asarray(poly[0])
    for i in range(0, 3000, 7):
        inside = False
        for j in range(len(ring)):
            (x0, y0), (x1, y1) = ring[j], ring[(j + 1) % len(ring)]
            if (y0 > y[i]) != (y1 > y[i]) and x[i] < x0 + (y[i] - y0) * (x1 - x0) / (y1 - y0):
                inside = not inside
        assert got[i] == inside


def test_parsers_and_their_messages():
    assert parse_classes("ground, building") == (2, 6)
    assert parse_classes("vegetation,9") == (3, 4, 5, 9)
    assert parse_returns("first,2") == ("first", 2)
    assert parse_range("intensity=100:") == ("intensity", 100.0, np.inf)
    assert parse_range("z=:5.5") == ("z", -np.inf, 5.5)
    bad = [
        (lambda: parse_classes("grond"), "--class 'grond': 'grond' is neither a code nor an ASPRS class name"),
        (lambda: parse_returns("second"), "--return 'second': 'second' is not a return number (1, 2...) or one of first, last, only"),
        (lambda: parse_range("intensity>3"), "--where 'intensity>3': write NAME=LO:HI (a bound may be left out: NAME=LO:)"),
        (lambda: parse_range("i=a:3"), "--where 'i=a:3': 'a' or '3' is not a number"),
        (lambda: parse_polygon("LINESTRING(0 0, 1 1)"), "--polygon 'LINESTRING(0 0, 1 1)': not WKT, GeoJSON or a readable file"),
        (lambda: parse_polygon("POLYGON((0 0, 1 1))"), "--polygon: a ring has 2 vertices; a polygon needs 3 or more"),
        (lambda: parse_polygon('{"type": "Point", "coordinates": [0, 0]}'),
         "--polygon: GeoJSON type 'Point'; expect Polygon, MultiPolygon, Feature or FeatureCollection"),
        (lambda: LevelFilter(box=(1, 0, 0, 1)), "a filter box has a minimum above its maximum: [1.0, 0.0, 0.0, 1.0]"),
        (lambda: LevelFilter(ranges=(("i", 3.0, 1.0),)), "filter range of 'i': 3 is above 1"),
    ]
    for call, message in bad:
        with pytest.raises(InputError) as e:
            call()
        assert str(e.value).startswith(message), str(e.value)
    pts, a = survey_like(10)
    with pytest.raises(InputError, match=r"^the filter needs attribute 'foo', which scan 's' does not have \(it has: classification, intensity, number_of_returns, return_number\)$"):
        LevelFilter(ranges=(("foo", 0.0, 1.0),)).mask(pts, a, "s")


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    """An archive of a synthetic survey-like sheet with classification and returns."""
    import lodbuilder
    from lodbuilder.io import Scan

    pts, attrs = survey_like(6000, seed=3)
    pts[:, 2] = 0.2 * np.sin(pts[:, 0])
    out = tmp_path_factory.mktemp("flt") / "sheet.h5"
    lodbuilder.build_archive(Scan(points=pts, attributes=attrs, name="sheet"), out, name="sheet")
    return out


def test_prefix_bounds_cover_like_the_level_they_were_cut_from(sheet):
    """For a box filter, every scan point inside the box at least rho from its edge is within
    rho of a kept point (brute force), for the bounds of every prefix of the filtered level."""
    import lodbuilder

    with lodbuilder.open_archive(sheet) as arc:
        view = arc.scan()
        full = np.asarray(view.points())
        radius = np.asarray(view.radius)
        level = view.level(size=3000)
    flt = LevelFilter(box=(0.0, 0.0, 10.0, 10.0))
    kept = flt.apply(level)
    b = prefix_bounds(radius, kept.rank)
    assert kept.size > 100 and np.all(np.diff(b[1:]) <= 0) and np.all(b[1:] >= kept.radius[1:])
    inside = flt.mask(full, {}, "sheet")
    for k in (20, 100, kept.size // 2, kept.size - 1):
        rho = b[k]
        core = inside & (full[:, 0] >= rho) & (full[:, 0] <= 10 - rho) & (full[:, 1] >= rho) & (full[:, 1] <= 10 - rho)
        d, _ = cKDTree(kept.points[:k]).query(full[core])
        assert core.sum() > 0 and d.max() <= rho * (1 + 1e-12), (k, d.max(), rho)
        # the kept points' own next radius would be no bound: it can be below the true cover
        assert kept.radius[k] <= rho


def test_slice_export_and_view_filters(sheet, tmp_path, capsys):
    import laspy

    import lodbuilder
    from lodbuilder.cli.main import main
    from lodbuilder.io import read_scan
    from lodbuilder.viewer.source import load_view_data

    with lodbuilder.open_archive(sheet) as arc:
        level = arc.scan().level(size=2000)
    x, y = level.points[:, 0], level.points[:, 1]
    want = ((level.attributes["classification"] == 2) & (level.attributes["return_number"] == 1)
            & (x >= 0) & (x <= 10) & (y >= 0) & (y <= 10))
    out = tmp_path / "g.ply"
    args = ["--class", "ground", "--return", "first", "--clip-box", "0", "0", "10", "10"]
    assert main(["slice", str(sheet), "--size", "2000", "-o", str(out), *args]) == 0
    text = capsys.readouterr().out
    n = int(want.sum())
    assert text.startswith(
        f"wrote {n:,} of 6,000 points of scan 'sheet' to {out} (filter class 2; return first; box x "
        f"0..10 y 0..10: {n:,} of the level's 2,000 points; covering radius <= "
    )
    assert f"  guarantee: every scan point is within {level.rho:.6g} of a point of the level before the filter; the filter may have removed that point\n" in text
    got = read_scan(out)
    np.testing.assert_allclose(got.points, level.points[want], rtol=0, atol=1e-6)
    # export: COPC and web page hold the same points; the COPC file says which filter
    cop = tmp_path / "g.copc.laz"
    assert main(["export", str(sheet), "--size", "2000", "-o", str(cop), "-q", *args]) == 0
    las = laspy.read(str(cop))
    assert len(las) == n and np.all(np.asarray(las.classification) == 2)
    (vlr,) = [v for v in las.header.evlrs if v.user_id == "lodbuilder"]
    assert json.loads(vlr.record_data)["filter"] == "class 2; return first; box x 0..10 y 0..10"
    page = tmp_path / "g.html"
    assert main(["export", str(sheet), "--size", "2000", "-o", str(page), "--json", "-q", *args]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["size"], doc["level_size"], doc["filter"]) == (n, 2000, "class 2; return first; box x 0..10 y 0..10")
    # view: the scan's points that pass, in order; the slider's rho is the level's it was cut from
    flt = LevelFilter(classes=(2,), returns=("first",), box=(0.0, 0.0, 10.0, 10.0))
    data = load_view_data(sheet, None, None, flt)
    with lodbuilder.open_archive(sheet) as arc:
        view = arc.scan()
        full = np.asarray(view.points())
        keep = flt.mask(full, view.attributes(None, ["classification", "return_number"]), "sheet")
        radius = np.asarray(view.radius)
    np.testing.assert_array_equal(data.points, full[keep])
    idx = np.flatnonzero(keep)
    assert data.rho_for_size(10) == radius[idx[9] + 1]
    assert np.all(data.parent < np.arange(len(data)))
