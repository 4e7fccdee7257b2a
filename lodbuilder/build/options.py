"""The one build contract: :class:`BuildOptions`, every option that decides what a build stores.

The command line and :func:`lodbuilder.build_archive` make one with :meth:`BuildOptions.make`, which
checks every value once; the in-memory, tiled, joint and collection paths all take it as it is, and
the resume key of every scan hashes :attr:`BuildOptions.key_params` (the same dictionary whatever
path the build takes). How a build runs (workers, Dask, progress, --force) is not an option of what
it stores and stays outside.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

from .._validate import check_positive, strict_keywords, strict_methods
from ..errors import InputError

#: the feature-sensitivity options (see lodbuilder.sampling.adaptive.feature_build)
FEATURE_OPTIONS = ("importance", "adaptive", "density_floor", "outlier_threshold", "importance_k", "combine")


@strict_methods
@dataclass(frozen=True)
class BuildOptions:
    """What a build stores. Make one with :meth:`make` (checked); the fields are read-only.

    ``voxel_size``/``band_radius``: the band's grid (default: from the point spacing, see
    :mod:`lodbuilder.sampling.band`). ``size``/``rho`` stop each ordering early (a partial
    ordering); ``seeds`` (one scan only) are must-keep input indices.

    ``features`` (``(name, value)`` pairs; keywords of :meth:`make`), see
    :func:`lodbuilder.sampling.adaptive.feature_build`: ``importance="curvature,colour"`` stores
    importance maps, ``adaptive=A`` adds the ``weighted`` ordering, ``density_floor=RHO0`` the
    ``floor`` ordering, ``outlier_threshold=T`` leaves points with a noise score above T out of
    every ordering (kept in the archive, flagged ``outlier``); ``importance_k``, ``combine``.

    ``max_memory`` (bytes, or text like ``"3GB"``; None: 60 % of this machine's memory) is the
    budget of the build's whole process tree on this machine (with a remote scheduler: of each
    worker); a scan whose in-memory build would exceed it is read in chunks, cut into tiles ordered
    on the workers and merged. ``seam_spacing`` (0..1, None: 0.25) is the seam repair of that merge:
    a point merged from one tile keeps at least this fraction of its merge radius from the earlier
    points of other tiles, so points of different tiles in any level are at least A / (1 + A) times
    the level's radius apart (0.2 at the default, 0.5 at 1, which costs covering at equal size; 0:
    no repair; see :data:`lodbuilder.build.tiled.SEAM_SPACING`). ``seam_rounds`` (default False)
    orders the tiles in radius rounds in which neighbouring tiles hand each other their points near
    a shared face (:mod:`lodbuilder.build.tiled.rounds`): points of different tiles then keep about
    0.4-0.5 times the level's radius apart in the coarse levels (measured, not a guarantee; the seam
    repair's bound still holds) for about 1.0-1.6 times the ordering's CPU, and each worker holds its
    tiles' ordering states in memory meanwhile (about 260 bytes a point with the halos: a build whose
    workers cannot hold them is refused).

    ``crs`` (EPSG:XXXX, WKT or a file holding WKT; stored as WKT) gives every scan without one a
    coordinate reference system; a scan whose file declares another is refused unless
    ``crs_override``. ``to_crs`` (EPSG:XXXX or WKT; needs pyproj) reprojects every scan to that
    CRS before ordering (the transform is recorded in the scan's provenance); without it, the scans
    of a joint build must share one CRS. ``tile_points``/``tile_passes`` are private knobs of the
    tiled path."""

    voxel_size: float | None = None
    band_radius: float | None = None
    size: int | None = None
    rho: float | None = None
    seeds: tuple[int, ...] | None = None
    features: tuple[tuple[str, Any], ...] = ()
    max_memory: int | None = None
    seam_spacing: float | None = None
    seam_rounds: bool = False
    crs: str | None = None
    crs_override: bool = False
    to_crs: str | None = None
    tile_points: int | None = None
    tile_passes: int | None = None

    @classmethod
    @strict_keywords(extra=FEATURE_OPTIONS)
    def make(cls, *, voxel_size: Any = None, band_radius: Any = None, size: Any = None, rho: Any = None,
             seeds: Any = None, max_memory: Any = None, seam_spacing: Any = None, seam_rounds: Any = False,
             crs: Any = None, crs_override: bool = False, to_crs: Any = None, tile_points: Any = None, tile_passes: Any = None,
             **features: Any) -> BuildOptions:
        """Check every option once and return them frozen (one-line InputError otherwise)."""
        if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 1):
            raise InputError(f"size must be a whole number of points >= 1, got {size!r}")
        feats = {k: v for k, v in features.items() if v is not None}
        unknown = sorted(set(feats) - set(FEATURE_OPTIONS))
        if unknown:
            raise InputError(f"unknown build option(s) {', '.join(map(repr, unknown))}; the feature options are "
                             f"{', '.join(FEATURE_OPTIONS)}")
        rho = check_positive(rho, "rho")
        if seam_rounds is True and tile_passes not in (None, 1):
            raise InputError("seam_rounds order the tiles in one pass of rounds; drop _tile_passes or seam_rounds")
        if feats and (size is not None or rho is not None):
            raise InputError("size/rho (partial orderings) do not combine with feature options; drop one")
        if seeds is not None:
            import numpy as np

            seeds = tuple(np.asarray(seeds).reshape(-1).tolist())
        return cls(
            voxel_size=check_positive(voxel_size, "voxel_size"),
            band_radius=check_positive(band_radius, "band_radius"),
            size=None if size is None else int(size),
            rho=rho,
            seeds=seeds,
            features=tuple(feats.items()),
            max_memory=None if max_memory is None else _memory(max_memory),
            seam_spacing=None if seam_spacing is None else _seam_spacing(seam_spacing),
            seam_rounds=_seam_rounds(seam_rounds),
            crs=None if crs is None else _crs(crs),
            crs_override=bool(crs_override) if crs is not None else False,
            to_crs=None if to_crs is None else _crs(to_crs),
            tile_points=None if tile_points is None else int(tile_points),
            tile_passes=None if tile_passes is None else int(tile_passes),
        )

    @property
    def feature_kwargs(self) -> dict[str, Any]:
        """The feature options as keywords of :func:`lodbuilder.sampling.adaptive.feature_build`."""
        return dict(self.features)

    @property
    def partial(self) -> bool:
        """True when the orderings stop early (``size`` or ``rho``)."""
        return self.size is not None or self.rho is not None

    @property
    def in_memory_only(self) -> bool:
        """True when the options need the in-memory path (partial orderings, seeds, feature options)."""
        return self.partial or bool(self.features) or self.seeds is not None

    @functools.cached_property
    def key_params(self) -> dict[str, Any]:
        """The options that decide a built scan, as the resume key hashes them (computed once;
        only the tiled options that were given enter it, so a default never changes a key)."""
        params: dict[str, Any] = {"voxel_size": self.voxel_size, "band_radius": self.band_radius,
                                  "rho": self.rho, "size": self.size}
        if self.features:
            params["features"] = dict(self.features)
        if self.seeds is not None:
            params["seeds"] = list(self.seeds)
        optional = {"max_memory": self.max_memory, "seam_alpha": self.seam_spacing,
                    "_tile_points": self.tile_points, "_tile_passes": self.tile_passes}
        params.update({k: v for k, v in optional.items() if v is not None})
        if self.seam_rounds:
            params["seam_rounds"] = True
        if self.crs is not None:
            params["crs"] = self.crs
            params["crs_override"] = self.crs_override
        if self.to_crs is not None:
            params["to_crs"] = self.to_crs
        return params


def _memory(value: Any) -> int:
    from .._resources import parse_bytes

    return parse_bytes(value, "max_memory")


def _seam_spacing(value: Any) -> float:
    try:
        a = float(value)
    except (TypeError, ValueError):
        a = float("nan")
    if not 0.0 <= a <= 1.0:
        raise InputError(f"seam_spacing must be a number in [0, 1], got {value!r}")
    return a


def _seam_rounds(value: Any) -> bool:
    if value is None or value is False or value is True:
        return bool(value)
    raise InputError(f"seam_rounds must be True or False, got {value!r}")


def _crs(value: Any) -> str:
    from ..io.crs import crs_from_user

    return crs_from_user(value)  # WKT: the same CRS given two ways is the same key
