"""Scan input and output: one module per format, chosen by file suffix (see ``registry``).

    from lodbuilder.io import read_scan, read_scans, write_points
    scan = read_scan("bun000.ply")          # Scan(points float64 (N,3), attributes, metadata)
    write_points("level.ply", pts, {"red": r}, rank=True)

=========================  ======  =====  =========================================================
suffix                     read    write  notes
=========================  ======  =====  =========================================================
.ply                       yes     yes    ascii/binary; only the vertex element is read; every
                                          vertex property but x/y/z is an attribute (fixed-length
                                          lists as (N, k), others skipped with a note); written
                                          x y z, nx ny nz, red green blue alpha, rest; uchar colour
                                          by default; CRS as ``comment crs <WKT>``
.las .laz (.copc.laz)      yes     yes    laspy + lazrs (``pip install lodbuilder[las]``); every
                                          dimension incl. extra bytes; writing through
                                          ``las.las_layout`` (nothing lost, every change noted);
                                          .copc.laz is read, not written (``lodbuilder.export``)
.e57                       yes     no     pye57 (``pip install lodbuilder[e57]``); every scan
                                          (``read_scans``), pose applied, invalid points dropped
.xyz .pts .csv .txt        yes     .csv   header detection; see ``lodbuilder.io.text``; written
                                   .xyz   with one header line, values at the source precision
.npy .npz                  yes     yes    plain (N, 3) or structured x/y/z/...; see ``lodbuilder.io.npy``
=========================  ======  =====  =========================================================

CRS: every reader puts the file's CRS (WKT) in ``metadata["crs_wkt"]`` and every writer writes it
(LAS VLR, PLY comment, ``<file>.prj`` sidecar for CSV/XYZ/NPY, NPZ metadata); see
:mod:`lodbuilder.io.crs`. What a writer had to change (a cast, a scaled colour, quantised
coordinates) is logged as a warning of ``lodbuilder.io`` (:func:`collect_notes` gathers them).

Every error is a one-line :mod:`lodbuilder.errors` exception naming the file and the fix.
Writes are atomic (temporary file in the same directory, then ``os.replace``).
"""

from __future__ import annotations

from ._files import file_sha256
from .api import collect_notes, read_scan, read_scans, write_points, write_scan
from .base import Scan
from .registry import READERS, WRITERS, register

__all__ = ["READERS", "WRITERS", "Scan", "collect_notes", "file_sha256", "read_scan", "read_scans", "register",
           "write_points", "write_scan"]
