"""Assembling a scan's part file from chunks filtered elsewhere (:mod:`.chunks`).

:class:`ChunkWriter` is a :class:`~lodbuilder.archive.scanwriter.ScanWriter` whose rows arrive as
finished HDF5 chunks, row groups in stored order: it places their bytes with
``write_direct_chunk`` (no filter runs) in the order the scan writer writes its own chunks, keeps
what :meth:`ScanWriter.finish` needs (bounds, the radius index, the rows written) from what the
makers of the chunks report, and finishes like a scan writer. A tiled build's band tasks filter the
rows (:mod:`lodbuilder.build.tiled.bands`), the parent assembles: the part file is the one a scan
writer fed row by row writes.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from ..errors import InputError
from . import files as F
from . import layout as L
from .chunks import Spec, spec_bytes
from .scanwriter import ScanWriter


class ChunkWriter(ScanWriter):
    """Write one scan from filtered chunks: ``spec`` the datasets' creation properties (from the
    first row group: :func:`lodbuilder.archive.chunks.spec_of`), the other arguments as for
    :class:`ScanWriter` (``encoding`` required: the chunks are already encoded). Rows are added a
    band of whole row groups at a time (:meth:`write_chunks`), in stored order; then
    :meth:`finish`."""

    def __init__(self, path: str | os.PathLike[str], name: str, n_points: int, spec: Spec, *,
                 metadata: Any = None, encoding: str) -> None:
        super().__init__(path, name, n_points, metadata=metadata, encoding=encoding)
        self._spec = [(str(k), str(dt), tuple(int(x) for x in tail), bool(c)) for k, dt, tail, c in spec]
        self._row_width = spec_bytes(self._spec, self.rows)[0]
        try:
            self._create(self._spec)
        except BaseException:
            self.abort()
            raise

    def write_chunks(self, lo: int, hi: int, table: list[list[int]], blob: bytes | memoryview, *,
                     bounds: tuple[Any, Any], radius_index: np.ndarray, last_tail: int, last_radius: float) -> None:
        """Rows ``lo .. hi`` (``lo`` the next row, at a row group's start; ``hi`` at one's start or
        the end) as chunks: ``table`` ``[size, filter mask]`` of each chunk, row group by row group
        and in the spec's order within one, ``blob`` their bytes; ``bounds`` the rows' smallest and
        largest coordinates, ``radius_index`` their radii at the positions that are multiples of
        RADIUS_INDEX_STEP, ``last_tail`` the last row with a radius or a parent (-1: none),
        ``last_radius`` the radius of row ``hi - 1``."""
        where = f"scan {self.name!r}"
        groups = -(-(hi - lo) // self.rows)
        if lo != self._flushed or (hi != self.n and (hi - lo) % self.rows) or not lo < hi <= self.n:
            raise InputError(f"{where}: chunks of rows {lo}..{hi} do not follow row {self._flushed} in row groups "
                             f"of {self.rows}")
        if len(table) != groups * len(self._spec) or sum(int(s) for s, _ in table) != len(blob):
            raise InputError(f"{where}: the chunk table of rows {lo}..{hi} does not match its bytes")
        assert self._tmp is not None
        F.reserve(self._tmp, int((hi - lo) * self._row_width * 1.1) + self._margin, f"scan {self.name!r}")
        view, at = memoryview(blob), 0
        try:
            for i in range(groups):
                for (key, _, tail, _), (size, mask) in zip(self._spec, table[i * len(self._spec):(i + 1) * len(self._spec)], strict=True):
                    off = (lo + i * self.rows,) + (0,) * len(tail)
                    self._ds[key].id.write_direct_chunk(off, view[at:at + int(size)], int(mask))
                    at += int(size)
        except OSError as exc:
            raise F.disk_error(exc, self.path) from None
        self._lo = np.minimum(self._lo, np.asarray(bounds[0], np.float64))
        self._hi = np.maximum(self._hi, np.asarray(bounds[1], np.float64))
        self._rindex.append(np.asarray(radius_index, np.float64))
        self._last_tail = max(self._last_tail, int(last_tail))
        self._last_radius = float(last_radius)
        self._written = self._flushed = hi


def radius_index(rad: np.ndarray, lo: int) -> np.ndarray:
    """The radius index's entries among rows ``lo .. lo + len(rad)`` (those at multiples of
    RADIUS_INDEX_STEP), as :class:`ScanWriter` samples them."""
    first = -(-lo // L.RADIUS_INDEX_STEP) * L.RADIUS_INDEX_STEP
    return rad[first - lo :: L.RADIUS_INDEX_STEP].copy()
