"""Neighbourhoods and local PCA, vectorised and chunked.

Neighbour queries go through :class:`scipy.spatial.cKDTree` with ``workers=-1``. A neighbourhood is
either the k nearest points (a dense ``(N, k)`` index array, the point itself included) or every point
within a radius (CSR: ``indptr``, ``indices``). Local covariances of all neighbourhoods are computed at
once per chunk (``einsum`` on ``(chunk, k, 3)`` offsets), so memory stays bounded by ``chunk_bytes``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError

#: bytes of temporary arrays a chunk may use (offsets, products); 64 MiB by default
CHUNK_BYTES = 64 * 2**20


@dataclass
class Neighbourhoods:
    """Neighbour lists of N points.

    Exactly one representation is set: ``knn`` (N, k) int64 (each row sorted by distance, the point
    itself usually first), or ``indptr`` (N + 1,) / ``indices`` (nnz,) for radius neighbourhoods.
    """

    n: int
    knn: np.ndarray | None = None
    indptr: np.ndarray | None = None
    indices: np.ndarray | None = None

    def counts(self) -> np.ndarray:
        if self.knn is not None:
            return np.full(self.n, self.knn.shape[1], dtype=np.int64)
        assert self.indptr is not None
        return np.diff(self.indptr)

    def rows(self) -> tuple[np.ndarray, np.ndarray]:
        """Flat (row, neighbour) pairs: two (nnz,) int64 arrays."""
        if self.knn is not None:
            k = self.knn.shape[1]
            return np.repeat(np.arange(self.n, dtype=np.int64), k), self.knn.reshape(-1)
        assert self.indptr is not None and self.indices is not None
        return np.repeat(np.arange(self.n, dtype=np.int64), self.counts()), self.indices

    def without_self(self) -> Neighbourhoods:
        """The same neighbourhoods with each point removed from its own list.

        For kNN rows the entry equal to the row index is dropped (the farthest neighbour when the
        point is missing, e.g. among exact duplicates), so every row keeps k - 1 entries.
        """
        if self.knn is not None:
            idx = self.knn
            k = idx.shape[1]
            if k < 2:
                raise InputError(
                    "a neighbourhood needs k >= 2 points to leave the point itself out"
                )
            drop = idx == np.arange(self.n)[:, None]
            missing = ~drop.any(axis=1)
            drop[missing, k - 1] = True
            # a row could hold the point twice only with duplicate indices, which cKDTree never returns
            return Neighbourhoods(self.n, knn=idx[~drop].reshape(self.n, k - 1))
        rows, cols = self.rows()
        keep = rows != cols
        counts = np.bincount(rows[keep], minlength=self.n)
        indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        return Neighbourhoods(self.n, indptr=indptr, indices=cols[keep])


def kd_tree(points: np.ndarray) -> Any:
    from scipy.spatial import cKDTree

    return cKDTree(points)


def knn(points: np.ndarray, k: int, tree: Any = None) -> Neighbourhoods:
    """The ``k`` nearest neighbours of every point (the point itself included), queried in chunks."""
    n = points.shape[0]
    k = check_k(k)
    k = min(k, n)
    tree = kd_tree(points) if tree is None else tree
    out = np.empty((n, k), dtype=np.int64)
    step = max(1, CHUNK_BYTES // (16 * k))
    for s in range(0, n, step):
        _, idx = tree.query(points[s : s + step], k=k, workers=-1)
        out[s : s + step] = np.asarray(idx, dtype=np.int64).reshape(-1, k)
    return Neighbourhoods(n, knn=out)


def radius_neighbours(points: np.ndarray, radius: float, tree: Any = None) -> Neighbourhoods:
    """Every point within ``radius`` of each point (the point itself included), as CSR."""
    n = points.shape[0]
    tree = kd_tree(points) if tree is None else tree
    lists = tree.query_ball_point(points, r=radius, workers=-1, return_sorted=False)
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=n)
    indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    indices = np.fromiter((j for x in lists for j in x), dtype=np.int64, count=int(indptr[-1]))
    return Neighbourhoods(n, indptr=indptr, indices=indices)


def neighbourhoods(
    points: np.ndarray, k: int | None = None, radius: float | None = None, tree: Any = None
) -> Neighbourhoods:
    """kNN when ``radius`` is None, else radius neighbourhoods."""
    if radius is not None:
        r = float(radius)
        if not np.isfinite(r) or r <= 0:
            raise InputError(f"neighbourhood radius must be a finite number > 0, got {radius!r}")
        return radius_neighbours(points, r, tree)
    return knn(points, 16 if k is None else k, tree)


def check_k(k: Any, name: str = "k") -> int:
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) or int(k) < 3:
        raise InputError(f"{name} (neighbours per point) must be a whole number >= 3, got {k!r}")
    return int(k)


def _row_chunks(nb: Neighbourhoods, bytes_per_entry: int):
    """Yield (s, e, lo, hi): row ranges whose neighbour entries fit :data:`CHUNK_BYTES`."""
    step_nnz = max(1, CHUNK_BYTES // bytes_per_entry)
    if nb.knn is not None:
        k = nb.knn.shape[1]
        step = max(1, step_nnz // k)
        for s in range(0, nb.n, step):
            e = min(nb.n, s + step)
            yield s, e, s * k, e * k
        return
    assert nb.indptr is not None
    s = 0
    while s < nb.n:
        e = int(np.searchsorted(nb.indptr, nb.indptr[s] + step_nnz, side="right")) - 1
        e = min(nb.n, max(e, s + 1))
        yield s, e, int(nb.indptr[s]), int(nb.indptr[e])
        s = e


def _flat(nb: Neighbourhoods) -> np.ndarray:
    return nb.knn.reshape(-1) if nb.knn is not None else nb.indices  # type: ignore[return-value]


def local_pca(
    points: np.ndarray, nb: Neighbourhoods, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Covariance eigen-analysis of every neighbourhood.

    Args:
        weights: optional per-entry weights >= 0 in the flat layout of :meth:`Neighbourhoods.rows`
            (a weighted covariance; used for robust refits).

    Returns ``(evals, normals, centroids)``: (N, 3) eigenvalues in ascending order, (N, 3) unit
    eigenvectors of the smallest eigenvalue (unoriented normals) and (N, 3) neighbourhood centroids.
    Offsets are taken relative to each query point before summing, so large coordinates (survey
    data at 1e6 m) keep their precision.
    """
    n = points.shape[0]
    cov = np.zeros((n, 3, 3))
    cen = points.copy()
    if nb.knn is not None:  # dense (c, k, 3) blocks: one einsum per chunk
        k = nb.knn.shape[1]
        for s, e, lo, hi in _row_chunks(nb, 160):
            q = points[nb.knn[s:e]] - points[s:e, None, :]  # local offsets
            w = np.ones((e - s, k)) if weights is None else weights[lo:hi].reshape(e - s, k)
            wsum = w.sum(axis=1)
            safe = np.where(wsum > 0, wsum, 1.0)
            m = np.einsum("nk,nki->ni", w, q) / safe[:, None]
            q -= m[:, None, :]
            cov[s:e] = np.einsum("nk,nki,nkj->nij", w, q, q) / safe[:, None, None]
            cen[s:e] += m
        return _eig(cov, cen)
    flat = _flat(nb)
    counts = nb.counts()
    for s, e, lo, hi in _row_chunks(nb, 160):
        rows = np.repeat(np.arange(s, e, dtype=np.int64), counts[s:e])
        q = points[flat[lo:hi]] - points[rows]  # local offsets
        w = np.ones(hi - lo) if weights is None else weights[lo:hi]
        wsum = np.bincount(rows - s, weights=w, minlength=e - s)
        safe = np.where(wsum > 0, wsum, 1.0)
        m = np.stack(
            [np.bincount(rows - s, weights=w * q[:, c], minlength=e - s) for c in range(3)], 1
        )
        m /= safe[:, None]
        q -= m[rows - s]
        outer = np.einsum("ni,nj,n->nij", q, q, w).reshape(-1, 9)
        so = np.stack(
            [np.bincount(rows - s, weights=outer[:, c], minlength=e - s) for c in range(9)], 1
        )
        cov[s:e] = so.reshape(-1, 3, 3) / safe[:, None, None]
        cen[s:e] += m
    return _eig(cov, cen)


def _eig(cov: np.ndarray, cen: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    evals, evecs = np.linalg.eigh(cov)
    evals = np.maximum(evals, 0.0)  # rounding can leave -1e-20 on flat neighbourhoods
    return evals, np.ascontiguousarray(evecs[:, :, 0]), cen


def plane_residuals(
    points: np.ndarray, nb: Neighbourhoods, normals: np.ndarray, centroids: np.ndarray
) -> np.ndarray:
    """Per-entry distance of each neighbour to its row's plane (flat layout of ``rows()``)."""
    flat = _flat(nb)
    counts = nb.counts()
    out = np.empty(flat.shape[0])
    for s, e, lo, hi in _row_chunks(nb, 64):
        rows = np.repeat(np.arange(s, e, dtype=np.int64), counts[s:e])
        d = points[flat[lo:hi]] - centroids[rows]
        out[lo:hi] = np.abs(np.einsum("ij,ij->i", d, normals[rows]))
    return out


def mean_pair_function(nb: Neighbourhoods, fn: Any) -> np.ndarray:
    """Mean over each neighbourhood of ``fn(i, j)`` (flat index arrays in, flat values out),
    evaluated in chunks of rows so temporaries stay within :data:`CHUNK_BYTES`."""
    out = np.zeros(nb.n)
    flat = _flat(nb)
    counts = nb.counts()
    for s, e, lo, hi in _row_chunks(nb, 96):
        rows = np.repeat(np.arange(s, e, dtype=np.int64), counts[s:e])
        sums = np.bincount(rows - s, weights=fn(rows, flat[lo:hi]), minlength=e - s)
        out[s:e] = sums / np.maximum(counts[s:e], 1)
    return out


def median_of_entries(values: np.ndarray, nb: Neighbourhoods) -> np.ndarray:
    """Per-row median of per-entry ``values`` (flat layout of :meth:`Neighbourhoods.rows`); 0 for
    empty rows."""
    if nb.knn is not None:
        return np.median(values.reshape(nb.n, -1), axis=1)
    assert nb.indptr is not None
    rows, _ = nb.rows()
    order = np.lexsort((values, rows))
    vs = values[order]
    c = nb.counts()
    has = c > 0
    lo = nb.indptr[:-1] + (c - 1) // 2
    hi = nb.indptr[:-1] + c // 2
    out = np.zeros(nb.n)
    out[has] = 0.5 * (vs[lo[has]] + vs[hi[has]])
    return out


def median_over_neighbours(values: np.ndarray, nb: Neighbourhoods) -> np.ndarray:
    """Median over each neighbourhood of a per-point quantity ``values`` (N,)."""
    return median_of_entries(values[_flat(nb)], nb)
