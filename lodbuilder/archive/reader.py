"""Reading archives: open, list scans, per-scan views, level queries reading only the prefix.

This module and the ones it imports stay clear of numba, pyvista and dask, so that
``lodbuilder slice`` starts fast.
"""

from __future__ import annotations

import os
from typing import Any

from .._validate import quoted_names, strict_keywords, strict_methods
from ..errors import (
    CorruptArchiveError,
    LodbuilderError,
    NotAnArchiveError,
    ScanFileError,
    ScanNotFoundError,
)
from . import layout as L
from . import safety
from .index import Where, check_part, first_line, read_rows, root_attrs
from .layout import IndexRow
from .scanview import ScanView


@strict_keywords
def check_archive_file(
    path: str | os.PathLike[str], *, storage_options: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Root attributes of the archive at ``path`` (a file or a URL); raise a one-line error if it
    is not one we can read."""
    where = Where.of(path, storage_options)
    f, io = open_h5(where)
    try:
        return _checked_root(f, where)
    finally:
        f.close()
        if io is not None:
            io.close()


def _checked_root(f: Any, where: Where) -> dict[str, Any]:
    """Root attributes of the open archive file ``f``, after :func:`safety.check_file` has
    walked its metadata: nothing in it points outside the file, and its sizes are ones the file
    can hold. Called on every archive file (index or part) before anything else is read."""
    with safety.h5_errors(where.display, "its root attributes"):
        attrs = root_attrs(f, where)
    safety.check_file(f, where.display)
    return attrs


@strict_keywords
def open_h5(where: Where, size: int | None = None) -> tuple[Any, Any]:
    """Open the archive file at ``where`` read-only: ``(h5py.File, remote file or None)``.

    This is the one place where lodbuilder opens an archive file (an index, a single-scan archive
    or a part), local or remote. ``size`` is the file's size when the caller knows it (a part's
    size is in its index), which saves a request for a remote file."""
    import h5py

    path = where.display
    rf = None
    if where.url is not None:
        from .remote import open_remote

        rf = open_remote(where.url, size=size, storage_options=where.options)
        target: Any = rf
    else:
        local = where.local
        assert local is not None
        if not local.exists():
            raise ScanFileError(
                f"archive {local} does not exist; build one with 'lodbuilder build'"
            )
        if local.is_dir():
            raise NotAnArchiveError(f"{local} is a directory, not an lodbuilder archive")
        if not h5py.is_hdf5(local):
            raise NotAnArchiveError(
                f"{local} is not an lodbuilder archive (not an HDF5 file); build one with "
                "'lodbuilder build'"
            )
        target = local
    try:
        # through safety.GuardedFile: global heaps are checked before HDF5 parses them
        f = safety.open_h5(target, path)
        if rf is not None:  # later misses fetch whole file-space pages (metadata is paged)
            rf.set_block(max(rf.block, f.id.get_create_plist().get_file_space_page_size()))
    except (OSError, RuntimeError, ValueError, KeyError) as exc:
        if isinstance(exc, LodbuilderError):
            raise
        if rf is not None:
            rf.close()
            if not rf.looks_like_hdf5():
                raise NotAnArchiveError(
                    f"{path} is not an lodbuilder archive (not an HDF5 file)"
                ) from None
        raise NotAnArchiveError(
            f"{path} cannot be opened as an HDF5 archive: {first_line(exc)}"
        ) from None
    return f, rf


@safety.guarded(lambda self: self.path)
@strict_methods
@safety.open_only(allowed=("close",))
class Archive:
    """An open archive. Use as a context manager: ``with open_archive(p) as a: ...``.

    ``path`` is a local file or an ``http(s)://`` / ``s3://`` URL (read through fsspec, which the
    ``remote`` extra installs); ``storage_options`` go to fsspec (e.g. an S3 ``endpoint_url``),
    but for lodbuilder's own ``timeout`` (seconds a server may stay silent, default 30) and
    ``follow_redirects`` (an HTTP redirect to another host is refused without it)."""

    def __init__(
        self, path: str | os.PathLike[str], *, storage_options: dict[str, Any] | None = None
    ) -> None:
        self._where = Where.of(path, storage_options)
        self.path: Any = self._where.display
        self._parts: dict[str, tuple[Any, Any]] = {}
        self._file, self._io = open_h5(self._where)
        try:
            self.attrs = _checked_root(self._file, self._where)
            self._rows = {r.name: r for r in read_rows(self._file, self.path)}
        except BaseException:
            self.close()
            raise
        self.schema_version = int(self.attrs[L.A_SCHEMA_VERSION])
        self.lodbuilder_version = str(self.attrs.get(L.A_VERSION, ""))

    def _check_open(self) -> None:
        if not self._file.id.valid:
            raise safety.closed_error(self.path)

    @property
    def file(self) -> Any:
        """The h5py file of the archive itself (its index; scans may be in part files)."""
        return self._file

    @property
    def rows(self) -> list[IndexRow]:
        """One :class:`IndexRow` per scan (name, size, bounds, part file), sorted by name."""
        return [self._rows[n] for n in self.scans]

    @property
    def scans(self) -> list[str]:
        """Scan names, sorted."""
        return sorted(self._rows)

    @property
    def nbytes(self) -> int:
        """Bytes of the archive: its file plus the part files it lists."""
        if self._io is not None:
            total = int(self._io.size)
        else:
            assert self._where.local is not None
            total = self._where.local.stat().st_size
        return total + sum({r.part: r.part_bytes for r in self._rows.values() if r.part}.values())

    def scan(self, name: str | None = None) -> ScanView:
        """The scan called ``name``; ``None`` is allowed when the archive holds exactly one scan."""
        names = self.scans
        if name is None:
            if len(names) == 1:
                name = names[0]
            elif not names:
                raise ScanNotFoundError(f"archive {self.path} holds no scans")
            else:
                raise ScanNotFoundError(
                    f"archive {self.path} holds {len(names)} scans; choose one with --scan "
                    f"(one of {quoted_names(names)})"
                )
        if name not in self._rows:
            raise ScanNotFoundError(
                f"archive {self.path} has no scan {name!r}; it holds {quoted_names(names)}"
            )
        group, io = self._scan_group(name)
        return ScanView(self, name, group, io)

    def _scan_group(self, name: str) -> tuple[Any, Any]:
        """``(h5py group, remote file or None)`` of scan ``name``: the one place where a scan name
        is resolved to its data, in this file or in a part file of the archive's own directory."""
        import h5py

        row = self._rows[name]
        f, io = self._file, self._io
        where = self._where
        if row.part:
            part = self._parts.get(row.part)
            if part is None:
                part = self._open_part(row)
                self._parts[row.part] = part
            f, io = part
            where = self._where.part(row.part)
        try:
            scans = f.get(L.G_SCANS)
            link = scans.get(name, getlink=True) if isinstance(scans, h5py.Group) else None
            if not isinstance(link, h5py.HardLink) or not isinstance(scans[name], h5py.Group):
                what = f"part {row.part}" if row.part else "it"
                raise CorruptArchiveError(
                    f"archive {self.path}: {what} does not hold scan {name!r} (no group "
                    f"/scans/{name}); the index is damaged or crafted"
                )
            return scans[name], io
        except CorruptArchiveError:
            raise
        except (OSError, RuntimeError, KeyError, ValueError) as exc:
            raise CorruptArchiveError(
                f"archive {where.display}: scan {name!r} cannot be read ({first_line(exc)}); the "
                "file is damaged"
            ) from None

    def _check_part(self, row: IndexRow) -> Where:
        """Where the part file of ``row`` is, checked to be one of this archive's own."""
        return check_part(self._where, row, self.path)

    def _open_part(self, row: IndexRow) -> tuple[Any, Any]:
        """Open the part file of ``row`` after checking that it is one of this archive's own."""
        where = self._check_part(row)
        try:
            f, io = open_h5(where, size=row.part_bytes or None)
        except NotAnArchiveError:
            raise CorruptArchiveError(
                f"archive {self.path}: part {row.part} of scan {row.name!r} is not an lodbuilder "
                "archive; refusing to read it"
            ) from None
        try:
            _checked_root(f, where)
        except NotAnArchiveError:
            f.close()
            raise CorruptArchiveError(
                f"archive {self.path}: part {row.part} of scan {row.name!r} is not an lodbuilder "
                "archive; refusing to read it"
            ) from None
        except BaseException:
            f.close()
            raise
        return f, io

    def __iter__(self):
        return (self.scan(n) for n in self.scans)

    def __len__(self) -> int:
        return len(self._rows)

    def index(self) -> list[dict[str, Any]]:
        """One dict per scan: name, n_points, bounds_min, bounds_max, part (from /index)."""
        ig = self._file.get(L.G_INDEX)
        if ig is None:
            return []
        if L.I_PART in ig:
            return [
                {
                    "name": r.name,
                    "n_points": r.n_points,
                    "bounds_min": list(r.bounds_min),
                    "bounds_max": list(r.bounds_max),
                    "part": r.part,
                }
                for r in self.rows
            ]
        names = [b.decode("utf-8", "replace") for b in ig[L.I_NAME][:]]
        counts = ig[L.I_N_POINTS][:]
        lo, hi = ig[L.I_BOUNDS_MIN][:], ig[L.I_BOUNDS_MAX][:]
        return [
            {"name": n, "n_points": int(c), "bounds_min": a.tolist(), "bounds_max": b.tolist()}
            for n, c, a, b in zip(names, counts, lo, hi, strict=True)
        ]

    def close(self) -> None:
        for f, io in list(self._parts.values()):
            f.close()
            if io is not None:
                io.close()
        self._parts.clear()
        if self._file is not None:
            self._file.close()
            if self._io is not None:
                self._io.close()

    def __enter__(self) -> Archive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<Archive {self.path} scans={sorted(self._rows)}>"


@strict_keywords
def open_archive(
    path: str | os.PathLike[str], *, storage_options: dict[str, Any] | None = None
) -> Archive:
    """Open an archive for reading (a context manager): a local file, or an ``https://``,
    ``http://`` or ``s3://`` URL (needs ``pip install 'lodbuilder[remote]'``)."""
    return Archive(path, storage_options=storage_options)
