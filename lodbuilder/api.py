"""The public build/open functions (re-exported lazily from ``lodbuilder``).

import lodbuilder
lodbuilder.build_archive("bun_zipper_res2.ply", "bunny.h5")
with lodbuilder.open_archive("bunny.h5") as arc:
    level = arc.scan().level(rho=0.005)       # Level(points, attributes, source_index, ...)
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from ._validate import strict_keywords
from .archive.reader import Archive, open_archive
from .errors import InputError
from .progress import ProgressCallback, report

log = logging.getLogger(__name__)

__all__ = ["build_archive", "open_archive", "Archive", "build_record"]


def _provenance(source: Path | None, reader: str) -> dict[str, Any]:
    from .io import file_sha256

    if source is None:
        return {"source_name": None, "source_size": None, "source_sha256": None, "reader": reader}
    return {
        "source_name": source.name,
        "source_size": source.stat().st_size,
        "source_sha256": file_sha256(source),
        "reader": reader,
    }


def load_scan(
    scan_or_path: Any,
    name: str | None = None,
    progress: ProgressCallback = None,
    crs: str | None = None,
    crs_override: bool = False,
):
    """``(scan, source_path_or_None)`` from a path (read by suffix) or a Scan; ``crs`` assigns a
    CRS (see :func:`lodbuilder.io.crs.assign_crs`)."""
    from .archive.layout import check_name
    from .io import Scan, read_scan

    if isinstance(scan_or_path, Scan):
        scan = scan_or_path
        if name is not None:
            scan.name = name
        if crs is not None:
            from .io.crs import assign_crs

            assign_crs(scan.metadata, crs, override=crs_override, what=f"scan {scan.name!r}")
        source = Path(scan.source) if scan.source and Path(scan.source).is_file() else None
    elif isinstance(scan_or_path, (str, os.PathLike)):
        report(progress, "read", 0, 1)
        scan = read_scan(scan_or_path, name=name, crs=crs, crs_override=crs_override)
        source = Path(scan_or_path)
        report(progress, "read", 1, 1)
    else:
        raise InputError(
            f"build input must be a file path or a lodbuilder.Scan, got {type(scan_or_path).__name__}"
        )
    check_name(scan.name)
    return scan, source


def _feature_keywords() -> list[str]:
    import inspect

    from .sampling.adaptive import feature_build

    return [k for k in inspect.signature(feature_build).parameters if k != "scan"]


@strict_keywords(extra=_feature_keywords)
def build_record(
    scan_or_path: Any,
    *,
    name: str | None = None,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    seeds: Any = None,
    progress: ProgressCallback = None,
    _loaded: Any = None,
    **features: Any,
):
    """Read (if a path), order with FastFPS and return the :class:`ScanRecord` to store.

    ``features``: ``importance``, ``adaptive``, ``density_floor``, ``outlier_threshold``,
    ``importance_k``, ``combine`` of :func:`lodbuilder.sampling.adaptive.feature_build`
    (importance maps, outliers and the extra ``weighted``/``floor`` orderings).
    """
    from .archive.writer import ScanRecord
    from .sampling.fastfps import fastfps

    scan, source = _loaded or load_scan(scan_or_path, name, progress)
    features = {k: v for k, v in features.items() if v is not None}
    fb = None
    if features:
        from .sampling.adaptive import feature_build

        fb = feature_build(
            scan,
            seeds=seeds,
            voxel_size=voxel_size,
            band_radius=band_radius,
            progress=progress,
            **features,
        )
        scan, ordering = fb.scan, fb.ordering
    else:
        ordering = fastfps(
            scan.points,
            voxel_size=voxel_size,
            band_radius=band_radius,
            seeds=seeds,
            progress=progress,
        )
    build = {
        "voxel_size_requested": voxel_size,
        "band_radius_requested": band_radius,
        "seeds_given": seeds is not None,
    }
    if fb is not None:
        build.update(fb.build)
    return ScanRecord(
        scan=scan,
        ordering=ordering,
        build=build,
        provenance=_provenance(source, scan.reader),
        importance=fb.importance if fb else {},
        orderings=fb.orderings if fb else {},
    )


def build_archive(
    inputs: Any,
    archive: str | os.PathLike[str],
    *,
    name: str | None = None,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    seeds: Any = None,
    overwrite: bool = False,
    progress: ProgressCallback = None,
    crs: str | None = None,
    crs_override: bool = False,
    **features: Any,
) -> Path:
    """Order one scan (a path or a :class:`lodbuilder.Scan`) and add it to ``archive``.

    The archive is created when missing; otherwise the scan is added to it atomically (the scans
    already there are untouched whatever happens). A scan whose name is already in the archive is
    an error unless ``overwrite``. Returns the archive path.

    Feature sensitivity (see :func:`lodbuilder.sampling.adaptive.feature_build`):
    ``importance="curvature,colour"`` stores importance maps, ``adaptive=A`` adds the ``weighted``
    ordering, ``density_floor=RHO0`` the ``floor`` ordering, ``outlier_threshold=T`` leaves points
    with a noise score above T out of every ordering (kept in the archive, flagged ``outlier``).
    """
    from .archive.reader import check_archive_file
    from .archive.writer import check_writable_dir, update_archive

    archive = Path(archive)
    check_writable_dir(archive, "archive")
    if archive.exists():
        check_archive_file(archive)  # fail before the expensive ordering
    if isinstance(inputs, (str, os.PathLike)):
        src = Path(inputs)
        if src.exists() and archive.exists() and src.resolve() == archive.resolve():
            raise InputError(
                f"input {src} and archive {archive} are the same file; choose another -o"
            )
    loaded = load_scan(inputs, name, progress, crs, crs_override)
    scan_name = loaded[0].name
    if archive.exists() and not overwrite:
        with open_archive(archive) as arc:
            if scan_name in arc.scans:
                from .errors import ArchiveError

                raise ArchiveError(
                    f"archive {archive} already holds scan {scan_name!r}; pass --overwrite "
                    "(overwrite=True) to replace it or choose another --name"
                )
    rec = build_record(
        inputs,
        voxel_size=voxel_size,
        band_radius=band_radius,
        seeds=seeds,
        progress=progress,
        _loaded=loaded,
        **features,
    )
    report(progress, "write", 0, 1)
    update_archive(archive, [rec], overwrite=overwrite)
    report(progress, "write", 1, 1)
    return archive
