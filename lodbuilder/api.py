"""The public build/open functions (re-exported lazily from ``lodbuilder``).

import lodbuilder
res = lodbuilder.build_archive("bun_zipper_res2.ply", "bunny.h5")   # BuildResult: what was built
with lodbuilder.open_archive("bunny.h5") as arc:
    level = arc.scan().level(rho=0.005)       # Level(points, attributes, source_index, ...)
"""

from __future__ import annotations

import logging
import os
from typing import Any

from ._validate import strict_keywords
from .archive.reader import Archive, open_archive
from .collection.result import BuildResult
from .progress import ProgressCallback

log = logging.getLogger(__name__)

__all__ = ["build_archive", "open_archive", "Archive", "BuildResult", "build_record"]

#: the feature-sensitivity options (see lodbuilder.sampling.adaptive.feature_build)
FEATURE_OPTIONS = ("importance", "adaptive", "density_floor", "outlier_threshold", "importance_k", "combine")


@strict_keywords(extra=FEATURE_OPTIONS)
def build_record(
    scan: Any,
    *,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    seeds: Any = None,
    size: int | None = None,
    rho: float | None = None,
    progress: ProgressCallback = None,
    **features: Any,
):
    """Order an in-memory :class:`~lodbuilder.io.Scan` with FastFPS and return the
    :class:`~lodbuilder.archive.writer.ScanRecord` to store (no provenance: the caller adds it).

    ``size``/``rho`` stop the ordering early (at most ``size`` points; ``size`` larger than the scan
    means the whole scan). ``features``: ``importance``, ``adaptive``, ``density_floor``,
    ``outlier_threshold``, ``importance_k``, ``combine`` of
    :func:`lodbuilder.sampling.adaptive.feature_build` (importance maps, outliers and the extra
    ``weighted``/``floor`` orderings); they need a full ordering.
    """
    from .archive.writer import ScanRecord
    from .sampling.fastfps import fastfps

    features = {k: v for k, v in features.items() if v is not None}
    fb = None
    if features:
        from .sampling.adaptive import feature_build

        fb = feature_build(scan, seeds=seeds, voxel_size=voxel_size, band_radius=band_radius, progress=progress,
                           **features)
        scan, ordering = fb.scan, fb.ordering
    else:
        ordering = fastfps(scan.points, voxel_size=voxel_size, band_radius=band_radius, seeds=seeds,
                           size=None if size is None else min(int(size), len(scan)), rho=rho, progress=progress)
    build: dict[str, Any] = {"seeds_given": seeds is not None}
    if fb is not None:
        build.update(fb.build)
    return ScanRecord(
        scan=scan,
        ordering=ordering,
        build=build,
        importance=fb.importance if fb else {},
        orderings=fb.orderings if fb else {},
    )


@strict_keywords(extra=FEATURE_OPTIONS)
def build_archive(
    inputs: Any,
    archive: str | os.PathLike[str],
    *,
    name: str | None = None,
    manifest: str | os.PathLike[str] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    dask_local: int | None = None,
    voxel_size: float | None = None,
    band_radius: float | None = None,
    seeds: Any = None,
    size: int | None = None,
    rho: float | None = None,
    force: bool = False,
    overwrite: bool = False,
    max_memory: Any = None,
    joint: bool | str = False,
    seam_spacing: float | None = None,
    crs: str | None = None,
    crs_override: bool = False,
    wait: float | None = None,
    raise_on_failure: bool | None = None,
    progress: ProgressCallback = None,
    on_status: Any = None,
    _tile_points: int | None = None,
    _tile_passes: int | None = None,
    **features: Any,
) -> BuildResult:
    """Order every scan of ``inputs`` and add it to ``archive`` (created when missing).

    ``inputs``: a scan file, a :class:`lodbuilder.Scan`, or a list of files, directories (scanned
    recursively), glob patterns, manifests (``*.conf``, ``*.manifest``, ``*.lst``: files with poses)
    and Scans; ``manifest`` adds one more manifest. A single scan is a collection of one: every
    input takes the same path. Scans run in this process when there is one (or they are
    in-memory Scans), else on a process pool of ``workers`` (default: one per core), or on Dask
    (``scheduler`` address, or ``dask_local=N`` workers of a LocalCluster).

    Names: the file stem made safe and unique (``name`` names a single scan). A scan already in the
    archive with the same source, pose and parameters is skipped (``force`` rebuilds it); a scan of
    the same name built from other contents is refused unless ``overwrite``. Adding to an archive
    is atomic: the scans already in it are untouched whatever happens, and a killed build resumes
    where it stopped. One build (or other writer) of an archive runs at a time: while another
    process writes ``archive``, this build waits for it (with a warning), for at most ``wait``
    seconds (default: until it finishes; 0: not at all), then raises ArchiveBusyError.

    Scans larger than the memory budget take the tiled path (:mod:`lodbuilder.sampling.tiled`):
    ``max_memory`` (bytes, or text like ``"3GB"``; default 60 % of this machine's memory) is the
    budget of the build's whole process tree on this machine (with a remote ``scheduler``: of each
    worker); a scan whose in-memory build would exceed it is read in chunks, cut into tiles ordered
    on the workers and merged. ``seam_spacing`` (0..1, default 0.25) is the seam repair of the merge:
    a point merged from one tile keeps at least this fraction of its merge radius from the earlier
    points of other tiles, so points of different tiles in any level are at least A / (1 + A) times
    the level's radius apart (0.2 at the default, 0.5 at 1, which costs covering at equal size:
    see :data:`lodbuilder.sampling.tiled.SEAM_ALPHA`; 0: no repair). ``joint=True`` (or a scan name) orders every input scan,
    posed, as one surface: one scan in the archive whose points keep ``scan_id`` and
    ``scan_point`` (their index in their own scan) attributes.

    ``crs`` (EPSG:XXXX, WKT or a file holding WKT) gives every scan without one a coordinate
    reference system; a scan whose file declares another is refused unless ``crs_override``.

    ``size``/``rho`` stop each ordering early; ``seeds`` (one scan only) are must-keep input
    indices. Feature sensitivity (see :func:`lodbuilder.sampling.adaptive.feature_build`):
    ``importance="curvature,colour"`` stores importance maps, ``adaptive=A`` adds the ``weighted``
    ordering, ``density_floor=RHO0`` the ``floor`` ordering, ``outlier_threshold=T`` leaves points
    with a noise score above T out of every ordering (kept in the archive, flagged ``outlier``).

    Returns a :class:`BuildResult` (one :class:`~lodbuilder.collection.ScanStatus` per scan: name,
    status, points, seconds, encoding, method). Failures: with one scan its error is raised
    (nothing is written); with several, failed scans are reported in the result and the others
    are built (``raise_on_failure=True`` raises a BuildError naming them after the others are in,
    ``False`` never raises).
    """
    from .collection.runner import build

    return build(inputs, archive, name=name, manifest=manifest, workers=workers, scheduler=scheduler,
                 dask_local=dask_local, voxel_size=voxel_size, band_radius=band_radius, seeds=seeds, size=size,
                 rho=rho, force=force, overwrite=overwrite, max_memory=max_memory, joint=joint,
                 seam_spacing=seam_spacing, crs=crs, crs_override=crs_override, wait=wait,
                 raise_on_failure=raise_on_failure, progress=progress,
                 on_status=on_status, _tile_points=_tile_points, _tile_passes=_tile_passes, **features)
