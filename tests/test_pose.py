"""io.pose.apply_pose: the same bits on any machine (a tiled build's worker reads a block of an
input again and checks it against the first read, which may have run on another worker)."""

from __future__ import annotations

import numpy as np
import pytest

from lodbuilder.io.pose import apply_pose, quaternion_matrix


def _naive(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """One Python float operation at a time (no fused multiply-add): ((r0 x + r1 y) + r2 z) + t."""
    out = np.empty(points.shape)
    for j, p in enumerate(points.tolist()):
        for i in range(3):
            r = pose[i].tolist()
            out[j, i] = ((r[0] * p[0] + r[1] * p[1]) + r[2] * p[2]) + r[3]
    return out


def _points(n: int = 2_000) -> np.ndarray:
    rng = np.random.default_rng(7)
    return rng.normal(size=(n, 3)) * [300.0, 200.0, 20.0] + [5e5, 4e6, 100.0]


def test_the_identity_pose_keeps_every_bit():
    p = _points()
    np.testing.assert_array_equal(apply_pose(p, np.eye(4)).view(np.int64), p.view(np.int64))
    assert apply_pose(p, None) is p


@pytest.mark.parametrize("q", [(0.1, -0.3, 0.2, 0.9), (0.0, 0.0, 0.38, 0.92), (0.5, 0.5, -0.5, 0.5)])
def test_a_rotation_gives_the_bits_of_one_rounding_per_operation(q):
    """A rotation and translation: bit for bit the element-wise reference (a BLAS product with
    fused multiply-adds rounds otherwise: about half of these rows differed in the last bit)."""
    pose = np.eye(4)
    pose[:3, :3] = quaternion_matrix(*q)
    pose[:3, 3] = [12.5, -7.25, 3.0]
    p = _points()
    got = apply_pose(p, pose)
    np.testing.assert_array_equal(got.view(np.int64), _naive(p, pose).view(np.int64))
    # chunks, strided views and float32 input give the same bits as the whole
    np.testing.assert_array_equal(np.concatenate([apply_pose(p[:777], pose), apply_pose(p[777:], pose)]), got)
    np.testing.assert_array_equal(apply_pose(p[::3], pose), got[::3])
    p32 = p.astype(np.float32)
    np.testing.assert_array_equal(apply_pose(p32, pose), _naive(p32.astype(np.float64), pose))
