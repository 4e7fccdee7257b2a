"""Poses: 4x4 matrices that place a scan in a common frame (world = pose[:3, :3] @ p + pose[:3, 3]),
the Stanford ``bmesh`` (translation + quaternion) convention, and whether a pose is rigid."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)


def quaternion_matrix(qx: float, qy: float, qz: float, qw: float, where: str = "") -> np.ndarray:
    """Rotation matrix of the quaternion (x, y, z, w), normalised first (scipy's Rotation).
    ``where`` prefixes errors (the manifest line)."""
    from scipy.spatial.transform import Rotation

    q = np.array([qx, qy, qz, qw], dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-12:
        text = " ".join(f"{v:g}" for v in q)
        raise InputError(f"{where + ': ' if where else ''}quaternion ({text}) has zero or non-finite "
                         "length; give a unit quaternion qx qy qz qw")
    return Rotation.from_quat(q / n).as_matrix()


def bmesh_pose(t: Any, q: Any, where: str = "") -> np.ndarray:
    """4x4 (column-vector) pose for the bun.conf convention world = p @ R(q) + t."""
    m = np.eye(4)
    qx, qy, qz, qw = (float(v) for v in q)
    m[:3, :3] = quaternion_matrix(qx, qy, qz, qw, where=where).T
    m[:3, 3] = np.asarray(t, dtype=np.float64)
    return m


#: a pose is rigid when its 3x3 part is orthonormal within this tolerance (rounding in manifests)
RIGID_TOL = 1e-6


def pose_kind(pose: np.ndarray | None) -> str:
    """``"rigid"`` (rotation + translation, or no pose) or ``"affine"`` (scales or shears)."""
    if pose is None:
        return "rigid"
    r = np.asarray(pose, dtype=np.float64)[:3, :3]
    ok = np.allclose(r.T @ r, np.eye(3), atol=RIGID_TOL) and np.linalg.det(r) > 0
    return "rigid" if ok else "affine"


def check_pose(m: np.ndarray, where: str) -> np.ndarray:
    """Refuse a singular pose (it collapses the scan); warn that a non-rigid one is applied as is."""
    r = m[:3, :3]
    sv = np.linalg.svd(r, compute_uv=False)
    if not np.isfinite(sv).all() or sv[-1] <= 1e-9 * max(float(sv[0]), 1e-300):
        raise InputError(f"{where}: the 4x4 pose is singular (its 3x3 part has rank < 3) and would collapse "
                         "the scan; give an invertible pose (a rotation and a translation)")
    if pose_kind(m) != "rigid":
        reflect = " and mirrors" if np.linalg.det(r) < 0 else ""
        log.warning("%s: the pose is not rigid: it scales or shears the scan (scale factors %s)%s; "
                    "it is applied as given", where, " ".join(f"{v:.6g}" for v in sv), reflect)
    return m


def apply_pose(points: np.ndarray, pose: np.ndarray | None) -> np.ndarray:
    """world = pose[:3, :3] @ p + pose[:3, 3] for each row p (float64), element by element in one
    fixed order, ``((r0 * x + r1 * y) + r2 * z) + t`` with every product and sum rounded once: the
    same rows give the same bits on any machine and in any chunking. A BLAS product's rounding
    depends on its kernel (fused multiply-adds, blocking: the CPU and the library pick it), so a
    tiled build's worker that reads a block of the input again (to check it, then to write it)
    could get other bits than the worker that read it first."""
    if pose is None:
        return points
    m = np.asarray(pose, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    out = np.empty(p.shape, dtype=np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    for i in range(3):
        col = x * m[i, 0]
        col += y * m[i, 1]
        col += z * m[i, 2]
        col += m[i, 3]
        out[:, i] = col
    return out
