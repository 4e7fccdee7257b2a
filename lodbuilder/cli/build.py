"""``lodbuilder build INPUT -o ARCHIVE``: order a scan with FastFPS and add it to an archive."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "build",
        help="order a scan and store it in an archive",
        description=(
            "Read a scan (PLY; other formats through lodbuilder.io), compute its farthest point "
            "ordering and add it to ARCHIVE (created when missing). Adding to an existing archive "
            "is atomic: the scans already in it are never at risk."
        ),
    )
    p.add_argument(
        "input",
        metavar="INPUT",
        nargs="*",
        help="scan file (.ply, .las, .laz, .e57, .xyz, .csv, .npy, ...); several files, directories, "
        "globs or a manifest build a collection",
    )
    p.add_argument("-o", "--output", required=True, metavar="ARCHIVE", help="archive file (.h5)")
    p.add_argument(
        "--name", help="scan name in the archive (default: the file name without suffix)"
    )
    p.add_argument(
        "--voxel-size",
        type=float,
        metavar="H",
        help="band grid spacing (default: from the point spacing)",
    )
    p.add_argument("--band-radius", type=float, metavar="R", help="band radius (default: from H)")
    p.add_argument("--overwrite", action="store_true", help="replace a scan of the same name")
    p.add_argument(
        "--crs",
        metavar="EPSG:XXXX|WKT|FILE",
        help="coordinate reference system of a scan whose file has none (EPSG codes need pyproj: "
        "pip install 'lodbuilder[crs]')",
    )
    p.add_argument(
        "--crs-override",
        action="store_true",
        help="let --crs replace the CRS the scan file declares",
    )
    p.add_argument("--no-progress", action="store_true", help="do not show progress bars")
    from .feature_options import add_build_options

    add_build_options(p)
    from .collection_options import add_arguments as add_collection_arguments

    add_collection_arguments(p)
    return p


def run(args: argparse.Namespace) -> int:
    from .._validate import check_positive
    from ..api import build_archive
    from ..archive.writer import check_writable_dir
    from ..errors import InputError
    from . import collection_options as collection_cli
    from .progressbar import ProgressBars

    if args.crs and collection_cli.wants_collection(args):
        raise InputError("--crs applies to one scan file; build the scans of a collection one by one")
    if collection_cli.wants_collection(
        args
    ):  # several scans, a directory, a manifest, --workers ...
        return collection_cli.run(args)
    args.input = args.input[0]
    src, out = Path(args.input), Path(args.output)
    if src.exists() and (src.resolve() == out.resolve()):
        raise InputError(f"output {out} is the input file; choose another -o ARCHIVE")
    check_positive(args.voxel_size, "--voxel-size")
    check_positive(args.band_radius, "--band-radius")
    check_writable_dir(out, "output")
    from .feature_options import build_kwargs

    features = build_kwargs(args)
    t0 = time.perf_counter()
    from .output import progress_enabled, say

    with ProgressBars(enabled=progress_enabled(args)) as bars:
        build_archive(
            src,
            out,
            name=args.name,
            voxel_size=args.voxel_size,
            band_radius=args.band_radius,
            overwrite=args.overwrite,
            crs=args.crs, crs_override=args.crs_override,
            progress=bars,
            **features,
        )
    from ..archive.reader import open_archive

    with open_archive(out) as arc:
        # the reader names the scan (file stem, or the name inside the file): find the newest
        # scan built from this source
        if args.name in arc.scans:
            v = arc.scan(args.name)
        else:
            built = [s for s in arc if s.provenance.get("source_name") == src.name]
            v = max(built, key=lambda s: str(s.provenance.get("created_utc", "")))
        say(
            args,
            f"added scan {v.name!r} ({v.n_points} points, {v.encoding} coordinates) to {out} "
            f"in {time.perf_counter() - t0:.1f} s; the archive holds {len(arc)} scan(s)",
        )
    return 0
