"""The sheets of a scan: where another piece of surface lies close across a gap, measured on the
cells of a grid (:mod:`lodbuilder._kernels.sheets`), and whether the thin parts lie on flat sheets.
:mod:`lodbuilder.sampling.band` plans its one-sided band from these (its docstring gives the rule)."""

from __future__ import annotations

import numpy as np

from .._resources import release_pages
from .spacing import axis_min, cells

SEP_GAP_MIN = 1.5  # in default voxels (3 point spacings): closer layers count as one sheet
SEP_CONE = 0.8  # the other sheet's cell lies within acos(0.8) = 37 degrees of the normal
NORMAL_RADIUS = 0.9  # default voxels (1.8 point spacings): the neighbours that give a cell's normal
THIN_SHARE = 25.0  # percent: when this much of the scan is thin, hand over below 0.9 x separation
SHEET_BALL = 0.7  # x the separation: the thin cells whose normals a thin cell's is compared with
SHEET_BEND = 0.06  # a thin cell lies on a flat sheet when their mean |cos| is at least 1 - this (~20 deg)
SHEET_SAMPLE = 4096  # thin cells tested (every k-th in cell order)


def sheet_separation(points: np.ndarray, h: float, r: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point (input order), on a grid of spacing h for a band of radius r: the distance across
    the gap to the nearer other sheet within reach (inf where there is none), the same on the
    opposite side, and the unit normal toward the nearer one (float32; zero where there is none)."""
    sep_in, sep_out, normal, _ = measure_sheets(points, h, r, judge=False)
    return sep_in, sep_out, normal


def measure_sheets(
    points: np.ndarray, h: float, r: float, judge: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float | None]:
    """:func:`sheet_separation` and, when ``judge`` and at least THIN_SHARE % of the points are
    thin, the share of the thin cells tested (up to SHEET_SAMPLE) whose normals agree within
    SHEET_BALL x their separation (:func:`lodbuilder._kernels.sheets.normal_agreement`; None when
    not judged)."""
    from .._kernels.sheets import cell_separation

    n = points.shape[0]
    origin = axis_min(points) - 2 * h
    ckeys, perm, u, ostart = cells(points, origin, h)
    del ckeys
    release_pages(points)  # (a scan set aside: read again from its file by the next pass)
    sin, sout, nrm = cell_separation(u, ostart, 2 * r / h, SEP_GAP_MIN, SEP_CONE, NORMAL_RADIUS)
    counts = np.diff(ostart)
    flat = None
    if judge and int(counts[np.isfinite(sin)].sum()) >= THIN_SHARE / 100 * n:
        flat = _flat_share(u, ostart, sin, nrm)
    del u
    if not np.isfinite(sin).any():  # nothing thin (most scans): no scatter into point order
        return np.full(n, np.inf), np.full(n, np.inf), np.zeros((n, 3), dtype=np.float32), flat
    sep_in = np.empty(n)
    sep_in[perm] = np.repeat(sin * h, counts)
    sep_out = np.empty(n)
    sep_out[perm] = np.repeat(sout * h, counts)
    normal = np.empty((n, 3), dtype=np.float32)
    normal[perm] = np.repeat(nrm.astype(np.float32), counts, axis=0)
    return sep_in, sep_out, normal, flat


def _flat_share(u: np.ndarray, ostart: np.ndarray, sin: np.ndarray, nrm: np.ndarray) -> float | None:
    """The share of the thin cells tested whose normals agree (mean |cos| >= 1 - SHEET_BEND) with
    those of the thin cells within SHEET_BALL x their separation (None when none could be tested)."""
    from .._kernels.sheets import normal_agreement

    stride = max(1, int(np.isfinite(sin).sum()) // SHEET_SAMPLE)
    agree = normal_agreement(u, ostart, sin, nrm, SHEET_BALL, stride)
    agree = agree[np.isfinite(agree)]
    return float((agree >= 1.0 - SHEET_BEND).mean()) if agree.size else None
