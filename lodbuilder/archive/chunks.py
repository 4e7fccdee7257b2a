"""A scan's rows as finished HDF5 chunks, made apart from the file they go to.

:class:`~lodbuilder.archive.scanwriter.ScanWriter` writes a scan's per-point datasets one row
group at a time (the chunks of rows ``[iR, (i+1)R)`` of every dataset, next to each other). The
same chunks can be made anywhere, in parallel, by any process that knows the datasets' creation
properties (a *spec*: :func:`spec_of`, from the first row group, as the scan writer decides them):
:func:`filter_rows` writes rows into an HDF5 file in memory created with those properties
(:func:`create_datasets`: chunk shape, shuffle, gzip level, Fletcher-32) and reads back each
chunk's filtered bytes, which :class:`~lodbuilder.archive.chunkwriter.ChunkWriter` places into
the archive file as they are (no filter work). The bytes are the ones HDF5 writes itself, edge
chunk included (its rows beyond the scan's end hold the fill value in both files), so the
archive is the same whichever process filtered which rows.

Every row is checked on the way as :meth:`ScanWriter.write` checks it (:func:`check_rows`,
:func:`encode_exactly`), with the same messages.
"""

from __future__ import annotations

import itertools
import os
from typing import Any

import numpy as np

from ..errors import InputError
from . import layout as L

#: one dataset of a spec: name (relative to the scan group), dtype (``numpy.dtype.str``), the
#: shape of one row, whether shuffle + gzip are on
Spec = list[tuple[str, str, tuple[int, ...], bool]]

_names = itertools.count()


def spec_of(block: dict[str, np.ndarray]) -> Spec:
    """The datasets' creation properties from the first row group (``block``: dataset name ->
    rows as stored, points encoded), in the order the datasets are created and written."""
    return [(key, a.dtype.str, tuple(int(x) for x in a.shape[1:]), bool(L.compression_pays(a)))
            for key, a in block.items()]


def spec_bytes(spec: Spec, rows: int) -> tuple[int, int]:
    """Bytes of one row of every dataset together, and of the largest chunk (``rows`` rows)."""
    widths = [np.dtype(dt).itemsize * int(np.prod(tail)) for _, dt, tail, _ in spec]
    return sum(widths), rows * max(widths)


def create_datasets(group: Any, n: int, rows: int, spec: Spec) -> dict[str, Any]:
    """Create the datasets of ``spec`` (``n`` rows in chunks of ``rows``) in ``group``."""
    out = {}
    for key, dt, tail, compress in spec:
        kw: dict[str, Any] = {"chunks": (rows, *tail), "fletcher32": True}
        if compress:
            kw.update(compression="gzip", compression_opts=L.GZIP_LEVEL, shuffle=True)
        out[key] = group.create_dataset(key, shape=(n, *tail), dtype=np.dtype(dt), **kw)
    return out


def filter_rows(spec: Spec, rows: int, arrays: dict[str, np.ndarray]) -> tuple[list[list[int]], bytes]:
    """The chunks of ``arrays`` (dataset name -> rows as stored, starting at a row group's first
    row) filtered by HDF5 as ``spec`` says: a table of ``[size, filter mask]`` per chunk, row group
    by row group and in ``spec``'s order within one, and their bytes one after another."""
    import h5py

    m = int(next(iter(arrays.values())).shape[0])
    groups = -(-m // rows)
    f = h5py.File(f"lodbuilder-chunks-{os.getpid()}-{next(_names)}", "w", driver="core", backing_store=False)
    try:
        ds = create_datasets(f, groups * rows, rows, spec)
        for key, d in ds.items():
            if m:
                d.write_direct(np.ascontiguousarray(arrays[key]), dest_sel=np.s_[:m])
        table, parts = [], []
        for i in range(groups):
            for key, _, tail, _ in spec:
                mask, data = ds[key].id.read_direct_chunk((i * rows,) + (0,) * len(tail))
                table.append([len(data), int(mask)])
                parts.append(data)
        return table, b"".join(parts)
    finally:
        f.close()


def encode_exactly(pts: np.ndarray, enc: str, offset: Any, scale: Any, where: str, lo: int) -> np.ndarray:
    """Points as stored in encoding ``enc``; refuses (never rounds) rows it would change."""
    stored = L.encode_as(pts, enc, offset, scale)
    if stored is None:
        raise InputError(
            f"points of {where} at stored rows {lo}..{lo + pts.shape[0] - 1} cannot be stored "
            f"exactly as {enc} (chosen from the first row group); pass encoding='float64' to "
            "ScanWriter"
        )
    return stored


def check_points(pts: np.ndarray, where: str, lo: int) -> None:
    """Every coordinate finite."""
    if not np.isfinite(pts).all():
        bad = lo + int(np.flatnonzero(~np.isfinite(pts).all(axis=1))[0])
        raise InputError(f"points of {where} hold NaN or inf at stored row {bad}")


def check_rows(src: np.ndarray, rad: np.ndarray, par: np.ndarray, n: int, lo: int, last_radius: float,
               where: str) -> None:
    """Rows from stored row ``lo`` on: source indices in range and distinct among themselves,
    radii never NaN or negative and non-increasing (from ``last_radius``, the radius of row
    ``lo - 1``), parents earlier rows or -1. (Distinct from earlier rows: the caller's check.)"""
    m = src.size
    if m and (src.min() < 0 or src.max() >= n):
        raise InputError(f"source_index of {where} must be in [0, {n}); got values outside")
    if np.isnan(rad).any() or (rad < 0).any():
        raise InputError(f"radius of {where} holds NaN or negative values")
    prev = np.concatenate([[last_radius], rad[:-1]])
    inc = np.flatnonzero(rad > prev)
    if inc.size:
        raise InputError(
            f"radius of {where} increases at stored row {lo + int(inc[0])}; rows must be in "
            "farthest-point order (non-increasing radii)"
        )
    pos = lo + np.arange(m, dtype=np.int64)
    badp = np.flatnonzero((par >= pos) | (par < -1))
    if badp.size:
        i = int(badp[0])
        raise InputError(
            f"parent of {where} at stored row {lo + i} is {int(par[i])}; parents must be "
            "earlier rows or -1"
        )
    if m > 1:
        ordered = np.sort(src)
        if (ordered[1:] == ordered[:-1]).any():
            raise InputError(f"source_index of {where} repeats an input index; each point goes once")
