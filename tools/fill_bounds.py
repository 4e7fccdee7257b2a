"""What bounds a fill's error on a punched hole (issue 21), for tools/bench_fill.py.

Per hole, points are placed over the hole at the removed points thinned to rho/2 apart (about
the synthetic points' density, so that a largest error is taken over as many points as a fill's)
on surfaces fitted

- to the TRUTH at the scale of the level (:func:`truth_errors`, ``truth_local_max_rho``): the
  quadric through the original points within 1.5 rho of each placed point (moving least squares,
  the point itself included). It reads the surface at rho resolution and no coarser: its error is
  the floor of the measure (scan noise, the mesh's facets, detail finer than rho). Where it is
  small and a fit misses, the fit lacks the surface's shape, not the measure its precision;
- to the TRUTH over the whole hole (``truth_quartic_max_rho``): the quartic through the removed
  points and those within rho of the hole: a smooth surface that knows the hole;
- to the RIM only (``rim_best_max_rho``): polynomials of degree 2-4 fitted to the punched scan's
  points within 1, 2 or 4 rho of the hole, the best of the eight chosen knowing the truth (no
  rule can choose better among them), and ``rim_cv_max_rho``: the one whose sector
  cross-validation on the inner rim is smallest (what a rule can choose).

:func:`hole_distribution` counts the filled holes whose synthetic points miss the surface by more
than 0.25 rho, by hole radius and by the hole's sagitta (the plane oracle's error: how curved the
surface is over the hole), and :func:`refusal_bound` what any confidence rule that refuses holes
could at best keep: every filled hole within 0.25 rho.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

#: a fill's largest error allowed (issue 21), in rho
TARGET = 0.25
#: moving least squares over the truth: radius of each local quadric, in rho
LOCAL = 1.5
#: rim widths (rho) and polynomial degrees of the rim fits (degree 4 only over rims >= 2 rho)
RIM_WIDTHS = (1.0, 2.0, 4.0)
RIM_DEGREES = (2, 3, 4)
#: radius bins (rho) and sagitta bins (plane oracle error, rho) of :func:`hole_distribution`
RADIUS_BINS = ((1.5, 2.5), (2.5, 3.5), (3.5, 5.0))
SAGITTA_BINS = ((0.0, 0.5), (0.5, 1.0), (1.0, 99.0))


def poly(uv: np.ndarray, deg: int) -> np.ndarray:
    """The monomials of (u, v) up to degree ``deg``, one column each."""
    return np.column_stack(
        [uv[:, 0] ** (d - i) * uv[:, 1] ** i for d in range(deg + 1) for i in range(d + 1)]
    )


def thin(points: np.ndarray, step: float) -> np.ndarray:
    """Indices of points at least ``step`` apart, greedily in input order (each point kept
    removes those within ``step`` of it): every point lies within ``step`` of one kept."""
    tree = cKDTree(points)
    alive = np.ones(points.shape[0], dtype=bool)
    kept = []
    for i in range(points.shape[0]):
        if alive[i]:
            kept.append(i)
            alive[tree.query_ball_point(points[i], step)] = False
    return np.asarray(kept, dtype=np.int64)


def _frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and eigenvectors (columns, the normal first) of ``points``."""
    cen = points.mean(axis=0)
    return cen, np.linalg.eigh((points - cen).T @ (points - cen))[1]


def _height_fit(points: np.ndarray, deg: int, rho: float):
    """(centroid, frame, coefficients): the polynomial height field of degree ``deg`` over the
    least-squares plane of ``points``, in rho units."""
    cen, vec = _frame(points)
    uv, h = (points - cen) @ vec[:, 1:] / rho, (points - cen) @ vec[:, 0] / rho
    return cen, vec, np.linalg.lstsq(poly(uv, deg), h, rcond=None)[0]


def _place(at: np.ndarray, fit, deg: int, rho: float) -> np.ndarray:
    """The points of the height field ``fit`` over the places of ``at`` in its plane."""
    cen, vec, coef = fit
    uv = (at - cen) @ vec[:, 1:] / rho
    return cen + rho * (uv @ vec[:, 1:].T + (poly(uv, deg) @ coef)[:, None] * vec[:, 0])


def _sector_cv(points: np.ndarray, inner: np.ndarray, deg: int, rho: float) -> float:
    """RMS error (rho) predicting the ``inner`` points of each sixth of ``points`` (angular
    sectors in their plane) from a fit to the other five sixths; inf when no sixth is tested."""
    cen, vec = _frame(points)
    uv, h = (points - cen) @ vec[:, 1:] / rho, (points - cen) @ vec[:, 0] / rho
    sec = np.floor((np.arctan2(uv[:, 1], uv[:, 0]) + np.pi) / (np.pi / 3)).astype(int) % 6
    err = []
    need = (deg + 1) * (deg + 2) // 2 + 3
    for s in range(6):
        train, test = sec != s, (sec == s) & inner
        if test.any() and train.sum() >= need:
            coef = np.linalg.lstsq(poly(uv[train], deg), h[train], rcond=None)[0]
            err.append(poly(uv[test], deg) @ coef - h[test])
    if not err:
        return float("inf")
    e = np.concatenate(err)
    return float(np.sqrt(np.mean(e * e)))


def truth_errors(
    original: np.ndarray,
    keep: np.ndarray,
    normals: np.ndarray,
    centre: np.ndarray,
    radius: float,
    rho: float,
    distance: Callable[[np.ndarray], np.ndarray],
    tree: cKDTree | None = None,
) -> dict:
    """Largest errors (rho) over one hole of the surfaces in the module's docstring.

    ``keep`` masks the points left by the punch, ``normals`` are the original's unit normals
    (those within 72 degrees of the hole's centre's face count: the hole's own face, not the
    other side of a thin part), ``distance`` gives the distance of points to the true surface
    (scan units). Empty when fewer than 10 points were removed from the hole's face."""
    tree = tree if tree is not None else cKDTree(original)
    d = np.linalg.norm(original - centre, axis=1)
    nc = normals[int(np.argmin(d))]
    face = np.abs(normals @ nc) > 0.3
    removed = np.flatnonzero((d < radius) & face)
    if removed.size < 10:
        return {}
    at = original[removed][thin(original[removed], 0.5 * rho)]
    placed: dict[str, np.ndarray] = {}
    local = np.empty_like(at)
    for i, q in enumerate(at):
        nb = original[tree.query_ball_point(q, LOCAL * rho)]
        local[i] = _place(q[None], _height_fit(nb, 2, rho), 2, rho)[0]
    placed["truth_local"] = local
    whole = original[(d < radius + rho) & face]
    placed["truth_quartic"] = _place(at, _height_fit(whole, 4, rho), 4, rho)
    cv = {}
    for w in RIM_WIDTHS:
        in_rim = keep & face & (d < radius + w * rho)
        rim = original[in_rim]
        for deg in RIM_DEGREES:
            if (deg == 4 and w < 2) or rim.shape[0] < 3 * (deg + 1) * (deg + 2) // 2:
                continue
            name = f"rim{w:g}_p{deg}"
            placed[name] = _place(at, _height_fit(rim, deg, rho), deg, rho)
            cv[name] = _sector_cv(rim, d[in_rim] < radius + rho, deg, rho)
    names = list(placed)
    err = distance(np.concatenate([placed[n] for n in names])) / rho
    worst = dict(zip(names, (float(e.max()) for e in np.split(err, len(names))), strict=True))
    out = {
        "truth_local_max_rho": round(worst["truth_local"], 3),
        "truth_quartic_max_rho": round(worst["truth_quartic"], 3),
    }
    rims = [n for n in names if n.startswith("rim")]
    if rims:
        out["rim_best_max_rho"] = round(min(worst[n] for n in rims), 3)
        out["rim_cv_max_rho"] = round(worst[min(rims, key=lambda n: cv[n])], 3)
    return out


def near_mesh(
    original: np.ndarray, faces: np.ndarray | None, centre: np.ndarray, reach: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """The vertices within ``reach`` of ``centre`` and the faces among them (renumbered): the
    part of the mesh that distances from a hole need (a point within ``reach`` minus its
    distance to the surface of the centre is measured exactly on it)."""
    near = np.linalg.norm(original - centre, axis=1) < reach
    idx = np.flatnonzero(near)
    if faces is None:
        return original[idx], None
    new = np.full(original.shape[0], -1, dtype=np.int64)
    new[idx] = np.arange(idx.size)
    return original[idx], new[faces[near[faces].all(axis=1)]]


def hole_distribution(holes: list[dict]) -> dict:
    """Of the filled holes: how many, and how many whose largest synthetic error exceeds
    :data:`TARGET`, in all, by radius (rho) and by sagitta (the plane oracle's error, rho)."""
    filled = [h for h in holes if h["filled"] and h.get("synthetic_error_max_rho") is not None]

    def count(hs: list) -> dict:
        over = sum(h["synthetic_error_max_rho"] > TARGET for h in hs)
        return {"filled": len(hs), "over_0.25": over}

    out = {"all": count(filled), "by_radius": {}, "by_sagitta": {}}
    for lo, hi in RADIUS_BINS:
        out["by_radius"][f"{lo:g}-{hi:g} rho"] = count(
            [h for h in filled if lo <= h["radius_rho"] < hi]
        )
    with_sag = [h for h in filled if h.get("oracle_plane_max_rho") is not None]
    for lo, hi in SAGITTA_BINS:
        out["by_sagitta"][f"{lo:g}-{hi:g} rho"] = count(
            [h for h in with_sag if lo <= h["oracle_plane_max_rho"] < hi]
        )
    return out


def refusal_bound(holes: list[dict]) -> dict:
    """What any rule that refuses holes could at best keep: every filled hole within
    :data:`TARGET` (the rule knowing the truth), as a share of all holes; and how many holes of
    all each bound of the module's docstring leaves over :data:`TARGET`."""
    ok = [
        h
        for h in holes
        if h["filled"]
        and h.get("synthetic_error_max_rho") is not None
        and h["synthetic_error_max_rho"] <= TARGET
    ]
    out: dict = {
        "holes_kept_percent": round(100.0 * len(ok) / max(len(holes), 1), 1),
        "over_0.25": {},
    }
    for key in ("truth_local", "truth_quartic", "rim_best", "rim_cv"):
        v = [h[f"{key}_max_rho"] for h in holes if h.get(f"{key}_max_rho") is not None]
        if v:
            out["over_0.25"][key] = {
                "holes": len(v),
                "over": sum(x > TARGET for x in v),
                "max": max(v),
            }
    return out
