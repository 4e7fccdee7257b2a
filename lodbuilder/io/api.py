"""Public entry points of lodbuilder.io: read_scan, read_scans, write_points, write_scan."""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import strict_keywords
from ..errors import EmptyScanError, FormatError, InputError, LodbuilderError, ScanFileError
from ._files import atomic_output, check_input_file, exc_line, library_panic
from .base import Scan
from .crs import KEY_UNITS, KEY_WKT, assign_crs, crs_from_user, sidecar
from .registry import reader_for, writer_for

log = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]


@strict_keywords
def read_scans(path: PathLike, *, crs: str | None = None, crs_override: bool = False) -> list[Scan]:
    """Read every scan in a file (E57 files may hold several; other formats hold one).

    Each Scan has float64 (N, 3) points in world coordinates (poses applied), every other per-point
    field as an attribute, ``reader`` set to the format and ``metadata`` holding what a writer needs
    to reproduce the format. Raises ScanFileError (missing/unreadable file), UnsupportedFormatError
    (unknown suffix), MissingDependencyError (optional reader library absent) or FormatError
    (malformed file, no x/y/z, NaN/inf coordinates, no points).

    Each scan's CRS is ``metadata["crs_wkt"]`` (WKT or None; see :mod:`lodbuilder.io.crs`).
    ``crs`` (EPSG:XXXX, WKT or a file holding WKT) assigns one to scans without it; a file that
    declares another CRS is refused unless ``crs_override``.
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
        raise ScanFileError(f"{p}: cannot be read ({exc_line(exc)}); check the file") from None
    except BaseException as exc:  # a parser library's own error on a malformed file (or its panic)
        if not isinstance(exc, Exception) and not library_panic(exc):
            raise
        raise FormatError(f"{p}: cannot be read as {fmt.upper()} ({exc_line(exc)}); check or re-export the file") from exc
    if not scans:
        raise FormatError(f"{p}: holds no scans; nothing to read")
    for s in scans:
        _check_scan(p, s)
        s.metadata.setdefault(KEY_WKT, None)
        if crs is not None:
            assign_crs(s.metadata, crs, override=crs_override, what=str(p))
    return scans


def _check_scan(p: Path, s: Scan) -> None:
    pts = s.points
    where = f"{p}" if s.name == p.stem else f"{p} (scan {s.name!r})"
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FormatError(f"{where}: coordinates have shape {pts.shape}; expected (N, 3)")
    if pts.shape[0] == 0:
        raise EmptyScanError(f"{where}: holds no points; a scan needs at least one point")
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
def read_scan(path: PathLike, *, name: str | None = None, crs: str | None = None, crs_override: bool = False) -> Scan:
    """Read a file holding one scan; see :func:`read_scans`.

    A file with several scans (an E57 file with more than one scan) raises FormatError: read it
    with :func:`read_scans`, or let the collection builder take every scan.
    """
    scans = read_scans(path, crs=crs, crs_override=crs_override)
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


#: formats whose CRS travels in a ``<file>.prj`` sidecar (they have no place for it inside)
SIDECAR_CRS = ("text", "npy")


@strict_keywords
@contextlib.contextmanager
def collect_notes() -> Iterator[list[str]]:
    """Take the warnings lodbuilder.io logs while the block runs (what readers and writers
    changed: casts, scaled colours, skipped properties...) into a list, for a command's report.

    They are collected whatever the log level (``-q`` included) and not logged further: the
    caller reports them, once. Other records (INFO, DEBUG, errors) go on to the log as usual."""
    notes: list[str] = []
    logger = logging.getLogger("lodbuilder.io")
    parent = logger.parent if logger.propagate else None  # (a nested block: the outer one passes them on)

    class _Handler(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.levelno == logging.WARNING:
                notes.append(record.getMessage())
            elif parent is not None:
                parent.handle(record)

    handler = _Handler()
    level, propagate = logger.level, logger.propagate
    logger.setLevel(min(logger.getEffectiveLevel(), logging.WARNING))
    logger.propagate = False
    logger.addHandler(handler)
    try:
        yield notes
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate


def log_notes(path: PathLike, notes: list[str]) -> None:
    """Log what a writer changed in ``path``, one warning of lodbuilder.io per note (the one way
    writers report changes; :func:`collect_notes` gathers them)."""
    for note in notes:
        log.warning("%s: %s", path, note)


def _is_level(obj: Any) -> bool:
    return all(hasattr(obj, a) for a in ("points", "attributes", "source_index", "radius", "crs"))


def _what_to_write(points: Any, attributes: Any, metadata: Any, crs: Any,
                   colour_depth: Any) -> tuple[np.ndarray, Any, dict[str, Any]]:
    """The (N, 3) float64 points, the attributes and the metadata :func:`write_points` writes: a
    Level's own unless given, the CRS as WKT, the PLY colour depth; checked."""
    meta = dict(metadata or {})
    if _is_level(points):
        level = points
        if attributes is None:
            attributes = level.attributes
        if crs is None and level.crs is not None:
            meta[KEY_WKT] = level.crs  # already WKT: no pyproj on the slice path
        if level.units and not meta.get(KEY_UNITS):
            meta[KEY_UNITS] = level.units
        points = level.points
    if crs is not None:
        meta[KEY_WKT] = crs_from_user(crs)
    if colour_depth is not None:
        if colour_depth not in (8, 16):
            raise InputError(f"colour_depth must be 8 or 16, got {colour_depth!r}")
        meta["write_colour_depth"] = int(colour_depth)
    try:
        pts = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"points must be an (N, 3) array of numbers, got {type(points).__name__}") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must have shape (N, 3), got {pts.shape}")
    return np.ascontiguousarray(pts), attributes, meta


@strict_keywords
def write_points(
    path: PathLike,
    points: Any,
    attributes: dict[str, Any] | None = None,
    *,
    metadata: dict[str, Any] | None = None,
    rank: bool | np.ndarray | None = None,
    crs: str | None = None,
    colour_depth: int | None = None,
) -> Path:
    """Write points (and per-point attributes) to ``path``, the format chosen by its suffix.

    ``points`` is an (N, 3) array, or a :class:`lodbuilder.levels.Level` (its points,
    attributes and CRS are written; ``attributes`` and ``crs`` given here take precedence).

    Formats: ``.ply`` (binary little-endian; x, y, z first, then nx ny nz, red green blue alpha,
    then the other attributes in their order; colours as uchar unless ``colour_depth=16``;
    coordinates float32 when ``metadata`` says the source stored float32 and no value changes,
    else float64; the CRS as a ``comment crs <WKT>`` header line); ``.npy`` (plain (N, 3) float64
    without attributes, else a structured array with fields x, y, z, ...); ``.npz`` (``points``
    plus one array per attribute, and the metadata as JSON); ``.csv`` / ``.xyz`` (one header
    line of names, one point per line, every value printed so that it reads back to the same
    value of its dtype); ``.las`` / ``.laz`` (needs laspy; see
    :func:`lodbuilder.io.las.las_layout` for every rule). CSV, XYZ and NPY files carry their CRS
    in a sidecar ``<file>.prj`` (WKT). Every change a format forces (a cast, a scaled colour, a
    quantised coordinate) is logged as a warning of ``lodbuilder.io``: see :func:`collect_notes`.

    ``crs``: WKT (or EPSG:XXXX with pyproj) to write; by default ``metadata["crs_wkt"]``.
    ``colour_depth``: 8 or 16 bits for PLY colours (default 8: uchar, which PLY viewers expect;
    16-bit values above 255 are divided by 257, noted); other formats keep the source dtype
    (LAS always 16 bit).

    Progressive export: a level read from an archive is already in farthest-point order, so writing
    it keeps that order and every prefix of the file (its first k points) is itself a level. Pass
    ``rank=True`` to add a ``rank`` attribute 0..N-1 that records the order explicitly (or pass your
    own integer array of ranks).

    The file is written to a temporary file in the same directory and renamed into place, so a
    failure never leaves a partial file under ``path``. Returns the path written.
    """
    fmt, module = writer_for(path)
    pts, attributes, meta = _what_to_write(points, attributes, metadata, crs, colour_depth)
    attrs = _prepare_attributes(pts, attributes, rank)
    wkt = meta.get(KEY_WKT)
    with atomic_output(path) as tmp:  # (a full disk or another failed write: one line)
        notes = module.write(tmp, pts, attrs, meta) or []
        if fmt in SIDECAR_CRS and Path(path).suffix.lower() != ".npz":
            _write_sidecar(Path(path), wkt)
    log_notes(path, notes)
    log.info("wrote %d points to %s (%s)", pts.shape[0], path, fmt)
    return Path(path)


def _write_sidecar(path: Path, wkt: str | None) -> None:
    """``<file>.prj`` with the WKT; an old sidecar of the same file is removed when there is no CRS
    (it described the file being replaced)."""
    side = sidecar(path)
    if wkt:
        with atomic_output(side) as tmp:
            tmp.write_text(wkt + "\n", encoding="utf-8")
    elif side.is_file():
        side.unlink()
        log.info("removed %s: the new %s has no CRS", side, path.name)


@strict_keywords
def write_scan(path: PathLike, scan: Scan, *, rank: bool | np.ndarray | None = None) -> Path:
    """Write a :class:`Scan` with its attributes and metadata; see :func:`write_points`."""
    return write_points(path, scan.points, scan.attributes, metadata=scan.metadata, rank=rank)
