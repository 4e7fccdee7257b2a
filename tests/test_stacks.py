"""Stacks of sheets (an accordion: parallel sheets joined by folds): a sheet between two others is
bridged to neither, so levels cover the surface measured along the sheets; and the rule that cuts
the band between sheets against its naive reference."""

from __future__ import annotations

import numpy as np
import pytest
from naive import naive_sheet_cut
from scipy.spatial import cKDTree
from surfaces import accordion

from lodbuilder import fastfps
from lodbuilder.sampling.band import (
    _thin_plan,
    build_band,
    choose_parameters,
    cut_between_sheets,
    one_sided,
)

N = 60_000


def stack(sheets: int, gap_spacings: float, n: int = N, seed: int = 0):
    spacing = np.sqrt(sheets / n)  # each sheet is a unit square
    return accordion(n, sheets, gap_spacings * spacing, seed=seed)


@pytest.mark.parametrize(("sheets", "gap"), [(3, 4.0), (4, 5.0), (5, 6.0), (5, 4.0), (3, 6.0), (3, 3.0)])
def test_stacked_sheets_levels_cover_along_the_sheets(sheets, gap):
    # before the cut between sheets, the one-sided band split the stack (no choice of sides is
    # consistent around every fold) and the plain band bridged the inner sheets: 4 sheets 5
    # spacings apart covered only within 2.4 / 3.8 / 1.6 rho at rho = 0.3 / 0.1 / 0.05
    pts, uv = stack(sheets, gap)
    o = fastfps(pts)
    assert o.stats["thin_points"] >= 0.999 * len(pts)
    assert np.isinf(o.radius).sum() == 1  # one band component
    spacing = np.sqrt(sheets / len(pts))
    for rho in (0.3, 0.1, 0.05, 0.03, 0.02, 3 * spacing):
        k = o.size_for_rho(rho)
        geo = cKDTree(uv[o.order[:k]]).query(uv, k=1)[0].max()
        assert geo <= 1.10 * rho, (rho, geo / rho)


def test_no_marchable_neighbours_on_different_sheets():
    sheets, n = 4, 30_000
    pts, uv = stack(sheets, 4.0, n=n)
    gap = 4.0 * np.sqrt(sheets / n)
    h, r = choose_parameters(pts, None, None)
    plan = _thin_plan(pts, h, r)
    band = build_band(pts, h, r)
    vcost, near = cut_between_sheets(band, band.vcost, plan)
    # the sheet of every point (-1 on the folds, whose sides are neither sheet)
    period = 1.0 + np.pi * gap / 2
    k = np.minimum(uv[:, 0] // period, sheets - 1)
    sheet = np.where(uv[:, 0] - k * period < 1.0, k, -1)
    fs = sheet[band.perm[band.foot]]

    def cross_edges(vc: np.ndarray) -> int:
        ok = np.isfinite(vc)
        count = 0
        for j in range(6):
            w = np.maximum(band.nbr[:, j], 0)
            count += int((ok & (band.nbr[:, j] >= 0) & ok[w] & (fs >= 0) & (fs[w] >= 0) & (fs != fs[w])).sum())
        return count

    # the plain band joins the sheets in thousands of places; the cut leaves a handful at the ends
    # of sheets, where a normal fitted over a fold's points is off by up to 80 degrees (3 of 25,352
    # voxels here)
    plain = cross_edges(band.vcost)
    assert plain > 1000
    assert cross_edges(vcost) <= 1e-3 * plain
    assert (near != 255).all()


@pytest.mark.parametrize(("sheets", "gap", "one_side"), [(3, 4.0, False), (4, 5.0, True), (3, 3.0, False)])
def test_sheet_cut_matches_the_naive_rule(sheets, gap, one_side):
    pts, _ = stack(sheets, gap, n=4000, seed=2)
    pts = pts[(pts[:, 1] < 0.3)]  # a strip: fewer voxels for the naive rule
    h, r = choose_parameters(pts, None, None)
    plan = _thin_plan(pts, h, r)
    assert plan.normal is not None
    band = build_band(pts, h, r)
    vcost = band.vcost
    if one_side:
        vcost, _ = one_sided(band, plan.normal, plan.separation, plan.radius, 0.2)
    got, _ = cut_between_sheets(band, vcost, plan)
    nin = plan.normal[band.perm].astype(np.float64)
    want = naive_sheet_cut(band, vcost, nin, plan.separation[band.perm] / band.h)
    np.testing.assert_array_equal(got, want)
    assert np.isfinite(vcost).sum() > np.isfinite(got).sum()  # the rule did cut something


@pytest.mark.parametrize("kind", ["stack", "two sheets", "two sheets split"])
def test_the_planned_band_keeps_the_pieces_of_its_final_costs(kind):
    """build_planned_band hands the ordering the pieces it found while deciding (Band.pieces):
    exactly point_pieces of the band it returns, whichever band that is (the cut plain band of a
    stack, the one-sided band of two sheets, the plain band when the cut splits two sheets that
    the plain band joins)."""
    from lodbuilder._kernels.topology import point_pieces
    from lodbuilder.sampling.band import plan_and_build_band

    if kind == "stack":
        pts, _ = stack(4, 5.0, n=20_000)
    elif kind == "two sheets":
        pts, _ = stack(2, 6.0, n=20_000, seed=3)
    else:  # two sheets 5 spacings apart with no fold: the cut splits them, the plain band is kept
        rng = np.random.default_rng(2)
        pts = np.vstack([np.c_[rng.random((8000, 2)), np.zeros(8000)],
                         np.c_[rng.random((8000, 2)), np.full(8000, 5 / np.sqrt(8000))]])
    band, plan, _ = plan_and_build_band(pts, None, None)
    assert (plan.normal is None) == (kind == "two sheets split")
    assert band.pieces is not None
    piece, npiece = point_pieces(band.nbr, band.cs, band.near, band.vcost)
    assert band.pieces[1] == npiece
    assert np.array_equal(band.pieces[0], piece)
    assert fastfps(pts).stats["pieces"] == npiece


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nearest_corners_since_agrees_with_a_full_recompute(seed):
    """nearest_corners_since (only the cells whose corners changed are looked at again) gives
    exactly nearest_corners of the new costs: for the one-sided band and the cut of a stack, and
    for random voxels dropped from (and some put back into) the band."""
    from lodbuilder._kernels.topology import nearest_corners, nearest_corners_since

    pts, _ = stack(3, 4.0, n=8000, seed=seed)
    h, r = choose_parameters(pts, None, None)
    plan = _thin_plan(pts, h, r)
    band = build_band(pts, h, r)
    side, side_near = one_sided(band, plan.normal, plan.separation, plan.radius, 0.2)
    np.testing.assert_array_equal(side_near, nearest_corners(band.u, band.nbr, band.cs, side))
    cut, cut_near = cut_between_sheets(band, side, plan, side_near)
    np.testing.assert_array_equal(cut_near, nearest_corners(band.u, band.nbr, band.cs, cut))
    rng = np.random.default_rng(seed)
    new = band.vcost.copy()
    new[rng.random(new.shape[0]) < 0.6] = np.inf
    back = rng.random(new.shape[0]) < 0.05
    new[back] = 1.0  # (corners outside the band made marchable: the rule does not care why)
    got = nearest_corners_since(band.u, band.nbr, band.cs, new, band.vcost, band.near)
    want = nearest_corners(band.u, band.nbr, band.cs, new)
    assert (want == 255).any() and (want != band.near).any()
    np.testing.assert_array_equal(got, want)
