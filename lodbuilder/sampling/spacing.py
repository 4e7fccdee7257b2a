"""The point spacing and the cells the points are sorted into (the grid's first step).

The spacing rule (median distance to the 6th neighbour x sqrt(pi / 6)) is the one the band's
automatic parameters start from: see :mod:`lodbuilder.sampling.band`.
"""

from __future__ import annotations

import math

import numpy as np

from .._resources import cores as _cores


def axis_min(points: np.ndarray) -> np.ndarray:
    """``points.min(axis=0)`` of ``points`` (N, D), column by column: NumPy reduces a C-ordered
    (N, 3) array along its first axis about 14 x slower (27 ms for 1M points); the same values."""
    return np.array([points[:, j].min() for j in range(points.shape[1])], dtype=points.dtype)


def axis_max(points: np.ndarray) -> np.ndarray:
    """``points.max(axis=0)``, column by column (see :func:`axis_min`)."""
    return np.array([points[:, j].max() for j in range(points.shape[1])], dtype=points.dtype)


def cells(points: np.ndarray, origin: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points sorted into cubic cells of ``size`` from ``origin``: the occupied cells' Morton
    keys (sorted, one per cell), the permutation (input index of each sorted point), the points'
    grid coordinates in that order and the start of every cell's run (with N at the end)."""
    from .._kernels.grid import cell_order, grid_coords

    n = points.shape[0]
    keys, perm = sorted_keys(cell_order(points, origin, size))
    u = grid_coords(points, perm, origin, size)
    first = np.empty(n, dtype=bool)
    first[0] = True
    np.not_equal(keys[1:], keys[:-1], out=first[1:])
    ostart = np.append(np.flatnonzero(first), n).astype(np.int32)
    return keys[ostart[:-1]], perm, u, ostart


SORTED_SHARE = 1 / 64  # keys with fewer descents than this share of them are nearly sorted


def sorted_keys(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cell keys (non-negative int64) sorted, and the int32 permutation that sorts them
    (stable: equal keys in input order), i.e. np.argsort(keys, kind="stable"): NumPy's merge sort
    when the keys are nearly sorted already (a scan in scan-line order: it only merges runs), a
    radix sort otherwise (a third of the time of the merge sort on a million keys in random order)."""
    from .._kernels.grid import radix_argsort

    n = keys.shape[0]
    if n < 2 or np.count_nonzero(keys[1:] < keys[:-1]) < SORTED_SHARE * n:
        perm = np.argsort(keys, kind="stable").astype(np.int32)
        return keys[perm], perm
    return radix_argsort(keys)


THREAD_MIN_QUERIES = 4096  # fewer queries are answered in this thread alone


def _in_two_threads(kernel, u, ostart, cell_keys, queries, k):  # noqa: ANN001 - a numba kernel and its arrays
    """``kernel(u, ostart, cell_keys, queries, k)`` -> per-query arrays, with the second half of
    the queries answered on a second thread when there are two cores and enough queries (the
    kernels release the GIL; the result is the same)."""
    nq = queries.shape[0]
    if nq < THREAD_MIN_QUERIES or _cores() < 2:
        return kernel(u, ostart, cell_keys, queries, k)
    from concurrent.futures import ThreadPoolExecutor

    half = nq // 2
    with ThreadPoolExecutor(1) as pool:
        second = pool.submit(kernel, u, ostart, cell_keys, queries[half:], k)
        first = kernel(u, ostart, cell_keys, queries[:half], k)
        rest = second.result()
    return tuple(np.concatenate((a, b)) for a, b in zip(first, rest, strict=True))


def median_spacing(
    points: np.ndarray, sample: int = 20_000, k: int = 6, subset: int = 500_000
) -> float:
    """Typical point spacing: the median distance to the k-th neighbour times sqrt(pi / k).

    On a surface sampled at density 1/s^2 this is about s whether the samples are a jittered grid
    (like a range scan) or random; the plain nearest-neighbour distance would be half of s for random
    samples. Measured on a deterministic sample of the points; above ``subset`` points the
    neighbours are searched in a random subset of that size and the spacing scaled by
    sqrt(subset / n) (a surface's spacing grows as the square root of the thinning). The search is
    exact: points hashed into cells, the cell size doubled until the k-th neighbour of most queries
    lies within one cell (no k-d tree: scipy.spatial would cost the build process 26 MB).
    """
    from .._kernels.grid import kth_neighbour

    n = points.shape[0]
    if n < 2:
        return 0.0
    rng = np.random.default_rng(0)
    scale = 1.0
    if n > subset:
        points = points[np.sort(rng.choice(n, subset, replace=False))]
        scale = math.sqrt(subset / n)
        n = subset
    q = points[rng.choice(n, sample, replace=False)] if n > sample else points
    k = min(k, n - 1)
    lo = axis_min(points)
    ext = float((axis_max(points) - lo).max())
    if ext <= 0.0:
        return 0.0
    c = max(2.5 * ext / math.sqrt(n), ext * 2.0**-20)  # 2.5 x the spacing of n points on a square
    while True:
        origin = lo - c
        keys, _, u, ostart = cells(points, origin, c)
        dk, sure = _in_two_threads(kth_neighbour, u, ostart, keys, (q - origin) / c, k + 1)
        if sure.mean() >= 0.9 or c >= 4 * ext:
            break
        c *= 2.0
    dk = dk[np.isfinite(dk)] * c
    s = float(np.median(dk)) * math.sqrt(math.pi / k) * scale if dk.size else 0.0
    if s <= 0.0:
        s = float(dk[dk > 0].min()) if (dk > 0).any() else 0.0
    return s
