"""The collection side of ``lodbuilder build``: many inputs, manifests, a pool or a Dask cluster.

``lodbuilder/cli/build.py`` calls :func:`add_arguments` on its parser and hands over to
:func:`run` when :func:`wants_collection` says the inputs are more than one plain scan.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("collections (several scans, directories, globs, manifests)")
    g.add_argument("--manifest", metavar="FILE",
                   help="text file listing scans, one per line, each optionally followed by a pose: 16 numbers "
                        "(row-major 4x4, world = M [p 1]) or the bun.conf form 'bmesh FILE tx ty tz qx qy qz qw'")
    g.add_argument("--workers", type=int, metavar="N", help="local worker processes (default: all cores)")
    g.add_argument("--scheduler", metavar="ADDRESS", help="run the scans on this Dask scheduler (tcp://host:8786)")
    g.add_argument("--dask-local", type=int, metavar="N", help="start a Dask LocalCluster of N workers and use it")
    g.add_argument("--size", type=int, metavar="N",
                   help="order only the first N points of each scan (quick previews; default: every point)")
    g.add_argument("--force", action="store_true", help="rebuild scans even when source and parameters are unchanged")


def wants_collection(args: argparse.Namespace) -> bool:
    """True unless the inputs are exactly one plain scan file with no collection option."""
    from ..collection.inputs import MANIFEST_SUFFIXES, expand_inputs

    inputs = list(args.input or [])
    if args.manifest or args.workers is not None or args.scheduler or args.dask_local is not None \
            or args.size is not None or args.force or len(inputs) != 1:
        return True
    from pathlib import Path

    p = Path(inputs[0])
    if p.is_dir() or (not p.exists() and any(c in inputs[0] for c in "*?[")):
        return True
    if p.suffix.lower() in MANIFEST_SUFFIXES:
        return True
    if p.suffix.lower() == ".e57" and p.is_file():
        return len(expand_inputs([p])) > 1
    return False


def _status_line(st: Any, done: int, total: int) -> str:
    if st.status == "built":
        return f"[{done}/{total}] {st.name}: built ({st.n_points} points, {st.seconds:.1f} s)"
    if st.status == "failed":
        return f"[{done}/{total}] {st.name}: FAILED: {st.error}"
    return f"[{done}/{total}] {st.name}: {st.status}"


def run(args: argparse.Namespace) -> int:
    from ..collection.runner import build_collection
    from ..errors import InputError
    from .feature_options import build_kwargs

    if args.name:
        raise InputError("--name names a single scan; a collection names each scan after its file")
    if not args.input and not args.manifest:
        raise InputError("give INPUT files, directories or globs, or --manifest FILE")
    from .output import QUIET, progress_enabled, say, verbosity

    show = progress_enabled(args) is not False and sys.stderr.isatty()
    bar: Any = None
    counter = {"done": 0}

    def on_status(st: Any) -> None:
        counter["done"] += 1
        if verbosity(args) == QUIET and st.status != "failed":
            return
        line = _status_line(st, counter["done"], total["n"])
        if bar is not None:
            bar.write(line, file=sys.stderr)
            bar.update(1)
            bar.set_postfix_str(f"{st.name}: {st.status}")
        else:
            print(line, file=sys.stderr)

    total = {"n": 0}

    def progress(stage: str, done: int, n: int) -> None:
        nonlocal bar
        total["n"] = n
        if show and bar is None and n:
            from tqdm import tqdm

            bar = tqdm(total=n, desc="scans", unit="scan", leave=False, file=sys.stderr)

    t0 = time.perf_counter()
    try:
        res = build_collection(
            list(args.input or []), args.output, manifest=args.manifest, workers=args.workers,
            scheduler=args.scheduler, dask_local=args.dask_local, voxel_size=args.voxel_size,
            band_radius=args.band_radius, size=args.size, force=args.force,
            overwrite=getattr(args, "overwrite", False), progress=progress, on_status=on_status,
            **build_kwargs(args),
        )
    finally:
        if bar is not None:
            bar.close()
    counts = res.summary()
    parts = [f"{counts[k]} {k}" for k in ("built", "recovered", "skipped", "failed") if counts.get(k)]
    where = f" on {res.executor}" if res.executor else ""
    say(args, f"{', '.join(parts)} scan(s) into {res.archive}{where} in {time.perf_counter() - t0:.1f} s")
    return 1 if res.failed else 0


def slice_all(args: argparse.Namespace) -> int:
    """``lodbuilder slice ARCHIVE --all-scans --rho R -o OUT``: the level of every scan, merged."""
    from pathlib import Path

    from ..collection.query import collection_level
    from ..errors import InputError
    from ..io import write_points

    if args.rho is None:
        raise InputError("--all-scans needs --rho (one density for every scan)")
    for flag, value in (("--scan", args.scan), ("--box", args.box), ("--viewpoint", args.viewpoint),
                        ("--ordering", args.ordering), ("--floor-rho", getattr(args, "floor_rho", None))):
        if value is not None:
            raise InputError(f"--all-scans does not combine with {flag}")
    lvl = collection_level(args.archive, args.rho)
    from ..archive.reader import open_archive

    with open_archive(args.archive) as arc:
        metas = [arc.scan(n).format_metadata for n in lvl.scans]
    meta = dict(metas[0]) if metas and all(m == metas[0] for m in metas) else {}
    meta["comments"] = [f"scan_id {i} = {name}" for i, name in enumerate(lvl.scans)]
    write_points(Path(args.output), lvl.points, lvl.attributes, metadata=meta)
    from .output import emit

    doc = {"archive": str(args.archive), "output": str(args.output), "size": len(lvl), "rho": lvl.rho,
           "scans": lvl.scans, "sizes": lvl.sizes, "attributes": sorted(lvl.attributes)}
    emit(args, doc, f"wrote {len(lvl)} points of {len(lvl.scans)} scans at rho {args.rho:g} to "
                    f"{args.output} (attribute scan_id: {', '.join(f'{i}={n}' for i, n in enumerate(lvl.scans))})")
    return 0
