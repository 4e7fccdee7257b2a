"""Where an archive's scans are: its location (a file or a URL), its /index rows, and the checks
that confine part files to the archive's own directory. No HDF5 is opened here; the reader opens
files (:func:`lodbuilder.archive.reader.open_h5`)."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import (
    ArchiveError,
    CorruptArchiveError,
    LodbuilderError,
    NotAnArchiveError,
    SchemaVersionError,
)
from . import layout as L
from .layout import IndexRow

_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:/")


def is_url(location: object) -> bool:
    """True for ``https://...``, ``s3://...`` (also after ``pathlib`` folded ``//`` into ``/``)."""
    return isinstance(location, (str, os.PathLike)) and bool(_URL.match(os.fspath(location)))


def url_text(location: object) -> str:
    """A URL as the user wrote it (``pathlib`` turns ``https://h/x`` into ``https:/h/x``)."""
    text = os.fspath(location)  # type: ignore[call-overload]
    scheme, _, rest = text.partition(":")
    return f"{scheme}://{rest.lstrip('/')}"


def root_attrs(f: Any, where: Where) -> dict[str, Any]:
    try:
        attrs = {k: L._attr_json(v) for k, v in f.attrs.items()}
    except LodbuilderError:
        raise
    except (OSError, RuntimeError, KeyError, ValueError) as exc:
        raise CorruptArchiveError(
            f"{where.display}: its root attributes cannot be read ({first_line(exc)}); the file "
            "is damaged"
        ) from None
    return _check_root_attrs(where.display, attrs)


def first_line(exc: BaseException) -> str:
    return (str(exc).splitlines() or [type(exc).__name__])[0]


def _check_root_attrs(path: Any, attrs: dict[str, Any]) -> dict[str, Any]:
    if attrs.get(L.A_FORMAT) != L.FORMAT:
        raise NotAnArchiveError(
            f"{path} is an HDF5 file but not an lodbuilder archive (no format='lodbuilder' attribute)"
        )
    version = attrs.get(L.A_SCHEMA_VERSION)
    if not isinstance(version, int):
        raise NotAnArchiveError(
            f"{path} has no integer schema_version attribute; it is not a valid archive"
        )
    if version > L.SCHEMA_VERSION:
        raise SchemaVersionError(
            f"{path} uses archive schema version {version}, newer than the {L.SCHEMA_VERSION} this "
            "lodbuilder reads; upgrade lodbuilder"
        )
    return attrs


class Where:
    """Where an archive file is: a local path or a URL (read through :mod:`.remote`)."""

    def __init__(self, local: Path | None, url: str | None, options: dict[str, Any] | None):
        self.local, self.url, self.options = local, url, options

    @classmethod
    def of(cls, path: Any, options: dict[str, Any] | None = None) -> Where:
        if isinstance(path, Where):
            return path
        if is_url(path):
            from .remote import normalise_url

            return cls(None, normalise_url(os.fspath(path)), options)
        return cls(Path(path), None, None)

    @property
    def display(self) -> Any:
        """``Path`` for a local file, the URL string for a remote one."""
        return self.local if self.local is not None else self.url

    @property
    def parts_dir(self) -> Any:
        if self.local is not None:
            return self.local.with_name(L.parts_dir_name(self.local.name))
        assert self.url is not None
        from .remote import sibling_url

        return sibling_url(self.url, L.PARTS_SUFFIX)

    def part(self, name: str) -> Where:
        """The part file ``name`` (a plain name, already checked) of this archive; a URL's query
        (a signed URL) is kept."""
        if self.local is not None:
            return Where(self.parts_dir / name, None, None)
        from .remote import sibling_url

        assert self.url is not None
        return Where(None, sibling_url(self.url, f"{L.PARTS_SUFFIX}/{name}"), self.options)


def read_rows(f: Any, path: Any) -> list[IndexRow]:
    """The scans of the open archive file ``f``: its /index rows (schema 2), or the members of
    /scans of an archive written before parts existed (schema 1)."""
    try:
        ig = f.get(L.G_INDEX)
        if ig is not None and L.I_PART in ig:
            names = [b.decode("utf-8") for b in ig[L.I_NAME][:]]
            counts = ig[L.I_N_POINTS][:]
            lo, hi = ig[L.I_BOUNDS_MIN][:], ig[L.I_BOUNDS_MAX][:]
            parts = [b.decode("ascii", "replace") for b in ig[L.I_PART][:]]
            sizes = ig[L.I_PART_BYTES][:]
            cols = (counts, lo, hi, parts, sizes)
            if any(len(c) != len(names) for c in cols):
                raise CorruptArchiveError(
                    f"archive {path}: its index columns have different lengths; the file is damaged"
                )
            rows = [
                IndexRow(n, int(c), tuple(a.tolist()), tuple(b.tolist()), p, int(s))
                for n, c, a, b, p, s in zip(names, *cols, strict=True)
            ]
            _check_names(rows, path)
            return rows
        scans = f.get(L.G_SCANS)
        rows = []
        for n in sorted(scans) if scans is not None else []:
            a = scans[n].attrs
            rows.append(
                IndexRow(
                    n,
                    int(a.get(L.S_N_POINTS, 0)),
                    tuple(np.asarray(a.get(L.S_BOUNDS_MIN, [np.nan] * 3), float).tolist()),
                    tuple(np.asarray(a.get(L.S_BOUNDS_MAX, [np.nan] * 3), float).tolist()),
                )
            )
        return rows
    except CorruptArchiveError:
        raise
    except (OSError, RuntimeError, KeyError, ValueError, TypeError, AttributeError) as exc:
        raise CorruptArchiveError(
            f"archive {path}: its index cannot be read ({first_line(exc)}); the file is damaged"
        ) from None


_LIES = "the index is damaged or crafted: restore the archive from a copy or rebuild it"


def _check_names(rows: list[IndexRow], path: Any) -> None:
    """Every index row names a valid scan, once: a name is never used as an HDF5 path, and no
    row hides another (a writer would delete the part of the row it cannot see)."""
    seen: dict[str, IndexRow] = {}
    for r in rows:
        try:
            L.check_name(r.name)
        except LodbuilderError:
            raise CorruptArchiveError(
                f"archive {path}: its index lists a scan named {r.name!r}, which is not a scan name (at most "
                f"255 bytes, no '/', '\\' or NUL, not starting with '.'); {_LIES}"
            ) from None
        if r.name in seen:
            raise CorruptArchiveError(
                f"archive {path}: its index lists scan {r.name!r} twice (parts {seen[r.name].part or path} "
                f"and {r.part or path}); {_LIES}"
            )
        seen[r.name] = r


def check_part(archive: Where, row: IndexRow, path: Any) -> Where:
    """Where the part file of ``row`` is, checked to be one of this archive's own: a plain
    name lodbuilder writes, a regular file (not a link) in the archive's own directory, of the
    size the index records."""
    import stat

    pdir = archive.parts_dir
    if not L.PART_NAME.fullmatch(row.part):
        raise CorruptArchiveError(
            f"archive {path}: scan {row.name!r} names part file {row.part!r}, which is "
            f"not a plain part name in {pdir}; refusing to follow it (the index is damaged "
            "or crafted)"
        )
    where = archive.part(row.part)
    if where.local is not None:
        try:
            dst = os.lstat(pdir)
        except FileNotFoundError:
            raise ArchiveError(
                f"archive {path}: scan {row.name!r} is stored in {where.local}, and the "
                f"directory {pdir} is missing: an archive of several scans is the file and "
                "that directory, move or copy them together"
            ) from None
        if not stat.S_ISDIR(dst.st_mode):
            raise CorruptArchiveError(
                f"archive {path}: {pdir} is not a directory (a symbolic link or a "
                "file); refusing to follow it"
            )
        try:
            st = os.lstat(where.local)
        except FileNotFoundError:
            raise ArchiveError(
                f"archive {path}: scan {row.name!r} is stored in {where.local}, which "
                f"is missing; restore the directory {pdir.name} that belongs to this archive"
            ) from None
        if not stat.S_ISREG(st.st_mode):
            raise CorruptArchiveError(
                f"archive {path}: part {row.part} of scan {row.name!r} is not a regular "
                "file (a symbolic link?); refusing to follow it"
            )
        if row.part_bytes and st.st_size != row.part_bytes:
            raise CorruptArchiveError(
                f"archive {path}: part {row.part} of scan {row.name!r} has "
                f"{st.st_size} bytes, the index says {row.part_bytes}; the part was changed "
                "or truncated"
            )
    return where


def write_index(root: Any, rows: list[IndexRow]) -> None:
    """Write /index of the open file ``root``: one row per scan, sorted by name."""
    rows = sorted(rows, key=lambda r: r.name)
    if L.G_INDEX in root:
        del root[L.G_INDEX]
    ig = root.create_group(L.G_INDEX)
    names = [r.name.encode("utf-8") for r in rows]
    parts = [r.part.encode("ascii") for r in rows]
    L.create_dataset(ig, L.I_NAME, np.array(names, dtype=f"S{max([len(e) for e in names] + [1])}"))
    L.create_dataset(ig, L.I_N_POINTS, np.array([r.n_points for r in rows], dtype=np.int64))
    L.create_dataset(
        ig, L.I_BOUNDS_MIN, np.array([r.bounds_min for r in rows], np.float64).reshape(-1, 3)
    )
    L.create_dataset(
        ig, L.I_BOUNDS_MAX, np.array([r.bounds_max for r in rows], np.float64).reshape(-1, 3)
    )
    L.create_dataset(ig, L.I_PART, np.array(parts, dtype=f"S{max([len(e) for e in parts] + [1])}"))
    L.create_dataset(ig, L.I_PART_BYTES, np.array([r.part_bytes for r in rows], dtype=np.int64))
    ig.attrs[L.A_N_SCANS] = np.int64(len(rows))
