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
from .build.options import FEATURE_OPTIONS, BuildOptions
from .build.result import BuildResult
from .errors import InputError
from .progress import ProgressCallback

log = logging.getLogger(__name__)

__all__ = ["build_archive", "build_collection", "open_archive", "Archive", "BuildOptions", "BuildResult",
           "build_record"]

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
    The keywords are those of :class:`~lodbuilder.build.options.BuildOptions`; see
    :func:`lodbuilder.build.record.build_record`."""
    from .build.record import build_record as record

    options = BuildOptions.make(voxel_size=voxel_size, band_radius=band_radius, seeds=seeds, size=size, rho=rho,
                                **features)
    return record(scan, options, progress=progress)


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
    options: BuildOptions | None = None,
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
    where it stopped.

    Scans larger than the memory budget take the tiled path (:mod:`lodbuilder.build.tiled`):
    ``max_memory`` (bytes, or text like ``"3GB"``; default 60 % of this machine's memory) is the
    budget of the build's whole process tree on this machine (with a remote ``scheduler``: of each
    worker); a scan whose in-memory build would exceed it is read in chunks, cut into tiles ordered
    on the workers and merged. ``seam_spacing`` (0..1, default 0.25) is the seam repair of the merge:
    a point merged from one tile keeps at least this fraction of its merge radius from the earlier
    points of other tiles, so points of different tiles in any level are at least A / (1 + A) times
    the level's radius apart (0.2 at the default, 0.5 at 1, which costs covering at equal size:
    see :data:`lodbuilder.build.tiled.SEAM_SPACING`; 0: no repair). ``joint=True`` (or a scan name) orders every input scan,
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

    ``options``: a :class:`~lodbuilder.build.options.BuildOptions` made beforehand, instead of the
    option keywords (voxel_size, band_radius, seeds, size, rho, max_memory, seam_spacing, crs,
    crs_override and the feature options); giving both is refused.
    """
    from .build.runner import build

    given = {"voxel_size": voxel_size, "band_radius": band_radius, "seeds": seeds, "size": size, "rho": rho,
             "max_memory": max_memory, "seam_spacing": seam_spacing, "crs": crs,
             "tile_points": _tile_points, "tile_passes": _tile_passes,
             **{k: v for k, v in features.items() if v is not None}}
    if options is None:
        options = BuildOptions.make(crs_override=crs_override, **given)
    elif any(v is not None for v in given.values()) or crs_override:
        named = ", ".join(k for k, v in given.items() if v is not None) or "crs_override"
        raise InputError(f"build options given twice: options= and {named}; put them all in options= "
                         "(BuildOptions.make(...)) or pass keywords only")
    return build(inputs, archive, options, name=name, manifest=manifest, workers=workers, scheduler=scheduler,
                 dask_local=dask_local, force=force, overwrite=overwrite, joint=joint,
                 raise_on_failure=raise_on_failure, progress=progress, on_status=on_status)


def _build_keywords() -> list[str]:
    import inspect

    names = [p.name for p in inspect.signature(build_archive).parameters.values()
             if p.kind is inspect.Parameter.KEYWORD_ONLY]
    return names + list(FEATURE_OPTIONS)


@strict_keywords(extra=_build_keywords)
def build_collection(inputs: Any = (), archive: str | os.PathLike[str] = "collection.h5", *,
                     raise_on_failure: bool = False, **options: Any) -> BuildResult:
    """:func:`build_archive` that reports failed scans in the result instead of raising (unless
    ``raise_on_failure``: then a BuildError names them after every other scan is merged)."""
    return build_archive(inputs, archive, raise_on_failure=raise_on_failure, **options)
