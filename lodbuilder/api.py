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
    name: str | None = None, manifest: str | os.PathLike[str] | None = None,
    workers: int | None = None, scheduler: str | None = None, dask_local: int | None = None,
    voxel_size: float | None = None, band_radius: float | None = None, seeds: Any = None,
    size: int | None = None, rho: float | None = None, force: bool = False, overwrite: bool = False,
    max_memory: Any = None, joint: bool | str = False, seam_spacing: float | None = None,
    seam_rounds: bool = False, crs: str | None = None, crs_override: bool = False, to_crs: str | None = None,
    wait: float | None = None, work_dir: str | os.PathLike[str] | None = None, options: BuildOptions | None = None,
    raise_on_failure: bool | None = None, progress: ProgressCallback = None, on_status: Any = None,
    _tile_points: int | None = None, _tile_passes: int | None = None,
    **features: Any,
) -> BuildResult:
    """Order every scan of ``inputs`` and add it to ``archive`` (created when missing).

    ``inputs``: a scan file, a :class:`lodbuilder.Scan`, or a list of files, directories (scanned
    recursively), glob patterns, manifests (``*.conf``, ``*.manifest``, ``*.lst``: files with poses)
    and Scans; ``manifest`` adds one more manifest. A single scan is a collection of one: every
    input takes the same path. Scans run in this process when there is one (or they are
    in-memory Scans), else on a process pool of ``workers`` (default: one per core), or on Dask
    (``scheduler`` address, or ``dask_local=N`` workers of a LocalCluster). ``work_dir``: where a tiled
    build keeps its work files, a directory or an object store's fsspec URL (``s3://BUCKET/PREFIX``:
    workers need no file system shared with this process; :mod:`lodbuilder.build.tiled.store`);
    default: a hidden directory beside the archive.

    Names: the file stem made safe and unique (``name`` names a single scan). A scan already in the
    archive with the same source, pose and parameters is skipped (``force`` rebuilds it); a scan of
    the same name built from other contents is refused unless ``overwrite``. Adding to an archive
    is atomic: the scans already in it are untouched whatever happens, and a killed build resumes
    where it stopped. One build (or other writer) of an archive runs at a time: while another
    process writes ``archive``, this build waits for it (with a warning), for at most ``wait``
    seconds (default: until it finishes; 0: not at all), then raises ArchiveBusyError.

    What each scan stores is decided by the option keywords ``voxel_size``, ``band_radius``,
    ``seeds``, ``size``, ``rho``, ``max_memory``, ``seam_spacing``, ``seam_rounds``, ``crs``,
    ``crs_override``, ``to_crs`` and the feature options (``importance``, ``adaptive``,
    ``density_floor``, ``outlier_threshold``, ...),
    documented once in :class:`~lodbuilder.build.options.BuildOptions`; or by ``options``, a
    BuildOptions made beforehand (giving both is refused). Scans larger than ``max_memory`` take
    the tiled path (:mod:`lodbuilder.build.tiled`). ``joint=True`` (or a scan name) orders every
    input scan, posed, as one surface: one scan whose points keep ``scan_id`` and ``scan_point``.

    Returns a :class:`BuildResult` (one :class:`~lodbuilder.collection.ScanStatus` per scan: name,
    status, points, seconds, encoding, method). Failures: with one scan its error is raised
    (nothing is written); with several, failed scans are reported in the result and the others
    are built (``raise_on_failure=True`` raises a BuildError naming them after the others are in,
    ``False`` never raises).
    """
    from .build.runner import build

    given = {"voxel_size": voxel_size, "band_radius": band_radius, "seeds": seeds, "size": size, "rho": rho,
             "max_memory": max_memory, "seam_spacing": seam_spacing,
             "seam_rounds": None if seam_rounds is False else seam_rounds, "crs": crs, "to_crs": to_crs,
             "tile_points": _tile_points, "tile_passes": _tile_passes,
             **{k: v for k, v in features.items() if v is not None}}
    options = _one_options(options, given, crs_override)
    return build(inputs, archive, options, name=name, manifest=manifest, workers=workers, scheduler=scheduler,
                 dask_local=dask_local, force=force, overwrite=overwrite, joint=joint, wait=wait, work_dir=work_dir,
                 raise_on_failure=raise_on_failure, progress=progress, on_status=on_status)


def _one_options(options: BuildOptions | None, given: dict[str, Any], crs_override: bool) -> BuildOptions:
    """``options``, or the BuildOptions of the keywords ``given``; refused when both are given."""
    if options is None:
        return BuildOptions.make(crs_override=crs_override, **given)
    if any(v is not None for v in given.values()) or crs_override:
        named = ", ".join(k for k, v in given.items() if v is not None) or "crs_override"
        raise InputError(f"build options given twice: options= and {named}; put them all in options= "
                         "(BuildOptions.make(...)) or pass keywords only")
    return options


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
