"""The collection options of ``lodbuilder build`` (manifests, a pool or a Dask cluster, resume) and
``lodbuilder slice --all-scans``.

``lodbuilder/cli/build.py`` calls :func:`add_arguments` on its parser and passes
:func:`collection_kwargs` to :func:`lodbuilder.build_archive`.
"""

from __future__ import annotations

import argparse
from typing import Any


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("collections (several scans, directories, globs, manifests)")
    g.add_argument("--manifest", metavar="FILE",
                   help="text file listing scans, one per line, each optionally followed by a pose: 16 numbers "
                        "(row-major 4x4, world = M [p 1]) or the bun.conf form 'bmesh FILE tx ty tz qx qy qz qw'")
    g.add_argument("--workers", type=int, metavar="N",
                   help="local worker processes, N >= 1 (default: one scan that fits in memory runs in this "
                        "process; several scans, or the tiles of a large scan, on one worker per core)")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="run the scans (or a large scan's tiles) on this Dask scheduler (tcp://host:8786); its "
                        "workers must see the archive's directory at the same path (shared file system)")
    g.add_argument("--dask-local", type=int, metavar="N",
                   help="start a Dask LocalCluster of N workers and run the scans (or a large scan's tiles) on it")
    g.add_argument("--size", type=int, metavar="N",
                   help="order only the first N points of each scan (quick previews; default: every point)")
    g.add_argument("--force", action="store_true", help="rebuild scans even when source and parameters are unchanged")
    g.add_argument("--wait", type=float, metavar="SECONDS",
                   help="while another build (or other writer) of the archive runs, wait for it at most this long "
                        "(default: until it finishes; 0: fail at once)")
    t = p.add_argument_group("large scans and joint orderings (the tiled, out-of-core path)")
    t.add_argument("--max-memory", metavar="BYTES",
                   help="memory budget of the build (this process and its workers; e.g. 3GB, 512MiB): a scan "
                        "whose in-memory build would not fit is read in chunks, ordered tile by tile on the "
                        "workers and merged (default: 60%% of this machine's memory)")
    t.add_argument("--joint", nargs="?", const=True, default=False, metavar="NAME",
                   help="order every input scan (posed, e.g. by a manifest) as one surface: one scan NAME "
                        "(default: the manifest's name) whose points keep scan_id and scan_point attributes")
    t.add_argument("--work-dir", metavar="DIR|URL",
                   help="where a tiled build keeps its work files: a directory, or an object store's fsspec URL "
                        "(s3://BUCKET/PREFIX; credentials and endpoint from fsspec's usual configuration, e.g. "
                        "AWS_ACCESS_KEY_ID and AWS_ENDPOINT_URL) for Dask workers that share no file system with "
                        "this process (default: a hidden directory beside the archive)")
    t.add_argument("--seam-spacing", type=float, metavar="A",
                   help="seam repair of the tiled merge, 0..1 (default 0.25): a point merged from one tile keeps "
                        "at least A times its merge radius from earlier points of other tiles, so points of "
                        "different tiles in a level are at least A/(1+A) times its radius apart (0.2; 0.5 at "
                        "A=1, at some cost in level size); 0 turns it off")
    t.add_argument("--seam-rounds", action="store_true",
                   help="order the tiles in radius rounds in which neighbouring tiles hand each other their points "
                        "near a shared face: points of different tiles stay about 0.4-0.5 times a coarse level's "
                        "radius apart (measured; the seam repair's bound still holds), for about 1.0-1.6 times "
                        "the ordering's CPU; each worker keeps its tiles' states in memory (about 260 bytes a "
                        "point), and a build whose workers cannot hold them is refused")


def collection_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """How :func:`lodbuilder.build_archive` runs, from the collection options (what it stores is
    in the build's :class:`~lodbuilder.build.options.BuildOptions`: :func:`option_kwargs`)."""
    return {"manifest": args.manifest, "workers": args.workers, "scheduler": args.scheduler,
            "dask_local": args.dask_local, "force": args.force, "wait": args.wait, "joint": args.joint,
            "work_dir": args.work_dir}


def option_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The collection options that are build options (keywords of ``BuildOptions.make``)."""
    return {"size": args.size, "max_memory": args.max_memory, "seam_spacing": args.seam_spacing,
            "seam_rounds": args.seam_rounds}


def slice_all(args: argparse.Namespace) -> int:
    """``lodbuilder slice ARCHIVE --all-scans --rho R -o OUT``: the level of every scan, merged (a
    joint scan counts as its members; ``--scan NAME`` keeps one scan or one member)."""
    from pathlib import Path

    from ..archive.reader import open_archive
    from ..collection.query import collection_level, joint_members
    from ..errors import InputError
    from ..io import write_points
    from ..io.api import collect_notes

    if args.rho is None:
        raise InputError("--all-scans needs --rho (one density for every scan)")
    for flag, value in (("--box", args.box), ("--viewpoint", args.viewpoint),
                        ("--ordering", args.ordering), ("--floor-rho", getattr(args, "floor_rho", None))):
        if value is not None:
            raise InputError(f"--all-scans does not combine with {flag}")
    # --scan NAME: that scan only, or that member of a joint scan (its points of the joint level)
    lvl = collection_level(args.archive, args.rho, scans=None if args.scan is None else [args.scan])
    with open_archive(args.archive) as arc:  # a joint scan's level lists its members, not itself
        views = [v for v in map(arc.scan, arc.scans) if set([v.name, *(joint_members(v) or [])]) & set(lvl.scans)]
        metas = [v.format_metadata for v in views]
        crss = [(v.name, v.crs, v.units) for v in views]
    meta = dict(metas[0]) if metas and all(m == metas[0] for m in metas) else {}
    crs, units, changes = _common_crs(crss)
    for key in ("crs_wkt", "crs_units", "crs_source"):
        meta.pop(key, None)
    if crs:
        meta["crs_wkt"] = crs  # already WKT (no pyproj on the slice path)
    if units:
        meta["crs_units"] = units
    meta["comments"] = [f"scan_id {i} = {name}" for i, name in enumerate(lvl.scans)]
    with collect_notes() as notes:
        write_points(Path(args.output), lvl.points, lvl.attributes, metadata=meta)
    changes += notes
    from .output import emit

    doc = {"archive": str(args.archive), "output": str(args.output), "size": len(lvl), "rho": lvl.rho,
           "scans": lvl.scans, "sizes": lvl.sizes, "attributes": sorted(lvl.attributes), "crs": crs,
           "units": units, "changes": changes}
    emit(args, doc, "\n".join(
        [f"wrote {len(lvl):,} points of {len(lvl.scans)} scans at rho {args.rho:g} to {args.output} "
         f"(attribute scan_id: {', '.join(f'{i}={n}' for i, n in enumerate(lvl.scans))})"]
        + [f"  changed: {line}" for line in changes]))
    return 0


def _common_crs(crss: list[tuple[str, str | None, str | None]]) -> tuple[str | None, str | None, list[str]]:
    """The CRS (WKT) and units every scan shares, else none and a note naming the scans' CRSs."""
    wkts = {wkt for _, wkt, _ in crss}
    if len(wkts) == 1:
        (wkt,) = wkts
        units = {u for _, _, u in crss}
        return wkt, (units.pop() if len(units) == 1 else None), []
    from ..io.crs import crs_name

    seen = ", ".join(f"{name}: {(crs_name(wkt) or 'a WKT CRS') if wkt else 'none'}" for name, wkt, _ in crss)
    return None, None, [f"the scans have different coordinate reference systems ({seen}); the output has none"]
