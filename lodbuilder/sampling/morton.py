"""Morton (Z-order) keys of voxel coordinates with NumPy, for the band's set-up (the kernels have
their own, compiled)."""

from __future__ import annotations

import numpy as np

_M = [np.uint64(m) for m in (0x1FFFFF, 0x1F00000000FFFF, 0x1F0000FF0000FF, 0x100F00F00F00F00F,
                               0x10C30C30C30C30C3, 0x1249249249249249)]


def _spread(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.uint64) & _M[0]
    for shift, mask in zip((32, 16, 8, 4, 2), _M[1:], strict=True):
        x = (x | (x << np.uint64(shift))) & mask
    return x


def _compact(x: np.ndarray) -> np.ndarray:
    x = x & _M[5]
    for shift, mask in zip((2, 4, 8, 16, 32), _M[4::-1], strict=True):
        x = (x ^ (x >> np.uint64(shift))) & mask
    return x.astype(np.int64)


def morton_np(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Morton keys of non-negative integer coordinates (NumPy; the kernels have their own)."""
    return (_spread(x) | (_spread(y) << np.uint64(1)) | (_spread(z) << np.uint64(2))).astype(np.int64)


def unmorton_np(keys: np.ndarray) -> np.ndarray:
    """(K, 3) coordinates of Morton keys."""
    k = keys.astype(np.uint64)
    return np.stack([_compact(k >> np.uint64(a)) for a in range(3)], axis=1)
