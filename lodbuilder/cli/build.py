"""``lodbuilder build INPUT... -o ARCHIVE``: order scans with FastFPS and add them to an archive.

One path for every input: a single scan is a collection of one (see
:func:`lodbuilder.build_archive`). The command prints from the :class:`~lodbuilder.BuildResult`
the build returns (``--json``: the result as JSON).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

#: what an archive file name ends with
ARCHIVE_SUFFIXES = (".h5", ".hdf5")


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "build",
        help="order scans and store them in an archive",
        description=(
            "Read scans (PLY, LAS/LAZ, E57, XYZ/CSV, NPY), compute their farthest point orderings and "
            "add them to ARCHIVE (created when missing). Adding to an existing archive is atomic: the "
            "scans already in it are never at risk. A scan already built from the same source with the "
            "same parameters is skipped; an interrupted build resumes where it stopped."
        ),
    )
    p.add_argument(
        "input",
        metavar="INPUT",
        nargs="*",
        help="scan files (.ply, .las, .laz, .e57, .xyz, .csv, .npy, ...), directories, globs or "
        "manifests (*.conf, *.manifest, *.lst)",
    )
    p.add_argument("-o", "--output", required=True, metavar="ARCHIVE",
                   help="archive file, ending in .h5 or .hdf5 (an HDF5 file: it cannot go to stdout)")
    p.add_argument(
        "--name", help="scan name in the archive (one scan only; default: the file name without suffix)"
    )
    p.add_argument(
        "--voxel-size",
        type=float,
        metavar="H",
        help="band grid spacing (default: from the point spacing)",
    )
    p.add_argument("--band-radius", type=float, metavar="R", help="band radius (default: from H)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a scan of the same name built from other contents or parameters")
    p.add_argument(
        "--crs",
        metavar="EPSG:XXXX|WKT|FILE",
        help="coordinate reference system of scans whose files have none (EPSG codes need pyproj: "
        "pip install 'lodbuilder[crs]')",
    )
    p.add_argument(
        "--crs-override",
        action="store_true",
        help="let --crs replace the CRS a scan file declares",
    )
    p.add_argument(
        "--to-crs",
        metavar="EPSG:XXXX|WKT",
        help="reproject every scan to this CRS before ordering (with pyproj; the transform is recorded "
        "in provenance): scans of a joint build in different CRSs need it",
    )
    p.add_argument("--no-progress", action="store_true", help="do not show progress bars")
    from .output import add_json_option

    add_json_option(p)
    from .feature_options import add_build_options

    add_build_options(p)
    from .collection_options import add_arguments as add_collection_arguments

    add_collection_arguments(p)
    return p


def check_archive_output(path: str, inputs: list[str]) -> Any:
    """``-o`` of build: a file name ending in .h5/.hdf5 in an existing, writable directory; never
    stdout and never one of the inputs."""
    from ..errors import InputError
    from .output import check_output

    if path == "-":
        raise InputError("-o -: an archive cannot be written to stdout (it is an HDF5 file, written "
                         "beside its final name and renamed); give a file name ending in .h5")
    from ..archive.index import is_url

    if is_url(path):
        from ..archive.writer import check_writable_dir

        check_writable_dir(path, "output")  # archives are read-only over HTTP/S3: one line
    return check_output(path, "-o", suffixes=ARCHIVE_SUFFIXES,
                        inputs={f"file {s}": s for s in inputs if "*" not in s and "?" not in s})


def _status_line(st: Any, done: int, total: int) -> str:
    if st.status == "built":
        return f"[{done}/{total}] {st.name}: built ({st.n_points:,} points, {st.seconds:.1f} s)"
    if st.status == "failed":
        return f"[{done}/{total}] {st.name}: FAILED: {st.error}"
    return f"[{done}/{total}] {st.name}: {st.status}"


def _single_line(res: Any, shown: str) -> str:
    (st,) = res.scans
    if st.status == "skipped":
        return (f"scan {st.name!r} in {shown} is unchanged (same source, pose and parameters); "
                "nothing to do (pass --force to rebuild it)")
    part = ""
    if st.n_ordered is not None and st.n_points is not None and st.n_ordered < st.n_points:
        part = f", ordered {st.n_ordered:,} of {st.n_points:,} points"
    return (f"added scan {st.name!r} ({st.n_points:,} points, {st.encoding} coordinates{part}) to {shown} "
            f"in {res.seconds:.1f} s; the archive holds {res.archive_scans} scan(s)")


def run(args: argparse.Namespace) -> int:
    from .._kernels.warm import fewer_collections
    from .._validate import check_positive
    from ..api import build_archive
    from ..build.options import BuildOptions
    from ..errors import InputError
    from .collection_options import collection_kwargs, option_kwargs
    from .feature_options import build_kwargs
    from .output import emit, one_line, progress_enabled, verbosity
    from .progressbar import ProgressBars

    if not args.input and not args.manifest:
        raise InputError("give INPUT files, directories or globs, or --manifest FILE")
    out = check_archive_output(args.output, list(args.input or []))
    check_positive(args.voxel_size, "--voxel-size")
    check_positive(args.band_radius, "--band-radius")
    options = BuildOptions.make(voxel_size=args.voxel_size, band_radius=args.band_radius, crs=args.crs,
                                crs_override=args.crs_override, to_crs=args.to_crs, **option_kwargs(args), **build_kwargs(args))
    how = collection_kwargs(args)
    show_lines = verbosity(args) >= 0 and not getattr(args, "json", False)
    counter = {"done": 0, "total": 0}
    bars = ProgressBars(enabled=progress_enabled(args), stage_lines=bool(args.joint) and show_lines)

    def progress(stage: str, done: int, total: int) -> None:
        counter["total"] = total if stage == "scans" else counter["total"]
        bars(stage, done, total)

    progress.tasks = bars.tasks  # type: ignore[attr-defined]  # phases of tasks (lodbuilder.progress.report_tasks)

    def on_status(st: Any) -> None:
        counter["done"] += 1
        if counter["total"] <= 1:
            return  # a single scan: its summary line or its error says it all
        if show_lines or st.status == "failed":
            line = one_line(_status_line(st, counter["done"], max(counter["total"], 1)))
            bars.write(line) if bars.active else print(line, file=sys.stderr)

    with bars, fewer_collections():  # (numba's import and kernel loading make many objects)
        res = build_archive(list(args.input or []), out, options=options, name=args.name,
                            overwrite=args.overwrite, progress=progress, on_status=on_status, **how)
    single = len(res.scans) == 1
    emit(args, res.to_json(), lambda: _single_line(res, args.output) if single else res.describe(args.output))
    return 1 if res.failed else 0
