"""The input around a group of seeds, over a plane: which points are on the seeds' sheet, the
grid of candidate nodes, and the flood of the nodes far from every point (see
:mod:`lodbuilder.fill.gaps`, steps 3 and 4)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .surface import MAX_TILT, Frame

#: neighbours per sample point for normals and the seeds' plane (and links along the surface)
K_SAMPLE = 8
#: longest link between neighbouring sample points along the surface, in units of rho
LINK = 1.5
#: grid nodes within NEAR_FRACTION * rho of a measured point are not in a region
NEAR_FRACTION = 0.5


def on_sheet(local: np.ndarray, seeds: np.ndarray, rho: float, limit: float) -> np.ndarray:
    """Mask of the ``local`` points on the seeds' sheet: within ``limit`` of the points next to
    the seeds along the surface (shortest paths over links to each point's :data:`K_SAMPLE`
    nearest points within :data:`LINK` rho). Steep and curved parts of that sheet are kept
    whatever their angle to the hole's plane; another sheet is dropped unless the surface
    joins them within ``limit`` (a fold, the edge of a thin part)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    n = local.shape[0]
    tree = cKDTree(local)
    k = min(K_SAMPLE + 1, n)
    d, nb = tree.query(local, k=k, distance_upper_bound=LINK * rho)
    d, nb = np.asarray(d).reshape(n, k)[:, 1:].ravel(), np.asarray(nb).reshape(n, k)[:, 1:].ravel()
    ok = np.isfinite(d)
    rows = np.repeat(np.arange(n), k - 1)[ok]
    # (a zero weight is no edge to csgraph: duplicates get a tiny length)
    g = coo_matrix((d[ok] + 1e-9 * rho, (rows, nb[ok])), shape=(n, n)).tocsr()
    _, src = tree.query(seeds, k=min(3, n))
    dist = dijkstra(g, directed=False, indices=np.unique(src), min_only=True, limit=limit)
    return np.isfinite(dist)


#: a point whose normal, oriented along the surface from the seeds' side, has this dot product
#: with the hole's normal or less faces away: the other face of a thin part
FACING = -0.3
#: ring points within rho/2 over the plane and this many rho apart in height: maybe two faces
STACKED = 0.6


def facing(points: np.ndarray, normal: np.ndarray, seeds: np.ndarray, rho: float, cloud):
    """(N,) dot product with ``normal`` of each point's normal oriented along the surface
    (:func:`oriented_normals`). The other face of a thin part (an ear, a leaf), reached round
    its edge, faces the other way."""
    return oriented_normals(points, normal, seeds, rho, cloud) @ normal


def oriented_normals(points: np.ndarray, normal: np.ndarray, seeds: np.ndarray, rho: float, cloud):
    """(N, 3) unit normals of ``points`` (from the nearest points of ``cloud``:
    :func:`fitting_normals`) oriented consistently along the surface: over
    a minimum spanning tree of links to the :data:`K_SAMPLE` nearest points within :data:`LINK`
    rho, weighted by how much the normals differ (Hoppe et al. 1992) and by how steep the link
    is to them (a link across a thin part's gap), from the point of each
    connected piece nearest the seeds, itself oriented along ``normal``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
    from scipy.spatial import cKDTree

    n = points.shape[0]
    nrm = fitting_normals(points, cloud)
    k = min(K_SAMPLE + 1, n)
    d, nb = cKDTree(points).query(points, k=k, distance_upper_bound=LINK * rho)
    d, nb = np.asarray(d).reshape(n, k)[:, 1:].ravel(), np.asarray(nb).reshape(n, k)[:, 1:].ravel()
    ok = np.isfinite(d)
    rows, cols = np.repeat(np.arange(n), k - 1)[ok], nb[ok]
    # a link across a thin gap (two faces of a thin part closer than LINK) runs along the
    # normals, a link over the surface across them: steep links cost as much as a turn of 90
    # degrees, so orientation goes round the fold, not across the gap (whose faces' normals
    # are parallel and would orient both faces the same way)
    e = points[cols] - points[rows]
    e /= np.maximum(np.linalg.norm(e, axis=1), 1e-300)[:, None]
    steep = np.maximum(
        np.abs(np.einsum("ij,ij->i", e, nrm[rows])), np.abs(np.einsum("ij,ij->i", e, nrm[cols]))
    )
    w = 1.0 - np.abs(np.einsum("ij,ij->i", nrm[rows], nrm[cols])) + steep + 1e-6
    g = coo_matrix((w, (rows, cols)), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(g.maximum(g.T))
    tree = tree + tree.T
    # each piece's root (its point nearest the seeds) points at itself; the others at the parent
    up = np.full(n, -1, dtype=np.int64)
    sign = np.ones(n)
    for root in np.argsort(np.linalg.norm(points - seeds.mean(axis=0), axis=1)):
        if up[root] >= 0:
            continue  # in a piece already walked
        order, pred = breadth_first_order(tree, root, directed=False)
        up[order] = pred[order]
        up[root] = root
        sign[root] = 1.0 if nrm[root] @ normal >= 0 else -1.0
    child = np.flatnonzero(up != np.arange(n))
    sign[child] = np.where(np.einsum("ij,ij->i", nrm[child], nrm[up[child]]) >= 0, 1.0, -1.0)
    # the product of the flips along the path to the root (pointer jumping)
    while True:
        go = up != up[up]
        if not go.any():
            break
        sign[go] *= sign[up[go]]
        up[go] = up[up[go]]
    sign[child] *= sign[up[child]]
    return nrm * sign[:, None]


def same_face(ring: np.ndarray, points: np.ndarray, frame: Frame, seeds, rho: float):
    """The mask ``ring`` (over ``points``) less the points facing away from the hole's side
    (:func:`facing` <= :data:`FACING`, normals oriented along the surface from the ``seeds``
    over the points within 2 rho of the ring): the other face of a thin part, reached round a fold within the grid,
    a rho or so behind the hole's face (an ear's tip) is not the hole's surface. Unchanged
    when none face away, or half of the ring or more (then the seeds' side is not known), and
    (without orienting anything) when no two ring points within rho/2 of each other over the
    plane lie :data:`STACKED` rho apart in height: one face."""
    from scipy.spatial import cKDTree

    r = np.flatnonzero(ring)
    if r.size < 12:
        return ring
    uv, h = frame.uv(points[r]), frame.height(points[r])
    tree = cKDTree(uv)
    d, nb = tree.query(uv, k=min(5, r.size), distance_upper_bound=0.5 * rho)
    nb = np.where(np.isfinite(d), nb, np.arange(r.size)[:, None])
    if not (np.abs(h[nb] - h[:, None]) > STACKED * rho).any():
        return ring
    # oriented over the points within 2 rho of the ring over the plane (a fold next to it)
    near = np.isfinite(tree.query(frame.uv(points), k=1, distance_upper_bound=2.0 * rho)[0])
    dots = np.zeros(points.shape[0])
    dots[near] = facing(points[near], frame.normal, seeds, rho, points[near])
    away = dots[r] <= FACING
    if not away.any() or 2 * int(away.sum()) >= away.size:
        return ring
    out = ring.copy()
    out[r[away]] = False
    return out


def near_plane(local: np.ndarray, frame: Frame, rho: float, slope: float) -> np.ndarray:
    """Mask of the local points near the hole's plane: |h| <= rho + slope |uv| (a cone), which
    drops far sheets across the plane (at ``SLOPE``, 27 degrees, also a steep part of the
    hole's own sheet)."""
    h = np.abs(frame.height(local))
    r = np.linalg.norm(frame.uv(local), axis=1)
    return h <= rho + slope * r


def normals_at(points: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    """PCA normals of ``points`` from their nearest points of ``cloud``."""
    from scipy.spatial import cKDTree

    k = min(K_SAMPLE + 1, cloud.shape[0])
    _, nb = cKDTree(cloud).query(points, k=k)
    nbhd = cloud[np.asarray(nb).reshape(points.shape[0], k)]
    c = nbhd - nbhd.mean(axis=1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", c, c))
    return vec[:, :, 0]


def fitting_normals(points: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    """Normals of ``points`` that fit their own sheet: of each point's PCA normal (from its
    nearest points of ``cloud``) and those of those nearest points, the one whose plane through
    the point lies closest to most of them (least median distance). At the edge of one face
    of a thin part, a point of the other face among the nearest tilts the PCA plane (up to
    edge-on: its normal along the face), while the normal of a point inside the face fits the
    edge point's own neighbours."""
    from scipy.spatial import cKDTree

    k = min(K_SAMPLE + 1, cloud.shape[0])
    tree = cKDTree(cloud)
    _, nb = tree.query(points, k=k)
    nb = np.asarray(nb).reshape(points.shape[0], k)
    cloud_nrm = normals_at(cloud, cloud)
    own = normals_at(points, cloud)
    cand = np.concatenate([own[:, None, :], cloud_nrm[nb]], axis=1)  # (N, k + 1, 3)
    off = cloud[nb] - points[:, None, :]  # (N, k, 3)
    miss = np.median(np.abs(np.einsum("nci,nki->nck", cand, off)), axis=2)
    best = np.argmin(miss, axis=1)  # (the first, the own normal, wins ties)
    return cand[np.arange(points.shape[0]), best]


class Grid:
    """Square grid of nodes at spacing ``g`` and half width ``half`` (in nodes) in a frame."""

    def __init__(self, frame: Frame, g: float, half: int) -> None:
        self.frame, self.g, self.half = frame, g, half
        side = 2 * half + 1
        ij = np.indices((side, side)).reshape(2, -1).T
        self.uv = (ij - half) * g
        self.shape = (side, side)

    def area_factor(self, nodes: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Surface area per unit of plane area, sqrt(1 + |grad h|^2), at the grid ``nodes`` of
        heights ``h``: finite differences with the neighbouring nodes of the same set (forward,
        else backward; 0 slope along an axis where a node has no neighbour)."""
        full = np.full(self.shape[0] * self.shape[1], np.nan)
        full[nodes] = h
        full = full.reshape(self.shape)
        grads = []
        for axis in (0, 1):
            fwd = np.diff(full, axis=axis, append=np.nan)
            bwd = np.diff(full, axis=axis, prepend=np.nan)
            d = np.where(np.isnan(fwd), bwd, fwd)
            grads.append(np.nan_to_num(d.ravel()[nodes]) / self.g)
        return np.sqrt(1.0 + grads[0] ** 2 + grads[1] ** 2)

    def node_of(self, uv: np.ndarray) -> np.ndarray:
        ij = np.rint(uv / self.g).astype(np.int64) + self.half
        inside = ((ij >= 0) & (ij < self.shape[0])).all(axis=1)
        flat = ij[:, 0] * self.shape[1] + ij[:, 1]
        return np.where(inside, flat, -1)


def flood(grid: Grid, tree2: Any, seed_uv: np.ndarray, rho: float):
    """Labels of the empty nodes (farther than rho/2 from the projected sample points indexed by
    ``tree2``) reachable from seeds: a list of (node indices, touches the grid's edge, opened).

    A region that touches the edge only through a channel in which no node is farther than rho
    from the points (a seam of sparser points: the surface there is within rho of the input) is
    cut at that channel (*opened*): its core (nodes farther than rho from every point) widened
    again by rho/2 within it (a morphological opening); a part of it with a seed that stays
    off the edge is enclosed."""
    from scipy import ndimage

    d, _ = tree2.query(grid.uv, k=1, distance_upper_bound=1.01 * rho)
    empty = ~(d <= NEAR_FRACTION * rho)
    labels, _ = ndimage.label(empty.reshape(grid.shape))
    labels = labels.ravel()
    nodes = grid.node_of(seed_uv)
    nodes = nodes[nodes >= 0]
    hit = np.unique(labels[nodes])
    edge = _edge_labels(labels.reshape(grid.shape))
    out = []
    for lab in hit[hit > 0]:
        mask = labels == lab
        if lab in edge:
            out += _opened(grid, mask, ~(d <= rho), nodes, rho)
        else:
            out.append((np.flatnonzero(mask), False, False))
    return out


def _edge_labels(labels: np.ndarray) -> np.ndarray:
    return np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))


def _opened(grid: Grid, mask: np.ndarray, far: np.ndarray, seed_nodes: np.ndarray, rho: float):
    """The enclosed parts of the region ``mask`` that touches the grid's edge: its core (``far``:
    nodes farther than rho from every point) widened by rho/2 within it, the parts with a seed
    within rho/2 that stay off the edge (opened); the rest of the region as leaking."""
    from scipy import ndimage

    k = max(1, int(round(NEAR_FRACTION * rho / grid.g)))
    ij = np.indices((2 * k + 1, 2 * k + 1)) - k
    disk = (ij[0] ** 2 + ij[1] ** 2) <= k * k
    box = mask.reshape(grid.shape)
    opened = ndimage.binary_dilation(box & far.reshape(grid.shape), structure=disk) & box
    labels, _ = ndimage.label(opened)
    seeds = np.zeros(mask.size, dtype=bool)
    seeds[seed_nodes] = True
    near = ndimage.binary_dilation(seeds.reshape(grid.shape), structure=disk) & opened
    edge = _edge_labels(labels)
    inner = [lab for lab in np.unique(labels[near]) if lab not in edge]
    flat = labels.ravel()
    out = [(np.flatnonzero(flat == lab), False, True) for lab in inner]
    return out + [(np.flatnonzero(mask & ~np.isin(flat, inner)), True, False)]


#: seeds spread over a plane (its smallest spread at most this share of the next) fix the
#: hole's plane themselves
FLAT_SEEDS = 0.25


def group_normal(seeds: np.ndarray, normals: np.ndarray, rho: float, min_seeds: int):
    """The normals of a group's planes: the sum of the seeds' level ``normals`` (oriented like
    the first), and the plane of the ``seeds`` themselves where they spread over one that most
    of the normals face within 60 degrees (else None): round a hole on a curved place the level normals at its rim turn by as much as the
    surface does, and their sum can be far off; the seeds along a border lie in a plane across
    the surface. Groups of fewer than ``min_seeds`` seeds have no plane of their own."""
    nrm = normals * np.where(normals @ normals[0] < 0, -1.0, 1.0)[:, None]
    summed = nrm.sum(axis=0)
    if seeds.shape[0] >= min_seeds:
        c = seeds - seeds.mean(axis=0)
        w, vec = np.linalg.eigh(c.T @ c)
        flat = w[1] >= (rho / 2) ** 2 * seeds.shape[0] and w[0] <= FLAT_SEEDS * w[1]
        if flat and np.median(np.abs(normals @ vec[:, 0])) >= np.cos(MAX_TILT):
            return summed, vec[:, 0]
    return summed, None


def stacked(tree2: Any, h: np.ndarray, rho: float) -> bool:
    """Some of the points (projected in ``tree2``, heights ``h``) lie over one another (within
    rho/2 in the plane, 1.5 rho apart in height): two faces, or a fold, over the grid."""
    n = h.shape[0]
    d, nb = tree2.query(tree2.data, k=min(5, n), distance_upper_bound=0.5 * rho)
    nb = np.where(np.isfinite(d), nb, np.arange(n)[:, None])
    return bool((np.abs(h[nb] - h[:, None]) > 1.5 * rho).any())


def two_layers(points: np.ndarray, normal: np.ndarray, rho: float) -> bool:
    """Some of ``points`` lie over others (:func:`~lodbuilder.fill.local.stacked`: within rho/2
    across, 1.5 rho apart) over the plane of their mean normal (oriented like ``normal``): two
    layers, a plate over a sheet, whose least-squares plane tilts to run through both."""
    from scipy.spatial import cKDTree

    nrm = normals_at(points, points)
    mean = (nrm * np.where(nrm @ normal < 0, -1.0, 1.0)[:, None]).sum(axis=0)
    frame = Frame.of(points.mean(axis=0), mean)
    return stacked(cKDTree(frame.uv(points)), frame.height(points), rho)


def groups(seeds: np.ndarray, rho: float) -> list[np.ndarray]:
    """Seed index arrays of the groups linked within 2 rho."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    m = seeds.shape[0]
    if m == 0:
        return []
    pairs = cKDTree(seeds).query_pairs(2.0 * rho, output_type="ndarray")
    g = coo_matrix((np.ones(pairs.shape[0]), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
    n_comp, labels = connected_components(g, directed=False)
    order = np.argsort(labels, kind="stable")
    splits = np.cumsum(np.bincount(labels, minlength=n_comp))[:-1]
    return np.split(order, splits)


def inside(regions: list, points: np.ndarray, rho: float, step: float) -> np.ndarray:
    """Mask of ``points`` inside a region (:class:`~lodbuilder.fill.gaps.Region`) found
    already: over one of its nodes (within a grid ``step``, in its plane) and within 2 rho of
    its surface. Another group of seeds of the same hole (seeds on a sheet above part of it,
    say) then finds nothing new."""
    from scipy.spatial import cKDTree

    hit = np.zeros(points.shape[0], dtype=bool)
    for reg in regions:
        if not reg.candidates.shape[0]:
            continue
        # (a point over a node and within 2 rho of the surface is within 4 rho of a candidate,
        # unless the surface rose by 1.7 rho over a grid step: most regions are far away)
        lo = reg.candidates.min(axis=0) - 4.0 * rho
        hi = reg.candidates.max(axis=0) + 4.0 * rho
        box = np.flatnonzero(((points >= lo) & (points <= hi)).all(axis=1) & ~hit)
        if not box.size:
            continue
        if reg.implicit:  # within 2 rho of its surface, next to a candidate
            d, _ = cKDTree(reg.candidates).query(points[box], k=1, distance_upper_bound=2.0 * rho)
            hit[box] = np.isfinite(d)
            continue
        uv = reg.frame.uv(points[box])
        d, _ = cKDTree(reg.uv).query(uv, k=1, distance_upper_bound=step * 1.01)
        over = np.isfinite(d)
        if over.any():
            h = reg.frame.height(points[box[over]])
            hit[box[over]] = np.abs(h - reg.surface(uv[over])) <= 2.0 * rho
    return hit
