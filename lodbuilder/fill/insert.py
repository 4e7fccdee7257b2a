"""Filling regions: farthest point insertion of candidates, and attributes for the new points.

Candidates of a region are grid nodes at spacing ``g`` on the fitted surface. They are inserted in
farthest point fashion: the candidate farthest from the level (and from the points already
inserted) goes in first, until every candidate is within ``rho - g / sqrt(2)`` of the level. Every
point of the region's fitted surface is within ``g / sqrt(2)`` (in the plane) of a candidate, so
it is then within about rho of the filled level.

Attributes of a new point are interpolated over the hole from the ring of input points around it
(all round, not only the nearest side):

* floating point attributes and the integer measurements of :data:`CONTINUOUS` (colours,
  intensity, ...) by a thin-plate spline with a linear part over the hole's plane (a linear ramp
  across the hole is reproduced exactly), clipped to the range the ring holds (integers rounded);
* normals (``nx``/``ny``/``nz``) are the fitted surface's normal, turned to agree with the
  nearest measured normals;
* any other integer or boolean attribute (classification, return number, flags, ...) is copied
  from the nearest input point: an average of categories means nothing.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: nearest ring points that orient a normal
K_ATTR = 8
#: ring points an attribute fit uses at most
MAX_FIT = 250
#: integer attributes that are measurements (averaged), not categories (copied from the nearest)
CONTINUOUS = frozenset(
    {"red", "green", "blue", "alpha", "intensity", "nir", "reflectance", "amplitude", "confidence"}
)
NORMALS = ("nx", "ny", "nz")


def farthest_insert(
    candidates: np.ndarray, start: np.ndarray, stop: float
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the candidates inserted in farthest point order and their insertion radii.

    ``start`` (M,) is each candidate's distance to the points already there; insertion stops when
    the largest distance is <= ``stop``. Deterministic: ties go to the lowest index.
    """
    d = np.array(start, dtype=np.float64)
    picked: list[int] = []
    radii: list[float] = []
    while d.size:
        i = int(np.argmax(d))
        if not d[i] > stop:
            break
        picked.append(i)
        radii.append(float(d[i]))
        np.minimum(d, np.linalg.norm(candidates - candidates[i], axis=1), out=d)
    return np.asarray(picked, dtype=np.int64), np.asarray(radii, dtype=np.float64)


def stop_distance(rho: float, grid: float) -> float:
    """Insertion stops at this candidate distance so that the surface is covered within rho."""
    return rho - grid / math.sqrt(2.0)


def _is_continuous(name: str, arr: np.ndarray) -> bool:
    return arr.dtype.kind == "f" or (arr.dtype.kind in "iu" and name in CONTINUOUS)


def region_attributes(
    attributes: dict[str, np.ndarray],
    sample: np.ndarray,
    region: Any,
    picked: np.ndarray,
) -> dict[str, np.ndarray]:
    """Attributes of the candidates ``picked`` of ``region`` (a
    :class:`~lodbuilder.fill.gaps.Region`), interpolated from its ring of input points
    (``attributes`` are per sample point, same rows as ``sample``)."""
    from scipy.spatial import cKDTree

    from .surface import _rbf

    ring = region.ring
    pts = region.candidates[picked]
    m = pts.shape[0]
    ring_pts = sample[ring]
    tree = cKDTree(ring_pts)
    k = min(K_ATTR, ring.size)
    _, near = tree.query(pts, k=k)
    near = np.asarray(near, dtype=np.int64).reshape(m, k)
    out: dict[str, np.ndarray] = {}
    if all(c in attributes for c in NORMALS) and m:
        nrm = region.normals_at(picked)
        measured = np.stack([np.asarray(attributes[c])[ring] for c in NORMALS], axis=1)
        agree = np.einsum("mki,mi->m", measured[near].astype(np.float64), nrm)
        nrm[agree < 0] *= -1.0
        for j, c in enumerate(NORMALS):
            out[c] = nrm[:, j].astype(np.asarray(attributes[c]).dtype)
    cont = [n for n, a in attributes.items() if n not in out and _is_continuous(n, np.asarray(a))]
    if cont and m:
        cols = [
            np.asarray(attributes[n])[ring].reshape(ring.size, -1).astype(np.float64) for n in cont
        ]
        widths = [c.shape[1] for c in cols]
        vals = np.concatenate(cols, axis=1)
        ring_uv = region.coordinates(ring_pts)
        keep = np.arange(ring.size)
        if ring.size > MAX_FIT:
            keep = np.linspace(0, ring.size - 1, MAX_FIT).round().astype(np.int64)
        fit = _rbf(ring_uv[keep], vals[keep], degree=1)(region.coordinates(pts))
        fit = np.clip(fit, vals.min(axis=0), vals.max(axis=0))
        start = 0
        for name, w in zip(cont, widths, strict=True):
            a = np.asarray(attributes[name])
            v = fit[:, start : start + w].reshape((m,) + a.shape[1:])
            start += w
            if a.dtype.kind == "f":
                out[name] = v.astype(a.dtype)
            else:
                out[name] = np.rint(v).astype(a.dtype)  # within the ring's range: no overflow
    for name, arr in attributes.items():
        if name not in out:
            a = np.asarray(arr)
            out[name] = a[ring][near[:, 0]] if m else a[:0]
    return out
