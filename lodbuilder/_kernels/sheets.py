"""Local sheet separation: how far, across the gap, the nearest other piece of surface is.

Works on the occupied cells of a grid (points sorted by cell, grid units), every other cell in a
checkerboard (the spread below covers the rest). A cell's normal is the smallest principal axis of
the points within ``normal_radius`` of its most central point (about two point spacings, so they
stay on its own sheet when another one is 3 spacings away), trusted only where those points are flat
(the smallest principal spread under PLANAR x the middle one: not too noisy, not a corner). From the cell's centroid a ray goes both ways
along the normal; the first occupied cell it meets whose centroid lies in the normal's cone
(offset along the normal >= ``cone`` x the distance) and at least ``gap_min`` away along the normal
belongs to another sheet, and that offset is the cell's separation; the normal is turned toward the nearer one. Cells of the same sheet (neighbours, noise, a curved sheet) are either too close along
the normal or outside the cone; holes in the sampling are sideways and never in the cone. The
result is spread to the 26 neighbour cells on the same side of the gap (min), so that every point
near a thin part gets it.

:func:`normal_agreement` tells flat sheets from a surface curving round within its separation (a
closed part only a few spacings across): how well a thin cell's normal agrees with those of the thin
cells near it.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import INLINE, JIT
from .grid import cell_gap2, hash_find, index_hash, morton, unmorton
from .march import corner_voxels

PLANAR = 0.25  # a normal counts only where the smallest spread is under this x the middle one
CUT_SHARE = 0.5  # two points lie on different sheets when one is this share of the separation ...
CUT_CONE = 0.7  # ... or more along the other's normal, and that offset is this share of their distance,
CUT_PARALLEL = 0.7  # ... and, nearer than the separation, their normals (where both have one) agree within 46 deg
AGREE_MIN = 3  # normal_agreement: a cell is judged by at least this many thin cells near it


@nb.njit(**JIT)
def _smallest_axis(a, b, c, d, e, f):  # pragma: no cover - compiled
    """Unit eigenvector of the smallest eigenvalue of [[a, d, e], [d, b, f], [e, f, c]]."""
    p1 = d * d + e * e + f * f
    q = (a + b + c) / 3.0
    p2 = (a - q) ** 2 + (b - q) ** 2 + (c - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    if p <= 1e-300:
        return 0.0, 0.0, 1.0, False
    ba = (a - q) / p
    bb = (b - q) / p
    bc = (c - q) / p
    bd = d / p
    be = e / p
    bf = f / p
    r = 0.5 * (ba * (bb * bc - bf * bf) - bd * (bd * bc - bf * be) + be * (bd * bf - bb * be))
    r = min(max(r, -1.0), 1.0)
    phi = np.arccos(r) / 3.0
    lam = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)  # the smallest eigenvalue
    mid = 3.0 * q - lam - (q + 2.0 * p * np.cos(phi))
    if lam > PLANAR * mid:
        return 0.0, 0.0, 1.0, False  # not flat enough for a trustworthy normal (noise, a corner)
    # rows of C - lam I; the eigenvector is the longest cross product of two rows
    r0x, r0y, r0z = a - lam, d, e
    r1x, r1y, r1z = d, b - lam, f
    r2x, r2y, r2z = e, f, c - lam
    best = -1.0
    nx = ny = nz = 0.0
    for k in range(3):
        if k == 0:
            ux, uy, uz, vx, vy, vz = r0x, r0y, r0z, r1x, r1y, r1z
        elif k == 1:
            ux, uy, uz, vx, vy, vz = r0x, r0y, r0z, r2x, r2y, r2z
        else:
            ux, uy, uz, vx, vy, vz = r1x, r1y, r1z, r2x, r2y, r2z
        cx = uy * vz - uz * vy
        cy = uz * vx - ux * vz
        cz = ux * vy - uy * vx
        l2 = cx * cx + cy * cy + cz * cz
        if l2 > best:
            best = l2
            nx, ny, nz = cx, cy, cz
    if best <= 0.0:
        return 0.0, 0.0, 1.0, False
    ln = np.sqrt(best)
    return nx / ln, ny / ln, nz / ln, True


@nb.njit(**JIT)
def _cell_normal(u, ostart, mom, cnt, ckey, hidx, c, radius2):  # pragma: no cover - compiled
    """The unit normal of cell c: the smallest principal axis of the points within
    sqrt(radius2) of the cell's point nearest its centroid (searched in the 27 cells around)."""
    p0, p1 = ostart[c], ostart[c + 1]
    fx = int(np.floor(u[p0, 0]))
    fy = int(np.floor(u[p0, 1]))
    fz = int(np.floor(u[p0, 2]))
    gx = mom[c, 0] / cnt[c]
    gy = mom[c, 1] / cnt[c]
    gz = mom[c, 2] / cnt[c]
    rep = p0
    best = np.inf
    for i in range(p0, p1):
        d2 = (u[i, 0] - gx) ** 2 + (u[i, 1] - gy) ** 2 + (u[i, 2] - gz) ** 2
        if d2 < best:
            best = d2
            rep = i
    rx, ry, rz = u[rep, 0], u[rep, 1], u[rep, 2]
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = 0.0
    nk = 0
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            for dz in range(-1, 2):
                # a neighbour cell whose box lies farther than the radius holds no point within it
                if cell_gap2(rx, ry, rz, fx, fy, fz, dx, dy, dz) > radius2:
                    continue
                x, y, z = fx + dx, fy + dy, fz + dz
                if x < 0 or y < 0 or z < 0:
                    continue
                j = hash_find(hidx, ckey, morton(x, y, z))
                if j < 0:
                    continue
                for i in range(ostart[j], ostart[j + 1]):
                    ex, ey, ez = u[i, 0] - rx, u[i, 1] - ry, u[i, 2] - rz
                    if ex * ex + ey * ey + ez * ez > radius2:
                        continue
                    nk += 1
                    s0 += ex
                    s1 += ey
                    s2 += ez
                    s3 += ex * ex
                    s4 += ey * ey
                    s5 += ez * ez
                    s6 += ex * ey
                    s7 += ex * ez
                    s8 += ey * ez
    if nk < 5:
        return 0.0, 0.0, 1.0, False
    nn = float(nk)
    mx, my, mz = s0 / nn, s1 / nn, s2 / nn
    return _smallest_axis(
        s3 / nn - mx * mx, s4 / nn - my * my, s5 / nn - mz * mz,
        s6 / nn - mx * my, s7 / nn - mx * mz, s8 / nn - my * mz,
    )


@nb.njit(**JIT)
def cell_separation(u, ostart, reach, gap_min, cone, normal_radius):  # pragma: no cover - compiled
    """Per occupied cell: the separation toward the nearer other sheet (inf: none within
    ``reach``), the one on the opposite side (inf: none), and the unit normal oriented toward the
    nearer other sheet (zero where there is none), all in grid units."""
    ncell = ostart.shape[0] - 1
    ckey = np.empty(ncell, np.int64)
    cnt = np.empty(ncell, np.float64)
    mom = np.zeros((ncell, 9), np.float64)  # sum x, y, z, xx, yy, zz, xy, xz, yz
    for c in range(ncell):
        p0, p1 = ostart[c], ostart[c + 1]
        ckey[c] = morton(int(np.floor(u[p0, 0])), int(np.floor(u[p0, 1])), int(np.floor(u[p0, 2])))
        cnt[c] = p1 - p0
        for i in range(p0, p1):
            x, y, z = u[i, 0], u[i, 1], u[i, 2]
            mom[c, 0] += x
            mom[c, 1] += y
            mom[c, 2] += z
            mom[c, 3] += x * x
            mom[c, 4] += y * y
            mom[c, 5] += z * z
            mom[c, 6] += x * y
            mom[c, 7] += x * z
            mom[c, 8] += y * z
    hidx = index_hash(ckey)
    sep_in = np.full(ncell, np.inf)
    sep_out = np.full(ncell, np.inf)
    nrm = np.zeros((ncell, 3), np.float64)
    radius2 = normal_radius * normal_radius
    for c in range(ncell):
        p0, p1 = ostart[c], ostart[c + 1]
        fx = int(np.floor(u[p0, 0]))
        fy = int(np.floor(u[p0, 1]))
        fz = int(np.floor(u[p0, 2]))
        if (fx + fy + fz) & 1:
            continue  # every other cell (a checkerboard): the spread below covers the others
        nx, ny, nz, ok = _cell_normal(u, ostart, mom, cnt, ckey, hidx, c, radius2)
        if not ok:
            continue
        cx = mom[c, 0] / cnt[c]
        cy = mom[c, 1] / cnt[c]
        cz = mom[c, 2] / cnt[c]
        found_pos = np.inf
        found_neg = np.inf
        for side in range(2):
            sgn = 1.0 if side == 0 else -1.0
            t = 0.5
            last = np.int64(-1)
            while t <= reach:
                x = int(np.floor(cx + sgn * t * nx))
                y = int(np.floor(cy + sgn * t * ny))
                z = int(np.floor(cz + sgn * t * nz))
                t += 0.5
                if x < 0 or y < 0 or z < 0:
                    continue
                k = morton(x, y, z)
                if k == last or k == ckey[c]:
                    continue
                last = k
                j = hash_find(hidx, ckey, k)
                if j < 0:
                    continue
                ox = mom[j, 0] / cnt[j] - cx
                oy = mom[j, 1] / cnt[j] - cy
                oz = mom[j, 2] / cnt[j] - cz
                along = sgn * (ox * nx + oy * ny + oz * nz)
                dist = np.sqrt(ox * ox + oy * oy + oz * oz)
                if along < gap_min or along < cone * dist:
                    continue
                if side == 0:
                    found_pos = along
                else:
                    found_neg = along
                break
        if found_pos == np.inf and found_neg == np.inf:
            continue
        if found_neg < found_pos:
            nx, ny, nz = -nx, -ny, -nz
        sep_in[c] = min(found_pos, found_neg)
        sep_out[c] = max(found_pos, found_neg)
        nrm[c, 0] = nx
        nrm[c, 1] = ny
        nrm[c, 2] = nz
    # spread to the neighbour cells that found nothing themselves, with their own normal turned
    # to agree with the finder's
    out_in = sep_in.copy()
    out_out = sep_out.copy()
    out_n = nrm.copy()
    for c in range(ncell):
        if sep_in[c] == np.inf:
            continue
        p0 = ostart[c]
        fx = int(np.floor(u[p0, 0]))
        fy = int(np.floor(u[p0, 1]))
        fz = int(np.floor(u[p0, 2]))
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    x, y, z = fx + dx, fy + dy, fz + dz
                    if x < 0 or y < 0 or z < 0:
                        continue
                    j = hash_find(hidx, ckey, morton(x, y, z))
                    if j < 0 or sep_in[j] < np.inf or sep_in[c] >= out_in[j]:
                        continue
                    # not to a cell of the other sheet (it may be this close when the gap is)
                    toward = (
                        (mom[j, 0] / cnt[j] - mom[c, 0] / cnt[c]) * nrm[c, 0]
                        + (mom[j, 1] / cnt[j] - mom[c, 1] / cnt[c]) * nrm[c, 1]
                        + (mom[j, 2] / cnt[j] - mom[c, 2] / cnt[c]) * nrm[c, 2]
                    )
                    if toward > 0.5 * sep_in[c]:
                        continue
                    out_in[j] = sep_in[c]
                    out_out[j] = sep_out[c]
                    for a in range(3):
                        out_n[j, a] = nrm[c, a]
    return out_in, out_out, out_n


@nb.njit(**JIT)
def normal_agreement(u, ostart, sep, nrm, ball, stride):  # pragma: no cover - compiled
    """Per occupied cell (grid units, points sorted by cell), for every ``stride``-th cell with a
    separation (``sep`` < inf, counted in cell order): the mean |cos| of the angle between its
    normal and the normal of every other cell with a separation whose centroid lies within
    ``ball`` x its separation of its centroid; nan for the other cells and where fewer than
    AGREE_MIN such cells are near. On two parallel sheets the normals within less than the
    separation agree (mean |cos| ~ 1); where the other side found is the same surface curving
    around (a tube or a blob a few spacings across) they turn by tens of degrees within it."""
    ncell = ostart.shape[0] - 1
    ckey = np.empty(ncell, np.int64)
    cen = np.empty((ncell, 3), np.float64)
    for c in range(ncell):
        p0, p1 = ostart[c], ostart[c + 1]
        ckey[c] = morton(int(np.floor(u[p0, 0])), int(np.floor(u[p0, 1])), int(np.floor(u[p0, 2])))
        for a in range(3):
            t = 0.0
            for i in range(p0, p1):
                t += u[i, a]
            cen[c, a] = t / (p1 - p0)
    hidx = index_hash(ckey)
    out = np.full(ncell, np.nan)
    seen = 0
    for c in range(ncell):
        if sep[c] == np.inf:
            continue
        seen += 1
        if (seen - 1) % stride:
            continue
        rad = ball * sep[c]
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        for a in range(3):
            lo[a] = max(int(np.floor(cen[c, a] - rad)), 0)
            hi[a] = int(np.floor(cen[c, a] + rad))
        total = 0.0
        count = 0
        for x in range(lo[0], hi[0] + 1):
            for y in range(lo[1], hi[1] + 1):
                for z in range(lo[2], hi[2] + 1):
                    j = hash_find(hidx, ckey, morton(x, y, z))
                    if j < 0 or j == c or sep[j] == np.inf:
                        continue
                    d2 = (cen[j, 0] - cen[c, 0]) ** 2 + (cen[j, 1] - cen[c, 1]) ** 2 + (cen[j, 2] - cen[c, 2]) ** 2
                    if d2 > rad * rad:
                        continue
                    total += abs(nrm[c, 0] * nrm[j, 0] + nrm[c, 1] * nrm[j, 1] + nrm[c, 2] * nrm[j, 2])
                    count += 1
        if count >= AGREE_MIN:
            out[c] = total / count
    return out


@nb.njit(**INLINE)
def apart(u, nin, psep, f, g):  # pragma: no cover - compiled
    """Whether points f and g lie on different sheets: along the normal of either one (where it
    has one: a thin part), the other lies at least CUT_SHARE x that point's separation away, and
    that offset is at least CUT_CONE x their distance (a sheet's own points lie beside it)."""
    if f == g:
        return False
    dx = u[g, 0] - u[f, 0]
    dy = u[g, 1] - u[f, 1]
    dz = u[g, 2] - u[f, 2]
    d = np.sqrt(dx * dx + dy * dy + dz * dz)
    return _across(dx, dy, dz, d, nin, psep, f, g) or _across(dx, dy, dz, d, nin, psep, g, f)


@nb.njit(**INLINE)
def _across(dx, dy, dz, d, nin, psep, e, o):  # pragma: no cover - compiled
    """Whether o lies across the gap from e along e's normal."""
    nx, ny, nz = nin[e, 0], nin[e, 1], nin[e, 2]
    if nx == 0.0 and ny == 0.0 and nz == 0.0:
        return False
    a = abs(dx * nx + dy * ny + dz * nz)
    if a < CUT_SHARE * psep[e] or a < CUT_CONE * d:
        return False
    mx, my, mz = nin[o, 0], nin[o, 1], nin[o, 2]
    if d >= psep[e] or (mx == 0.0 and my == 0.0 and mz == 0.0):
        return True
    return abs(nx * mx + ny * my + nz * mz) >= CUT_PARALLEL


@nb.njit(**JIT)
def sheet_cut(keys, nbr, cs, foot, vcost, u, nin, psep):  # pragma: no cover - compiled
    """The voxel costs of a band cut between sheets (inf: not marchable). A marchable voxel whose
    foot (nearest point) lies on another sheet (:func:`apart`) than the foot of a marchable
    6-neighbour is dropped when it is the farther of the two from its foot (the larger index on a
    tie), so no two neighbours of the result stand on different sheets; and a voxel is dropped when
    a point of one of the 8 cells it is a corner of lies on another sheet than its foot, so no point
    reads a distance from another sheet. Both tests look at the band as given (``vcost``), so the
    result does not depend on the order of the voxels."""
    nv = keys.shape[0]
    out = vcost.copy()
    # a voxel is tested only where a thin point is near: its foot, a neighbour's foot or a point of
    # one of its cells (two points without a normal are never apart), so the rule costs little
    # where few points are thin
    thin = np.zeros(u.shape[0], np.bool_)
    for p in range(u.shape[0]):
        thin[p] = nin[p, 0] != 0.0 or nin[p, 1] != 0.0 or nin[p, 2] != 0.0
    thin_cell = np.zeros(nv, np.bool_)
    for v in range(nv):
        for p in range(cs[v], cs[v + 1]):
            if thin[p]:
                thin_cell[v] = True
                break
    for v in range(nv):
        if vcost[v] == np.inf:
            continue
        f = foot[v]
        near = thin[f]
        if not near:
            for j in range(6):
                w = nbr[v, j]
                if w >= 0 and thin[foot[w]]:
                    near = True
                    break
        if not near:
            corners = corner_voxels(nbr, v)
            for k in range(8):
                c = corners[k]
                if c >= 0 and thin_cell[c]:
                    near = True
                    break
        if not near:
            continue
        x, y, z = unmorton(keys[v])
        dv = (x - u[f, 0]) ** 2 + (y - u[f, 1]) ** 2 + (z - u[f, 2]) ** 2
        drop = False
        for j in range(6):
            w = nbr[v, j]
            if w < 0 or vcost[w] == np.inf:
                continue
            g = foot[w]
            if not apart(u, nin, psep, f, g):
                continue
            wx, wy, wz = unmorton(keys[w])
            dw = (wx - u[g, 0]) ** 2 + (wy - u[g, 1]) ** 2 + (wz - u[g, 2]) ** 2
            if dw < dv or (dw == dv and w < v):
                drop = True
                break
        if not drop:
            corners = corner_voxels(nbr, v)
            for k in range(8):
                c = corners[k]
                if c < 0:
                    continue
                for p in range(cs[c], cs[c + 1]):
                    if apart(u, nin, psep, f, p):
                        drop = True
                        break
                if drop:
                    break
        if drop:
            out[v] = np.inf
    return out
