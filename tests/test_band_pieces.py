"""The band pieces of a tiled build's tiles (:func:`lodbuilder.sampling.band.band_pieces`) are the
pieces of the full band (``point_pieces`` of ``build_band``), found from the voxels' marchability
alone (:func:`lodbuilder._kernels.topology.band_marchable`): same voxels, same labels, same refusals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lodbuilder.errors import MemoryBudgetError


def _reference(pts: np.ndarray, h: float, r: float, lattice: np.ndarray | None, max_memory: int | None = None):
    from lodbuilder._kernels.topology import point_pieces
    from lodbuilder.sampling.band import build_band

    band = build_band(pts, h, r, max_memory, lattice=lattice)
    piece, n = point_pieces(band.nbr, band.cs, band.near, band.vcost)
    out = np.empty(pts.shape[0], np.int64)
    out[band.perm] = piece
    return out, int(n), band


def _scene(seed: int, kind: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == 0:  # scattered: many pieces
        return rng.random((n, 3)) * rng.uniform(1, 30)
    if kind == 1:  # blobs
        c = rng.random((5, 3)) * 40
        return c[rng.integers(0, 5, n)] + rng.normal(size=(n, 3)) * rng.uniform(0.2, 3)
    # a thin sheet on a quarter-voxel lattice: distances of exactly the band radius occur
    return np.round(np.c_[rng.random((n, 2)) * 30, rng.random(n) * 0.3] * 4) / 4


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31), kind=st.integers(0, 2), n=st.integers(1, 300),
       h=st.sampled_from([0.5, 1.0, 1.3]), ratio=st.sampled_from([1.0, 1.5, 2.0, 2.5, 3.7]),
       shift=st.booleans())
def test_band_pieces_are_the_full_bands_pieces(seed, kind, n, h, ratio, shift):
    from lodbuilder._kernels.grid import band_voxels
    from lodbuilder._kernels.topology import band_marchable
    from lodbuilder.sampling.band import band_pieces, block_plan
    from lodbuilder.sampling.spacing import cells

    pts = _scene(seed, kind, n)
    r = h * ratio
    lattice = pts.min(axis=0) - (np.random.default_rng(seed).random(3) * 3 if shift else 0.0)
    want, nwant, band = _reference(pts.copy(), h, r, lattice)
    got, ngot = band_pieces(pts.copy(), h, r, lattice=lattice)
    assert ngot == nwant
    np.testing.assert_array_equal(got, want)
    # the kernel: band_voxels' voxels, marchable where build_band's cost is finite
    cell_keys, _, u, ostart = cells(pts, band.origin, h)
    rad = r / h
    bkey, bstart, cand = block_plan(cell_keys, rad)
    keys, march, count = band_marchable(u, 1.0 / (rad * rad), rad, ostart, bkey, bstart, cand, 10**9)
    radv = np.full(n, rad)
    k2, q2, _, c2 = band_voxels(u, 1.0 / (radv * radv), radv, ostart, bkey, bstart, cand, 10**9)
    assert count == c2
    np.testing.assert_array_equal(keys, k2)
    np.testing.assert_array_equal(march.astype(bool), q2 <= 1.0)
    np.testing.assert_array_equal(march.astype(bool), np.isfinite(band.vcost))


def test_band_pieces_of_no_points():
    from lodbuilder.sampling.band import band_pieces

    piece, n = band_pieces(np.zeros((0, 3)), 1.0, 2.5)
    assert n == 0 and piece.shape == (0,) and piece.dtype == np.int64


def test_band_pieces_refuse_as_the_band_does():
    from lodbuilder.sampling.band import band_pieces, build_band

    pts = _scene(3, 0, 2000) * 10
    with pytest.raises(MemoryBudgetError) as ref:
        build_band(pts.copy(), 0.05, 0.2, 2_000_000)
    with pytest.raises(MemoryBudgetError) as got:
        band_pieces(pts.copy(), 0.05, 0.2, 2_000_000)
    assert str(got.value) == str(ref.value)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31), kind=st.integers(0, 2), n=st.integers(20, 300), ratio=st.sampled_from([1.75, 2.5]))
def test_an_orderings_pieces_on_a_lattice_are_band_pieces(seed, kind, n, ratio):
    """``fastfps(..., lattice=, pieces=True)``: its band on the given grid, and each point's piece
    of it as :func:`band_pieces` labels them (the same partition; an exact duplicate its first
    copy's): what a tiled build's ordering hands its covering task."""
    from lodbuilder import fastfps
    from lodbuilder.sampling.band import band_pieces

    pts = _scene(seed, kind, n)
    pts = np.vstack([pts, pts[: n // 5]])  # (duplicates)
    lattice = pts.min(axis=0) - np.random.default_rng(seed).random(3) * 3
    o = fastfps(pts, voxel_size=1.0, band_radius=ratio, lattice=lattice, pieces=True)
    want, nwant = band_pieces(pts, 1.0, ratio, lattice=lattice)
    assert o.pieces is not None and o.pieces.dtype == np.int32 and o.stats["pieces"] == nwant
    pairs = set(zip(o.pieces.tolist(), want.tolist(), strict=True))
    assert len(pairs) == nwant  # (a bijection of the labels)
    assert fastfps(pts, voxel_size=1.0, band_radius=ratio).pieces is None


def test_an_orderings_lattice_needs_its_grid():
    from lodbuilder import fastfps
    from lodbuilder.errors import InputError

    pts = _scene(1, 1, 100)
    with pytest.raises(InputError, match=r"^lattice places a given grid: pass voxel_size and band_radius with it$"):
        fastfps(pts, voxel_size=1.0, lattice=[0.0, 0.0, 0.0])
    with pytest.raises(InputError, match=r"^lattice must be 3 finite coordinates, got shape \(2,\)"):
        fastfps(pts, voxel_size=1.0, band_radius=2.5, lattice=[0.0, 0.0])
