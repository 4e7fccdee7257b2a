"""A sample on a thin part seeds its own voxel: its front reaches the points beside it.

The seeding ball keeps a straight distance from a thin part's sample only along chords within
TAIL_SLOPE of both ends' sheets. Where a thin part curves round (the tip of the bunny's ear in
bunnyDouble.e57, its two faces 3.3 spacings apart), the normal spread over the tip is steep to every
chord from the sample to its own voxel's nearest point, so no voxel of the ball was seeded (the
others see the sample through that voxel) and the sample's front never started: its neighbours
kept their distance from earlier samples and were taken one after the other (samples 5-8 of
bunnyDouble were 0.8-7 mm from sample 4, inserted at radius 96-97 mm). The voxel a sample reads
its own distance from is now seeded whatever the chord rule says (reading from it is as fair as
seeding it); the rest of the ball still needs the rule."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lodbuilder import fastfps
from lodbuilder.sampling.band import band_distance


@pytest.fixture(scope="module")
def bunny_double(shared_data):
    from lodbuilder.io import read_scan

    return np.asarray(read_scan(shared_data / "bunnyDouble.e57").points, dtype=np.float64)


@pytest.mark.data
def test_a_sample_at_a_thin_tip_reaches_its_neighbours(bunny_double):
    # before: from point 8129 (the ear's tip) only the point itself was reached (30,570 at inf)
    pts = bunny_double
    d = band_distance(pts, np.array([8129]))
    assert np.isfinite(d).all()
    near = cKDTree(pts).query_ball_point(pts[8129], 0.003)  # ~2.4 spacings
    # (13.9 mm now: the other face of the tip, 3.3 spacings away, measured round the band's outside)
    assert d[near].max() <= 5 * 0.003, d[near].max()


@pytest.mark.data
def test_coarse_samples_are_never_beside_an_earlier_one(bunny_double):
    # before: samples 5, 6, 8 lay 1.2, 1.2, 0.8 mm (under a spacing) from sample 4 at radius 96-97 mm
    pts = bunny_double
    o = fastfps(pts)
    k = 200
    for i in range(1, k):
        e = cKDTree(pts[o.order[:i]]).query(pts[o.order[i]])[0]
        assert e >= 0.3 * o.radius[i], (i, e, o.radius[i])
