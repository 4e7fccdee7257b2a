"""Atomic archive writes.

Every change produces a complete new file next to the archive (a hidden temporary named
``.<archive>.tmp-<pid>-<random>``), flushed and fsync'ed, then moved over the archive with
``os.replace``. A ``kill -9`` at any moment therefore leaves the previous archive intact, and
readers only ever see a complete archive. Changes to one archive are serialised by an advisory
lock on ``.<archive>.lock``. When an archive is changed, the scans already in it are copied into the
new file unchanged (HDF5 object copy: raw chunks, checksums and filters kept).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import os
import secrets
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ArchiveError, InputError
from ..io.base import Scan
from ..sampling.ordering import Ordering
from . import layout as L
from . import safety

log = logging.getLogger(__name__)


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


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
# temp files, locks


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temps(path: Path) -> list[Path]:
    """Delete temporaries of ``path`` left by writers that were killed (their pid is gone)."""
    removed: list[Path] = []
    prefix = f".{path.name}.tmp-"
    try:
        entries = list(path.parent.iterdir())
    except OSError:
        return removed
    for p in entries:
        if not p.name.startswith(prefix):
            continue
        try:
            pid = int(p.name[len(prefix) :].split("-")[0])
        except ValueError:
            continue
        if pid != os.getpid() and not _pid_alive(pid):
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
                log.info("removed stale temporary %s", p)
    return removed


@contextlib.contextmanager
def _lock(path: Path) -> Iterator[None]:
    import fcntl

    lock_path = path.with_name(f".{path.name}.lock")
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock; the lock file stays (removing it would race)


def check_writable_dir(path: Path, what: str = "output") -> None:
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise ArchiveError(f"{what} directory {parent} does not exist; create it first")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ArchiveError(f"{what} directory {parent} is not writable; choose another output path")


def _fsync_dir(directory: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success fsync it and move it onto ``path``.

    On any error (or interruption) the temporary is removed and ``path`` is left as it was."""
    path = Path(path)
    check_writable_dir(path)
    tmp = _tmp_name(path)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


# ---------------------------------------------------------------------------------------------
# writing one scan into an open file


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


def _stored_permutation(ordg: Ordering) -> np.ndarray:
    """Input index of each stored position: the ordering, then unordered points by input index."""
    n = ordg.n_points
    order = np.asarray(ordg.order, dtype=np.int64)
    if order.shape[0] == n:
        return order
    seen = np.zeros(n, dtype=bool)
    seen[order] = True
    return np.concatenate([order, np.flatnonzero(~seen)])


def write_scan(root: Any, rec: ScanRecord) -> None:
    """Write ``rec`` as ``/scans/<name>`` of the open, writable h5py file ``root``."""
    _validate_record(rec)
    scan, ordg = rec.scan, rec.ordering
    n, k = len(scan), len(ordg)
    perm = _stored_permutation(ordg)
    radius = np.zeros(n, dtype=np.float64)
    radius[:k] = ordg.radius
    parent = np.full(n, -1, dtype=np.int64)
    parent[:k] = ordg.parent

    g = root.require_group(L.G_SCANS).create_group(scan.name)
    pts = np.asarray(scan.points, dtype=np.float64)[perm]
    stored, enc, offset, scale = L.encode_points(pts, scan.metadata)
    p_attrs = {} if offset is None else {L.P_OFFSET: offset, L.P_SCALE: scale}
    L.create_dataset(g, L.D_POINTS, stored, p_attrs)
    L.create_dataset(g, L.D_SOURCE_INDEX, perm)
    L.create_dataset(g, L.D_RADIUS, radius)
    L.create_dataset(g, L.D_PARENT, parent)
    L.create_dataset(g, L.D_RADIUS_INDEX, radius[:: L.RADIUS_INDEX_STEP].copy())
    L.create_dataset(g, L.D_SEEDS, np.asarray(ordg.seeds, dtype=np.int64).reshape(-1))
    ga = g.create_group(L.G_ATTRIBUTES)
    for key, arr in scan.attributes.items():
        L.create_dataset(ga, key, np.asarray(arr)[perm])
    g.create_group(L.G_IMPORTANCE)
    g.create_group(L.G_ORDERINGS)
    for key, (values, params) in rec.importance.items():
        write_importance(g, key, values, params)
    for key, (extra, params) in rec.orderings.items():
        write_ordering(g, key, extra, params)

    build = {
        "voxel_size": ordg.voxel_size,
        "band_radius": ordg.band_radius,
        "n_seeds": int(np.asarray(ordg.seeds).size),
        "engine_stats": ordg.stats,
    }
    build.update(rec.build)
    prov = {"lodbuilder_version": __version__, "created_utc": utc_now(), "reader": scan.reader}
    prov.update(rec.provenance)
    g.attrs[L.S_N_POINTS] = np.int64(n)
    g.attrs[L.S_N_ORDERED] = np.int64(k)
    g.attrs[L.S_ENCODING] = enc
    g.attrs[L.S_BOUNDS_MIN] = pts.min(axis=0)
    g.attrs[L.S_BOUNDS_MAX] = pts.max(axis=0)
    g.attrs[L.S_RADIUS_STEP] = np.int64(L.RADIUS_INDEX_STEP)
    g.attrs[L.S_BUILD] = L.to_json(build)
    g.attrs[L.S_PROVENANCE] = L.to_json(prov)
    g.attrs[L.S_FORMAT_METADATA] = L.to_json(scan.metadata)


def _inverse(g: Any) -> np.ndarray:
    src = g[L.D_SOURCE_INDEX][:]
    inv = np.empty_like(src)
    inv[src] = np.arange(src.shape[0], dtype=np.int64)
    return inv


def write_importance(g: Any, name: str, values: Any, params: Mapping[str, Any] | None) -> None:
    """Store an importance map given per *input* point (input order) into scan group ``g``."""
    L.check_name(name, "importance map name")
    n = int(g.attrs[L.S_N_POINTS]) if L.S_N_POINTS in g.attrs else g[L.D_SOURCE_INDEX].shape[0]
    arr = np.asarray(values)
    if arr.shape != (n,) or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise InputError(
            f"importance map {name!r} must hold one number per point, shape ({n},), got {arr.shape}"
        )
    stored = arr.astype(np.float32)[g[L.D_SOURCE_INDEX][:]]
    grp = g.require_group(L.G_IMPORTANCE)
    if name in grp:
        del grp[name]
    L.create_dataset(grp, name, stored, {L.M_PARAMETERS: L.to_json(dict(params or {}))})


def write_ordering(g: Any, name: str, ordg: Ordering, params: Mapping[str, Any] | None) -> None:
    """Store an extra ordering (input indices) as positions into the stored points of ``g``."""
    L.check_name(name, "ordering name")
    n = g[L.D_SOURCE_INDEX].shape[0]
    if ordg.n_points != n:
        raise InputError(f"ordering {name!r} is for {ordg.n_points} points but the scan has {n}")
    positions = _inverse(g)[np.asarray(ordg.order, dtype=np.int64)]
    grp = g.require_group(L.G_ORDERINGS)
    if name in grp:
        del grp[name]
    og = grp.create_group(name)
    L.create_dataset(og, L.D_ORDER, positions)
    L.create_dataset(og, L.D_RADIUS, np.asarray(ordg.radius, dtype=np.float64))
    L.create_dataset(og, L.D_PARENT, np.asarray(ordg.parent, dtype=np.int64))
    meta = {
        "voxel_size": ordg.voxel_size,
        "band_radius": ordg.band_radius,
        "engine_stats": ordg.stats,
    }
    meta.update(dict(params or {}))
    og.attrs[L.M_PARAMETERS] = L.to_json(meta)
    og.attrs[L.S_N_ORDERED] = np.int64(len(ordg))


def _write_index(root: Any) -> None:
    scans = root.require_group(L.G_SCANS)
    names = sorted(scans)
    if L.G_INDEX in root:
        del root[L.G_INDEX]
    ig = root.create_group(L.G_INDEX)
    enc = [s.encode("utf-8") for s in names]
    width = max([len(e) for e in enc] + [1])
    L.create_dataset(ig, L.I_NAME, np.array(enc, dtype=f"S{width}"))
    L.create_dataset(
        ig,
        L.I_N_POINTS,
        np.array([int(scans[s].attrs[L.S_N_POINTS]) for s in names], dtype=np.int64),
    )
    L.create_dataset(
        ig,
        L.I_BOUNDS_MIN,
        np.array([scans[s].attrs[L.S_BOUNDS_MIN] for s in names], dtype=np.float64).reshape(-1, 3),
    )
    L.create_dataset(
        ig,
        L.I_BOUNDS_MAX,
        np.array([scans[s].attrs[L.S_BOUNDS_MAX] for s in names], dtype=np.float64).reshape(-1, 3),
    )
    ig.attrs[L.A_N_SCANS] = np.int64(len(names))


def _open_new(tmp: Path, created: str | None = None):
    import h5py

    f = h5py.File(tmp, "w", libver=L.LIBVER)
    f.attrs[L.A_FORMAT] = L.FORMAT
    f.attrs[L.A_SCHEMA_VERSION] = np.int64(L.SCHEMA_VERSION)
    f.attrs[L.A_VERSION] = __version__
    f.attrs[L.A_CREATED] = created or utc_now()
    f.attrs[L.A_MODIFIED] = utc_now()
    f.create_group(L.G_SCANS)
    return f


# ---------------------------------------------------------------------------------------------
# public entry points


def update_archive(
    path: str | os.PathLike[str],
    records: list[ScanRecord] | None = None,
    *,
    overwrite: bool = False,
    edit: Any = None,
    drop: Any = (),
) -> Path:
    """Add ``records`` to the archive at ``path`` (created if missing), atomically.

    Scans already in the archive are kept unless a record has the same name: that is an error
    unless ``overwrite``, which replaces it. ``edit(root)``, if given, is called on the new file
    before it is moved into place (to add importance maps or orderings to existing scans).
    Scans named in ``drop`` are not copied into the new file (``edit`` may add them back anew).
    """
    import h5py

    from .reader import check_archive_file

    path = Path(path)
    records = list(records or [])
    names = [r.scan.name for r in records]
    for rec in records:
        _validate_record(rec)
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise InputError(
            f"scan name(s) {sorted(dup)} given more than once; give each scan a unique name"
        )
    check_writable_dir(path, "archive")
    with _lock(path):
        remove_stale_temps(path)
        old = None
        if path.exists():
            old = check_archive_file(path)  # NotAnArchiveError / SchemaVersionError
        with atomic_output(path) as tmp:
            created = None
            keep: list[str] = []
            if old is not None:
                with safety.open_h5(path) as src:  # heaps checked as HDF5 loads them
                    created = src.attrs.get(L.A_CREATED)
                    created = created.decode() if isinstance(created, bytes) else created
                    existing = list(src[L.G_SCANS]) if L.G_SCANS in src else []
                    clash = sorted(set(existing) & set(names))
                    if clash and not overwrite:
                        raise ArchiveError(
                            f"archive {path} already holds scan(s) {clash}; pass --overwrite "
                            "(overwrite=True) to replace them or choose another --name"
                        )
                    keep = [s for s in existing if s not in names and s not in set(drop)]
                    with _open_new(tmp, created) as dst:
                        for s in keep:
                            src.copy(src[L.G_SCANS][s], dst[L.G_SCANS], name=s)
                        for key in src:  # groups other issues add at the root
                            if key not in (L.G_SCANS, L.G_INDEX):
                                src.copy(src[key], dst, name=key)
                        for key, value in src.attrs.items():
                            if key not in (L.A_MODIFIED, L.A_VERSION):
                                dst.attrs[key] = value
            mode = "a" if old is not None else "w"
            f = h5py.File(tmp, "r+", libver=L.LIBVER) if mode == "a" else _open_new(tmp)
            with f:
                for rec in records:
                    write_scan(f, rec)
                if edit is not None:
                    edit(f)
                _write_index(f)
                f.attrs[L.A_MODIFIED] = utc_now()
                f.flush()
    log.info("wrote %s (%d new scan(s))", path, len(records))
    return path


def write_archive(path: str | os.PathLike[str], records: list[ScanRecord]) -> Path:
    """Create (or replace) the archive at ``path`` holding exactly ``records``, atomically."""
    path = Path(path)
    check_writable_dir(path, "archive")
    with _lock(path):
        remove_stale_temps(path)
        with atomic_output(path) as tmp:
            with _open_new(tmp) as f:
                for rec in records:
                    write_scan(f, rec)
                _write_index(f)
    return path


def add_importance(
    path: str | os.PathLike[str],
    scan: str,
    name: str,
    values: Any,
    params: Mapping[str, Any] | None = None,
) -> None:
    """Add (or replace) importance map ``name`` of ``scan``; ``values`` in input order. Atomic."""

    def edit(root: Any) -> None:
        write_importance(_scan_group(root, scan, path), name, values, params)

    update_archive(path, edit=edit)


def add_ordering(
    path: str | os.PathLike[str],
    scan: str,
    name: str,
    ordering: Ordering,
    params: Mapping[str, Any] | None = None,
) -> None:
    """Add (or replace) an extra ordering of ``scan`` (input indices). Atomic."""

    def edit(root: Any) -> None:
        write_ordering(_scan_group(root, scan, path), name, ordering, params)

    update_archive(path, edit=edit)


def _scan_group(root: Any, scan: str, path: Any) -> Any:
    from ..errors import ScanNotFoundError

    scans = root[L.G_SCANS]
    if scan not in scans:
        raise ScanNotFoundError(f"archive {path} has no scan {scan!r}; it holds {sorted(scans)}")
    return scans[scan]
