"""Order an in-memory scan into the record the archive writer stores."""

from __future__ import annotations

from typing import Any

from ..progress import ProgressCallback
from .options import BuildOptions


def build_record(scan: Any, options: BuildOptions, progress: ProgressCallback = None) -> Any:
    """Order the in-memory :class:`~lodbuilder.io.Scan` ``scan`` with FastFPS under ``options`` and
    return the :class:`~lodbuilder.archive.writer.ScanRecord` to store (no provenance: the caller
    adds it).

    ``options.size``/``options.rho`` stop the ordering early (``size`` larger than the scan means
    the whole scan); feature options (:func:`lodbuilder.sampling.adaptive.feature_build`: importance
    maps, outliers and the extra ``weighted``/``floor`` orderings) need a full ordering."""
    from ..archive.writer import ScanRecord
    from ..sampling.fastfps import fastfps

    seeds = None if options.seeds is None else list(options.seeds)
    fb = None
    if options.features:
        from ..sampling.adaptive import feature_build

        fb = feature_build(scan, seeds=seeds, voxel_size=options.voxel_size, band_radius=options.band_radius,
                           progress=progress, **options.feature_kwargs)
        scan, ordering = fb.scan, fb.ordering
    else:
        size = None if options.size is None else min(options.size, len(scan))
        ordering = fastfps(scan.points, voxel_size=options.voxel_size, band_radius=options.band_radius,
                           seeds=seeds, size=size, rho=options.rho, progress=progress)
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
