"""What "read back equal to the source" means for each output format (the documented quantisation).

* Coordinates: PLY, NPY exact; CSV exact at the source precision (float32 sources print as
  float32, so ``back.astype(float32) == source``); LAS/LAZ exact for a LAS source (its scale and
  offset are kept), else within scale / 2 of the scale the writer chose.
* Attributes: NPY and PLY exact values (PLY colours become uchar: 16-bit colours that hold 8-bit
  values keep them); CSV values cast back to the source dtype exactly; LAS/LAZ exact values except
  uint8 colours, which are stored x 257 (``back // 257 == source``, ``back % 257 == 0``).
* CRS: identical WKT text.
"""

from __future__ import annotations

import numpy as np

COLOURS = ("red", "green", "blue", "alpha", "nir")


def coords_f32(scan) -> bool:
    """True when the scan's coordinates are all exactly float32."""
    p = scan.points
    return bool(np.array_equal(p.astype(np.float32).astype(np.float64), p))


def _flat(name, arr):
    a = np.asarray(arr)
    if a.ndim == 1:
        return [(name, a)]
    flat = a.reshape(a.shape[0], -1)
    return [(f"{name}_{j}", flat[:, j]) for j in range(flat.shape[1])]


def assert_same(src, back, fmt: str, *, src_points=None, src_attributes=None, src_crs=None) -> None:
    """Assert that ``back`` (read from a file of format ``fmt``) holds ``src``'s data."""
    pts = src.points if src_points is None else src_points
    attrs = src.attributes if src_attributes is None else src_attributes
    crs = src.metadata.get("crs_wkt") if src_crs is None else src_crs
    assert back.points.shape == pts.shape
    if fmt in ("las", "laz"):
        scale = np.asarray(back.metadata["las_scales"])
        err = np.abs(back.points - pts).max(axis=0) if len(pts) else np.zeros(3)
        assert np.all(err <= scale / 2 * (1 + 1e-6) + 1e-9 * np.abs(pts).max()), (err, scale)
        if src.reader == "las":
            np.testing.assert_array_equal(back.points, pts)
    elif fmt == "csv" and coords_f32(src):
        np.testing.assert_array_equal(back.points.astype(np.float32), pts.astype(np.float32))
    else:
        np.testing.assert_array_equal(back.points, pts)
    for name, arr in attrs.items():
        cols = _flat(name, arr) if fmt in ("ply", "csv") or np.asarray(arr).ndim > 2 else [(name, np.asarray(arr))]
        for key, v in cols:
            assert key in back.attributes, (key, sorted(back.attributes))
            got = np.asarray(back.attributes[key])
            if fmt in ("las", "laz") and key in COLOURS and v.dtype == np.uint8:
                assert got.dtype == np.uint16, key
                assert np.all(got % 257 == 0), key
                got = got // 257
            if v.dtype == np.bool_:
                v = v.astype(np.uint8)
            if fmt == "npy":
                assert got.dtype == v.dtype, (key, got.dtype, v.dtype)
            if v.dtype.kind == "f":
                np.testing.assert_array_equal(got.astype(v.dtype), v, err_msg=f"{fmt}: {key}")
            else:
                assert got.dtype.kind != "f" or np.all(got == np.round(got)), key
                np.testing.assert_array_equal(got.astype(np.float64), v.astype(np.float64), err_msg=f"{fmt}: {key}")
    assert back.metadata.get("crs_wkt") == crs, (fmt, back.metadata.get("crs_wkt"), crs)
