"""Archive writes that grow in O(new data) and stay atomic.

An archive of one scan is one self-contained file (``NAME.h5``). Adding scans turns it into an
index plus one *part* file per scan in ``NAME.h5.scans/``:

1. under the archive's lock, every new scan is written (or hard-linked, for a finished part) into
   ``NAME.h5.scans/<stem>-<token>.h5``, through a temporary that is fsync'ed and renamed;
2. the first time, the scans stored in ``NAME.h5`` itself are moved out by hard-linking that file
   into the directory as a part (O(1), nothing copied);
3. a new index file (a few kB) is written to a temporary, fsync'ed and renamed over ``NAME.h5``;
4. parts no index lists any more (replaced scans, leftovers of a killed writer) are deleted.

A ``kill -9`` at any moment leaves ``NAME.h5`` either the old archive or the new one, both
complete: before step 3 the old index lists only old, untouched parts; after it every part the
new index lists is already in place. Leftovers are collected by the next write. Scans already
stored are never copied (step 2 links, it does not copy), so adding a scan costs the scan plus
the index, whatever the archive holds; replacing one scan, or adding an importance map or an
ordering to it, rewrites only that scan.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import os
import secrets
import shutil
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .._resources import release_pages
from ..errors import ArchiveError, CorruptArchiveError, InputError, ScanNotFoundError
from ..io.base import Scan
from ..sampling.ordering import Ordering
from . import files as F
from . import layout as L
from .files import check_writable_dir, remove_stale_temps  # noqa: F401 - public re-exports
from .index import write_index
from .layout import IndexRow
from .scanwriter import PartInfo, ScanWriter, close_quietly, new_file

log = logging.getLogger(__name__)

__all__ = [
    "ScanRecord",
    "ScanWriter",
    "PartInfo",
    "register_parts",
    "update_archive",
    "write_archive",
    "add_importance",
    "add_ordering",
    "check_writable_dir",
    "remove_stale_temps",
]


@dataclass
class ScanRecord:
    """Everything stored for one scan.

    ``ordering`` orders the scan's points (input indices); ``importance`` maps are per input point
    (input order) with their parameters; ``orderings`` are extra orderings (input indices) with
    their parameters.
    """

    scan: Scan
    ordering: Ordering
    build: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    importance: dict[str, tuple[np.ndarray, dict[str, Any]]] = field(default_factory=dict)
    orderings: dict[str, tuple[Ordering, dict[str, Any]]] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# one scan into one file


def _validate_record(rec: ScanRecord) -> None:
    scan, ordg = rec.scan, rec.ordering
    L.check_name(scan.name)
    n = len(scan)
    if ordg.n_points != n:
        raise InputError(
            f"ordering of scan {scan.name!r} is for {ordg.n_points} points but the scan has {n}"
        )
    k = len(ordg)
    if k < 1:
        raise InputError(f"ordering of scan {scan.name!r} is empty; build a full ordering")
    for key, arr in scan.attributes.items():
        L.check_name(key, "attribute name")
        if np.asarray(arr).shape[:1] != (n,):
            raise InputError(
                f"attribute {key!r} of scan {scan.name!r} has shape {np.shape(arr)}, expected ({n}, ...)"
            )
    for key, (values, _) in rec.importance.items():
        arr = np.asarray(values)
        if arr.shape != (n,) or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
            raise InputError(
                f"importance map {key!r} must hold one number per point, shape ({n},), got {arr.shape}"
            )
    for key, (extra, _) in rec.orderings.items():
        if extra.n_points != n:
            raise InputError(f"ordering {key!r} is for {extra.n_points} points but the scan has {n}")


def _stored_permutation(ordg: Ordering) -> np.ndarray:
    """Input index of each stored position: the ordering, then unordered points by input index."""
    n = ordg.n_points
    order = np.asarray(ordg.order, dtype=np.int64)
    if order.shape[0] == n:
        return order
    seen = np.zeros(n, dtype=bool)
    seen[order] = True
    return np.concatenate([order, np.flatnonzero(~seen)])


def _inverse(perm: np.ndarray) -> np.ndarray:
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.shape[0], dtype=np.int64)
    return inv


def _write_rows_of(w: ScanWriter, rec: ScanRecord, perm: np.ndarray, lo: int, hi: int) -> None:
    """Hand ``w`` the stored rows ``lo:hi`` of ``rec`` (``perm``: the input index of each row)."""
    ordg, idx, k = rec.ordering, perm[lo:hi], len(rec.ordering)
    radius = np.zeros(hi - lo, dtype=np.float64)
    parent = np.full(hi - lo, -1, dtype=np.int64)
    if lo < k:
        radius[: min(hi, k) - lo] = ordg.radius[lo:hi]
        parent[: min(hi, k) - lo] = ordg.parent[lo:hi]
    w.write(
        np.asarray(rec.scan.points, dtype=np.float64)[idx],
        idx,
        radius,
        parent,
        attributes={key: np.asarray(arr)[idx] for key, arr in rec.scan.attributes.items()},
        importance={key: np.asarray(v)[idx].astype(np.float32) for key, (v, _) in rec.importance.items()},
    )
    for arr in (rec.scan.points, *rec.scan.attributes.values()):
        release_pages(arr)  # (a scan set aside: its pages are read from the file again by the next group)


def write_record(path: str | os.PathLike[str], rec: ScanRecord) -> PartInfo:
    """Write ``rec`` as a self-contained single-scan archive file at ``path`` (atomically)."""
    _validate_record(rec)
    scan, ordg = rec.scan, rec.ordering
    n, k = len(scan), len(ordg)
    perm = _stored_permutation(ordg)
    _, enc, _, _ = L.encode_points(scan.points, scan.metadata)  # (elementwise: the input order will do)
    build = {
        "voxel_size": ordg.voxel_size,
        "band_radius": ordg.band_radius,
        "n_seeds": int(np.asarray(ordg.seeds).size),
        "engine_stats": ordg.stats,
        **rec.build,
    }
    inv = _inverse(perm) if rec.orderings else None
    orderings = {}
    for key, (extra, params) in rec.orderings.items():
        assert inv is not None
        meta = {"voxel_size": extra.voxel_size, "band_radius": extra.band_radius,
                "engine_stats": extra.stats, **dict(params or {})}
        positions = inv[np.asarray(extra.order, dtype=np.int64)]
        orderings[key] = (positions, extra.radius, extra.parent, meta)
    with ScanWriter(path, scan.name, n, metadata=scan.metadata, encoding=enc) as w:
        for lo in range(0, n, w.rows):  # a row group at a time: no reordered copy of the whole scan
            _write_rows_of(w, rec, perm, lo, min(lo + w.rows, n))
        return w.finish(
            n_ordered=k,
            seeds=ordg.seeds,
            build=build,
            provenance={"reader": scan.reader, **rec.provenance},
            importance_parameters={key: p for key, (_, p) in rec.importance.items()},
            orderings=orderings,
            stop_radius=ordg.stop_radius,
        )


def copy_scan(
    view: Any,
    path: Path,
    *,
    importance: Mapping[str, tuple[np.ndarray, Mapping[str, Any] | None]] | None = None,
    orderings: Mapping[str, tuple[Any, Any, Any, Mapping[str, Any] | None]] | None = None,
) -> PartInfo:
    """Rewrite the scan of ``view`` (an open ScanView) into a new file at ``path``, with extra or
    replaced importance maps (stored order) and orderings (stored positions).

    Every row is read through the checksums and re-checked by the ScanWriter: a damaged scan is
    refused (CorruptArchiveError), never copied."""
    importance = dict(importance or {})
    orderings = dict(orderings or {})
    n = view.n_points  # the reader checked the file (nothing stored outside it) and the scan's shapes
    imp_names = sorted(set(view.importance_names) | set(importance))
    try:
        with ScanWriter(path, view.name, n, metadata=view.format_metadata, encoding=view.encoding) as w:
            step = w.rows * 16
            for lo in range(0, n, step):
                hi = min(n, lo + step)
                rows = view.stored_rows(lo, hi)
                imps = {key: (np.asarray(importance[key][0])[lo:hi] if key in importance else rows["importance"][key])
                        for key in imp_names}
                w.write(rows["points"], rows["source_index"], rows["radius"], rows["parent"],
                        attributes=rows["attributes"], importance=imps)
            params = {key: view.importance_parameters(key) for key in view.importance_names}
            params.update({key: dict(p or {}) for key, (_, p) in importance.items()})
            olds = {key: (*view.ordering(key), view.ordering_parameters(key))
                    for key in view.ordering_names if key not in orderings}
            olds.update(orderings)
            return w.finish(
                n_ordered=view.n_ordered,
                seeds=view.seeds,
                build=view.build,
                provenance=view.provenance,
                format_metadata=view.format_metadata,
                importance_parameters=params,
                orderings=olds,
                stop_radius=view.stop_radius,
            )
    except InputError as exc:
        raise CorruptArchiveError(
            f"archive {view.archive.path}: scan {view.name!r} breaks the archive's invariants "
            f"({exc}); it is damaged and was not copied, rebuild it from its source"
        ) from None


# ---------------------------------------------------------------------------------------------
# the index and its parts


@dataclass
class _Add:
    """A scan to add: its name and how to write it to a given final path."""

    name: str
    write: Callable[[Path], PartInfo]


def parts_dir(path: Path) -> Path:
    """The directory of ``path``'s part files: ``NAME.h5.scans``."""
    return path.with_name(L.parts_dir_name(path.name))


def _current(path: Path) -> tuple[list[IndexRow], str | None]:
    """The rows and creation time of the archive at ``path`` ([] and None if there is none), with
    every part it lists checked to be a plain file of its own directory."""
    if not path.exists():
        return [], None
    from .reader import open_archive

    with open_archive(path) as arc:
        rows = arc.rows
        created = arc.attrs.get(L.A_CREATED)
        parts = [r for r in rows if r.part]
        if parts:
            # the reader's confinement checks (plain name, regular file in the archive's own
            # directory, recorded size), from one directory listing; a row that fails them is
            # checked again by the reader, which names the fault
            if parts_dir(path).is_symlink():
                arc._check_part(parts[0])  # refuses a directory that is a link
            try:
                entries = {e.name: e for e in os.scandir(parts_dir(path))}
            except OSError:
                entries = {}
            for r in parts:
                e = entries.get(r.part)
                if not (
                    L.PART_NAME.fullmatch(r.part)
                    and e is not None
                    and e.is_file(follow_symlinks=False)
                    and e.stat(follow_symlinks=False).st_size == r.part_bytes
                ):
                    arc._check_part(r)
    return rows, created if isinstance(created, str) else None


def _link_or_copy(src: Path, dst: Path) -> None:
    """Make ``dst`` (new, in the same file system if possible) hold the bytes of ``src``: a hard
    link, or a copy through a temporary when the file system cannot link."""
    try:
        os.link(src, dst)
        return
    except OSError as exc:
        if exc.errno == errno.EEXIST:
            raise
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise F.disk_error(exc, dst) from None
    tmp = F.tmp_name(dst)
    try:
        tmp.touch()
        F.reserve(tmp, src.stat().st_size, f"a copy of {src.name}")
        shutil.copyfile(src, tmp)
        F.release(tmp)
        F.publish(tmp, dst)
    except OSError as exc:
        F.unlink_quietly(tmp)
        raise F.disk_error(exc, dst) from None
    except BaseException:
        F.unlink_quietly(tmp)
        raise


def _write_index_file(path: Path, rows: list[IndexRow], created: str | None) -> None:
    tmp = F.tmp_name(path)
    f = None
    try:
        tmp.touch()
        F.reserve(tmp, 2048 * len(rows) + (128 << 10), "the archive index")
        f = new_file(tmp, 1024 * len(rows), created)
        write_index(f, rows)
        f.flush()
        f.close()
        F.release(tmp)
        F.publish(tmp, path)
    except OSError as exc:
        if f is not None:
            close_quietly(f)
        F.unlink_quietly(tmp)
        raise F.disk_error(exc, path) from None
    except BaseException:
        if f is not None:
            close_quietly(f)
        F.unlink_quietly(tmp)
        raise


def _collect(path: Path, listed: Iterable[str], *, remove_empty: bool = True) -> None:
    """Delete what no index lists in ``NAME.h5.scans/`` (parts lodbuilder named, temporaries of
    dead writers) and the directory itself when that leaves it empty. Only ever runs under the
    archive's lock, so an unlisted part cannot belong to a writer still at work."""
    pdir = parts_dir(path)
    keep = set(listed)
    try:
        entries = list(pdir.iterdir())
    except OSError:
        return
    for p in entries:
        pid = F.temp_owner(p.name)
        if pid is not None:
            if pid != os.getpid() and not F.pid_alive(pid):
                F.unlink_quietly(p)
        elif L.PART_NAME.fullmatch(p.name) and p.name not in keep:
            F.unlink_quietly(p)
            log.info("removed unlisted part %s", p)
    if remove_empty:
        with contextlib.suppress(OSError):
            pdir.rmdir()  # only when empty


def _commit(
    path: Path,
    adds: list[_Add],
    *,
    overwrite: bool = False,
    drop: Iterable[str] = (),
    replace_all: bool = False,
) -> list[PartInfo]:
    """The one write transaction: add (or replace) scans, drop scans, under the archive's lock."""
    names = [a.name for a in adds]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"scan name(s) {dup} given more than once; give each scan a unique name")
    check_writable_dir(path, "archive")
    drop = set(drop)
    with F.lock(path):
        F.remove_stale_temps(path)
        rows, created = _current(path)
        F.check_plain_dir(parts_dir(path))  # never a link followed, nor a mount point emptied
        if replace_all:
            rows = []
        clash = sorted({r.name for r in rows} & set(names))
        if clash and not overwrite:
            raise ArchiveError(
                f"archive {path} already holds scan(s) {clash}; pass --overwrite "
                "(overwrite=True) to replace them or choose another --name"
            )
        listed_before = {r.part for r in rows}
        rows = [r for r in rows if r.name not in names and r.name not in drop]
        infos: list[PartInfo] = []
        if not rows and len(adds) == 1:
            # one scan: one self-contained file, written beside the archive and renamed onto it
            infos.append(adds[0].write(path))
            final: set[str] = set()
        else:
            pdir = parts_dir(path)
            pdir.mkdir(exist_ok=True)
            _collect(path, listed_before, remove_empty=False)
            try:
                if any(not r.part for r in rows):
                    # the scans stored in the archive file itself become one part: a hard link
                    p0 = pdir / L.part_file_name(next(r.name for r in rows if not r.part), _token())
                    _link_or_copy(path, p0)
                    size = p0.stat().st_size
                    rows = [r if r.part else replace(r, part=p0.name, part_bytes=size) for r in rows]
                for a in adds:
                    info = a.write(pdir / L.part_file_name(a.name, _token()))
                    infos.append(info)
                    rows.append(
                        IndexRow(info.name, info.n_points, info.bounds_min, info.bounds_max,
                                 info.path.name, info.nbytes)
                    )
                _write_index_file(path, rows, created)
            except BaseException:
                _collect(path, listed_before)  # the old index is still the archive
                raise
            final = {r.part for r in rows}
        _collect(path, final)
    log.info("wrote %s (%d new scan(s))", path, len(adds))
    return infos


def _token() -> str:
    return secrets.token_hex(8)


# ---------------------------------------------------------------------------------------------
# public entry points


def register_parts(
    path: str | os.PathLike[str],
    parts: Iterable[str | os.PathLike[str] | PartInfo],
    *,
    overwrite: bool = False,
) -> list[str]:
    """Add finished part files (each written by a :class:`ScanWriter`, holding one scan) to the
    archive at ``path``, atomically; returns the scan names added.

    O(new data): each part is hard-linked into ``NAME.h5.scans/`` (copied when the file system
    cannot link), then one new index replaces the old. The archive is created when missing (with a
    single part it is that part: one self-contained file). A scan whose name is already in the
    archive is an error unless ``overwrite``. The caller's files stay where they are: delete them
    once this returns (a part registered twice is simply linked again); never change a registered
    file in place. A ``kill -9`` at any moment leaves the previous archive complete."""
    path = Path(path)
    adds = []
    for part in parts:
        src = Path(part.path if isinstance(part, PartInfo) else part)
        info = _part_info(src)

        def write(dst: Path, src: Path = src, info: PartInfo = info) -> PartInfo:
            if dst == path:
                tmp = F.tmp_name(path)
                try:
                    _link_or_copy(src, tmp)
                    F.publish(tmp, path)
                except BaseException:
                    F.unlink_quietly(tmp)
                    raise
            else:
                _link_or_copy(src, dst)
            return replace(info, path=dst)

        adds.append(_Add(info.name, write))
    _commit(path, adds, overwrite=overwrite)
    return [a.name for a in adds]


def _part_info(src: Path) -> PartInfo:
    """Name, size and bounds of the one scan in the part file ``src`` (checked to be one)."""
    from .reader import open_archive

    with open_archive(src) as arc:
        rows = arc.rows
        if len(rows) != 1 or rows[0].part:
            raise ArchiveError(
                f"{src} is not a part file: it must hold exactly one scan stored in it (it holds "
                f"{len(rows)}{' in parts' if rows and rows[0].part else ''}); write parts with "
                "ScanWriter"
            )
        view = arc.scan(rows[0].name)
        # opening it checked the part: nothing stored outside it, one row per point
        return PartInfo(
            path=src,
            name=view.name,
            n_points=view.n_points,
            n_ordered=view.n_ordered,
            bounds_min=tuple(float(x) for x in view.bounds[0]),  # type: ignore[arg-type]
            bounds_max=tuple(float(x) for x in view.bounds[1]),  # type: ignore[arg-type]
            nbytes=src.stat().st_size,
        )


def update_archive(
    path: str | os.PathLike[str],
    records: list[ScanRecord] | None = None,
    *,
    overwrite: bool = False,
    drop: Any = (),
) -> Path:
    """Add ``records`` to the archive at ``path`` (created if missing), atomically.

    Scans already in the archive are kept, untouched and uncopied, unless a record has the same
    name: that is an error unless ``overwrite``, which replaces it. Scans named in ``drop`` are
    removed from the archive."""
    path = Path(path)
    records = list(records or [])
    for rec in records:
        _validate_record(rec)
    adds = [_Add(rec.scan.name, functools.partial(_write_to, rec)) for rec in records]
    _commit(path, adds, overwrite=overwrite, drop=drop)
    return path


def _write_to(rec: ScanRecord, dst: Path) -> PartInfo:
    return write_record(dst, rec)


def write_archive(path: str | os.PathLike[str], records: list[ScanRecord]) -> Path:
    """Create (or replace) the archive at ``path`` holding exactly ``records``, atomically."""
    path = Path(path)
    for rec in records:
        _validate_record(rec)
    adds = [_Add(rec.scan.name, functools.partial(_write_to, rec)) for rec in records]
    _commit(path, adds, overwrite=True, replace_all=True)
    return path


def _rewrite(
    path: str | os.PathLike[str],
    scan: str,
    importance: Mapping[str, tuple[Any, Mapping[str, Any] | None]] | None = None,
    orderings: Mapping[str, tuple[Ordering, Mapping[str, Any] | None]] | None = None,
) -> None:
    """Replace ``scan`` by a copy with extra importance maps / orderings (given in input order)."""
    from .reader import open_archive

    path = Path(path)
    check_writable_dir(path, "archive")
    for name in importance or {}:
        L.check_name(name, "importance map name")
    for name in orderings or {}:
        L.check_name(name, "ordering name")

    def write(dst: Path) -> PartInfo:
        with open_archive(path) as arc:  # under the archive's lock (called by _commit)
            view = arc.scan(scan)  # ScanNotFoundError naming the scans it holds
            n = view.n_points
            src = view.source_index
            imp = {}
            for name, (values, params) in (importance or {}).items():
                arr = np.asarray(values)
                if arr.shape != (n,) or not (
                    np.issubdtype(arr.dtype, np.number) or arr.dtype == bool
                ):
                    raise InputError(
                        f"importance map {name!r} must hold one number per point, shape ({n},), "
                        f"got {arr.shape}"
                    )
                imp[name] = (arr.astype(np.float32)[src], params)
            ords = {}
            for name, (ordg, params) in (orderings or {}).items():
                if ordg.n_points != n:
                    raise InputError(
                        f"ordering {name!r} is for {ordg.n_points} points but the scan has {n}"
                    )
                meta = {"voxel_size": ordg.voxel_size, "band_radius": ordg.band_radius,
                        "engine_stats": ordg.stats, **dict(params or {})}
                positions = _inverse(src)[np.asarray(ordg.order, dtype=np.int64)]
                ords[name] = (positions, ordg.radius, ordg.parent, meta)
            return copy_scan(view, dst, importance=imp, orderings=ords)

    if not Path(path).exists():
        raise ScanNotFoundError(f"archive {path} does not exist; build it first")
    _commit(path, [_Add(scan, write)], overwrite=True)


def add_importance(
    path: str | os.PathLike[str],
    scan: str,
    name: str,
    values: Any,
    params: Mapping[str, Any] | None = None,
) -> None:
    """Add (or replace) importance map ``name`` of ``scan``; ``values`` in input order. Atomic;
    rewrites only that scan."""
    _rewrite(path, scan, importance={name: (values, params)})


def add_ordering(
    path: str | os.PathLike[str],
    scan: str,
    name: str,
    ordering: Ordering,
    params: Mapping[str, Any] | None = None,
) -> None:
    """Add (or replace) an extra ordering of ``scan`` (input indices). Atomic; rewrites only that
    scan."""
    _rewrite(path, scan, orderings={name: (ordering, params)})

