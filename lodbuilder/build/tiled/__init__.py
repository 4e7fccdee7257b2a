"""Out-of-core, tiled farthest point ordering of one scan (the build path for scans that do not fit
in memory, and for joint orderings of registered collections: a survey of many files ordered as one
surface).

The parent plans from the inputs' headers (point counts, fields, CRS) and never reads a point in
the first three phases: tasks (on a process pool or a Dask cluster) read, survey and cut the scan,
one *block* each (a file, or a range of rows of a big LAS/LAZ, PLY or NPY file; see
:mod:`.survey` and :mod:`.blocks`). The phases:

1. **read** (tasks): each block decoded, posed and written raw (coordinates and attributes); the
   parent sums the blocks' counts, exact bounds, encodings and spacing sample;
2. **plan** (tasks, then the parent): each block's count histogram and its cells' first points of
   a decimated copy, summed; point spacing, voxel size and band radius shared by every tile; the
   tiles (a k-d split of the histogram, each tile small enough for the memory budget);
3. **coarse level**: a decimated copy (one point per grid cell) is ordered with FastFPS; its first
   points (the *head*) come first in the archive, with the certified bound "radius on the copy +
   the cell diagonal" (every point lies within a cell diagonal of the copy); meanwhile tasks cut
   every block into the tiles' core and halo pieces;
4. **tiles**: each tile's own points are ordered with FastFPS, seeded with the head points in the
   tile and its halo (tasks); with the option ``seam_rounds``, in radius rounds in which neighbouring
   tiles hand each other their points near a shared face, each tile's state kept on one worker
   (:mod:`.rounds`, :mod:`.affinity`);
5. **merge** (tasks): the seam repair of :mod:`lodbuilder.build.tiled.merge` over the tiles' seam
   points alone (one task), then the tile orders merged by descending insertion radius in bands of
   keys side by side (each band a run of every tile's stream); then tasks invert the merged order
   into every point's rank (an external transpose in two rounds: :mod:`.ranks`);
6. **covering**: for each tile (tasks), the exact Euclidean covering radius of its points by every
   prefix of the merged order (from the tile, its halo and the head points near it); the stored
   radius of a prefix is the largest over the tiles, capped by the coarse bound, never increasing:
   assembled in bands of positions by tasks (:mod:`.radii`; the parent carries two numbers from
   band to band);
7. **write** (tasks): first every raw block split by destination into the write's buckets (after
   the radii, once the covering files and the tiles' points are deleted: the work directory never
   holds the buckets beside them; see :mod:`.layout` for what is deleted when, and which work files
   are compressed); then the stored order cut into *bands* of whole row groups of the archive (one
   bucket each); a band task puts its bucket in order, checks its rows as the archive's scan writer
   does, and filters its rows' datasets into finished HDF5 chunks (an in-memory file with the
   archive's dataset creation properties, read back with ``read_direct_chunk``); the parent places
   the chunks in stored order with ``write_direct_chunk`` (bytes copied, no filter work) as the
   bands arrive, and writes the small metadata (:mod:`.bands`). The first band runs alone: its
   first row group decides which datasets are compressed, as a scan writer decides. The part file
   is the one a single scan writer fed every row in order gives; every archive reader is unchanged.

No process passes over every point (issue 19, item 2). The one task left that sees points of every
tile is the seam repair (``seam_repair``): a lazy greedy in merged order, each seam point's
acceptance depending on every earlier one, but over the linked seam points alone (seam points, those
nearer a shared face than their key, that come within ``alpha`` times their key of another tile's
seam point or of a head point, found by ``seam_links`` tasks over groups of tiles: 4,939 of the
21.56M-point survey's points, 0.02 %, where its seam points are 327,926). The merged order is
stored as pieces, the head's and one per band of keys (``merge_band`` tasks), listed in the merge's
marker. The parent's own pass over the write is a copy of the archive's bytes (the chunks), no
filter and no point.

Guarantees (checked by tests, stated in each tiled scan's build record): every prefix's stored
radius is a true Euclidean covering radius of the whole scan; radii never increase; every input
point is stored exactly once; the order is nested like any farthest point order (levels are
prefixes). Spacing: a point merged from one tile is at least ``seam_alpha`` times its merge key from
every earlier point of another tile, so between points of different tiles every level's spacing is
at least ``seam_alpha / (1 + seam_alpha)`` times its radius (0.2 at the default 0.25, 0.5 at 1);
inside a tile the tile's FastFPS order keeps its spacing (at least the insertion radius, in the band
metric). A larger ``seam_alpha`` costs covering at equal size (see ``SEAM_SPACING``).
"""

from __future__ import annotations

from typing import Any

__all__ = ["GUARANTEES", "SEAM_SPACING", "build_tiled", "needs_tiling", "parse_bytes", "tile_capacity"]

_FROM = {"GUARANTEES": "driver", "SEAM_SPACING": "driver", "build_tiled": "driver", "needs_tiling": "plan",
         "parse_bytes": "plan", "tile_capacity": "plan"}


def __getattr__(name: str) -> Any:
    """The package's names loaded with their module when first asked for: an in-memory build,
    which imports :mod:`.store` and :mod:`.plan` only, does not load the driver and its phases."""
    if name not in _FROM:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f".{_FROM[name]}", __name__), name)
