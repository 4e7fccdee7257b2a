"""Public entry points of lodbuilder.io: read_scan, read_scans, write_points, write_scan."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import strict_keywords
from ..errors import FormatError, InputError, LodbuilderError, ScanFileError
from ._files import atomic_output, check_input_file
from .base import Scan
from .registry import reader_for, writer_for

log = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


@strict_keywords
def read_scans(path: PathLike) -> list[Scan]:
    """Read every scan in a file (E57 files may hold several; other formats hold one).

    Each Scan has float64 (N, 3) points in world coordinates (poses applied), every other per-point
    field as an attribute, ``reader`` set to the format and ``metadata`` holding what a writer needs
    to reproduce the format. Raises ScanFileError (missing/unreadable file), UnsupportedFormatError
    (unknown suffix), MissingDependencyError (optional reader library absent) or FormatError
    (malformed file, no x/y/z, NaN/inf coordinates, no points).
    """
    p = check_input_file(path)
    fmt, module = reader_for(p)
    try:
        scans = module.read(p)
    except LodbuilderError:
        raise
    except MemoryError:
        raise FormatError(f"{p}: too large to load into memory; split the scan or use a machine with more memory") from None
    except OSError as exc:
        raise ScanFileError(f"{p}: cannot be read ({_one_line(exc)}); check the file") from None
    except Exception as exc:  # a parser library's own error on a malformed file
        raise FormatError(f"{p}: cannot be read as {fmt.upper()} ({_one_line(exc)}); check or re-export the file") from exc
    if not scans:
        raise FormatError(f"{p}: holds no scans; nothing to read")
    for s in scans:
        _check_scan(p, s)
    return scans


def _check_scan(p: Path, s: Scan) -> None:
    pts = s.points
    where = f"{p}" if s.name == p.stem else f"{p} (scan {s.name!r})"
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FormatError(f"{where}: coordinates have shape {pts.shape}; expected (N, 3)")
    if pts.shape[0] == 0:
        raise FormatError(f"{where}: holds no points; a scan needs at least one point")
    if pts.dtype != np.float64 or not pts.flags.c_contiguous:
        s.points = np.ascontiguousarray(pts, dtype=np.float64)
    bad = ~np.isfinite(s.points).all(axis=1)
    nbad = int(bad.sum())
    if nbad:
        raise FormatError(
            f"{where}: {nbad} point(s) have NaN or inf coordinates (first at index {int(np.argmax(bad))}); "
            "remove them from the file before building"
        )
    n = s.points.shape[0]
    for k, v in s.attributes.items():
        if v.shape[0] != n:
            raise FormatError(f"{where}: attribute {k!r} has {v.shape[0]} values for {n} points")


@strict_keywords
def read_scan(path: PathLike, *, name: str | None = None) -> Scan:
    """Read a file holding one scan; see :func:`read_scans`.

    A file with several scans (an E57 file with more than one scan) raises FormatError: read it
    with :func:`read_scans`, or let the collection builder take every scan.
    """
    scans = read_scans(path)
    if len(scans) > 1:
        names = ", ".join(s.name for s in scans[:5]) + (" ..." if len(scans) > 5 else "")
        raise FormatError(
            f"{path}: holds {len(scans)} scans ({names}); use lodbuilder.io.read_scans() to read them all"
        )
    scan = scans[0]
    if name is not None:
        scan.name = name
    return scan


def _prepare_attributes(points: np.ndarray, attributes: Any, rank: Any) -> dict[str, np.ndarray]:
    n = points.shape[0]
    attrs: dict[str, np.ndarray] = {}
    for k, v in dict(attributes or {}).items():
        a = np.asarray(v)
        if a.ndim == 0 or a.shape[0] != n:
            raise InputError(f"attribute {k!r} has shape {a.shape}; expected first dimension {n} (one value per point)")
        if a.dtype == object:
            raise InputError(f"attribute {k!r} holds Python objects; only numeric attributes can be written")
        if k in ("x", "y", "z"):
            raise InputError(f"attribute name {k!r} clashes with a coordinate; rename it")
        attrs[str(k)] = a
    if rank is not None and rank is not False:
        if rank is True:
            r = np.arange(n, dtype=np.uint32 if n < 2**32 else np.int64)
        else:
            r = np.asarray(rank)
            if r.shape != (n,) or r.dtype.kind not in "iu":
                raise InputError(f"rank must be True or an integer array of shape ({n},), got {r.dtype} {r.shape}")
        attrs["rank"] = r
    return attrs


@strict_keywords
def write_points(
    path: PathLike,
    points: Any,
    attributes: dict[str, Any] | None = None,
    *,
    metadata: dict[str, Any] | None = None,
    rank: bool | np.ndarray | None = None,
) -> Path:
    """Write points (and per-point attributes) to ``path``, the format chosen by its suffix.

    Formats: ``.ply`` (binary little-endian, every attribute a vertex property; coordinates float32
    when ``metadata`` says the source stored float32 and no value changes, else float64); ``.npy``
    (plain (N, 3) float64 without attributes, else a structured array with fields x, y, z, ...);
    ``.npz`` (``points`` plus one array per attribute); ``.csv`` / ``.xyz`` (header line, one point per
    line, exact float64 text); ``.las`` / ``.laz`` (needs laspy: the point format, scale, offset and
    CRS from ``metadata`` of a LAS source when given, other attributes as extra bytes).

    Progressive export: a level read from an archive is already in farthest-point order, so writing
    it keeps that order and every prefix of the file (its first k points) is itself a level. Pass
    ``rank=True`` to add a ``rank`` attribute 0..N-1 that records the order explicitly (or pass your
    own integer array of ranks).

    The file is written to a temporary file in the same directory and renamed into place, so a
    failure never leaves a partial file under ``path``. Returns the path written.
    """
    fmt, module = writer_for(path)
    try:
        pts = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"points must be an (N, 3) array of numbers, got {type(points).__name__}") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must have shape (N, 3), got {pts.shape}")
    pts = np.ascontiguousarray(pts)
    attrs = _prepare_attributes(pts, attributes, rank)
    with atomic_output(path) as tmp:
        try:
            module.write(tmp, pts, attrs, metadata)
        except LodbuilderError:
            raise
        except OSError as exc:
            raise ScanFileError(f"{path}: cannot be written ({_one_line(exc)}); check the disk and permissions") from None
    log.info("wrote %d points to %s (%s)", pts.shape[0], path, fmt)
    return Path(path)


@strict_keywords
def write_scan(path: PathLike, scan: Scan, *, rank: bool | np.ndarray | None = None) -> Path:
    """Write a :class:`Scan` with its attributes and metadata; see :func:`write_points`."""
    return write_points(path, scan.points, scan.attributes, metadata=scan.metadata, rank=rank)
