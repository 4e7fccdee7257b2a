"""``lodbuilder demo [-o DIR]``: build an archive from a generated scan-like surface and slice it."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo",
        help="build a demo archive from a generated surface and write three levels",
        description=(
            "Generate a scan-like surface (a wavy sheet with colours and normals), build its "
            "archive DIR/demo.h5 and write three levels of detail to DIR as PLY files."
        ),
    )
    p.add_argument(
        "-o",
        "--output",
        default="lodbuilder-demo",
        metavar="DIR",
        help="output directory (default: ./lodbuilder-demo)",
    )
    p.add_argument("--points", type=int, default=20000, help="number of points (default 20000)")
    p.add_argument(
        "--surface",
        default="wavy",
        choices=["wavy", "sphere", "torus", "folded"],
        help="generated surface",
    )
    p.add_argument("--seed", type=int, default=7, help="random seed")
    p.add_argument("--no-progress", action="store_true", help="do not show progress bars")
    from .output import add_json_option

    add_json_option(p)
    return p


FRACTIONS = (0.01, 0.05, 0.25)


def run(args: argparse.Namespace) -> int:
    from ..api import build_archive
    from ..archive.reader import open_archive
    from ..archive.writer import check_writable_dir
    from ..datasets import demo_scan
    from ..errors import InputError
    from ..io import write_points
    from .output import emit, progress_enabled
    from .progressbar import ProgressBars

    out = Path(args.output)
    if args.points < 100:
        raise InputError(f"--points must be at least 100, got {args.points}")
    if out.exists() and not out.is_dir():
        raise InputError(f"output {out} exists and is not a directory; choose another -o DIR")
    check_writable_dir(out / "x", "output") if out.is_dir() else check_writable_dir(out, "output")
    created = not out.is_dir()
    out.mkdir(exist_ok=True)
    scan = demo_scan(args.points, kind=args.surface, seed=args.seed)
    archive = out / "demo.h5"
    rows: list[tuple[int, float, float, Path]] = []
    try:
        t0 = time.perf_counter()
        with ProgressBars(enabled=progress_enabled(args)) as bars:
            result = build_archive(scan, archive, overwrite=True, progress=bars)
        t_build = time.perf_counter() - t0
        with open_archive(archive) as arc:
            view = arc.scan("demo")
            for f in FRACTIONS:
                t = time.perf_counter()
                level = view.level(fraction=f)
                ms = (time.perf_counter() - t) * 1e3
                path = out / f"level_{level.size}.ply"
                write_points(path, level.points, level.attributes, metadata=view.format_metadata)
                rows.append((level.size, level.rho, ms, path))
    except BaseException:
        if created:  # a folder this run made: take back what it wrote, then the folder
            _remove_created(out, [archive] + [row[3] for row in rows])
        raise
    doc, text = _report(args, archive, t_build, rows, bool(result.by_status("skipped")))
    emit(args, doc, text)
    return 0


def _report(args: argparse.Namespace, archive: Path, t_build: float, rows: list[tuple[int, float, float, Path]],
            reused: bool) -> tuple[dict[str, Any], str]:
    """The demo's --json document and its table."""
    doc = {
        "archive": str(archive),
        "surface": args.surface,
        "n_points": args.points,
        "build_seconds": t_build,
        "levels": [
            {"size": size, "rho": rho, "slice_ms": ms, "output": str(path)}
            for size, rho, ms, path in rows
        ],
    }
    doc["reused"] = reused
    first = (
        f"reused {archive}: it already holds the generated {args.surface} surface of "
        f"{args.points:,} points (same seed and parameters); the levels were written again"
        if reused
        else f"built {archive} from a generated {args.surface} surface of {args.points:,} points "
        f"in {t_build:.1f} s"
    )
    text = [
        first,
        f"{'points':>8}  {'covering radius <=':>18}  {'slice ms':>8}  file",
        *(f"{size:>8,}  {rho:>18.5f}  {ms:>8.1f}  {path}" for size, rho, ms, path in rows),
        f"next: lodbuilder info {archive}; lodbuilder slice {archive} --rho 0.01 -o level.ply",
    ]
    return doc, "\n".join(text)


def _remove_created(folder: Path, files: list[Path]) -> None:
    """Remove ``files`` and then ``folder`` when nothing else is in it (a failed first demo)."""
    import contextlib
    import os

    for path in files:
        with contextlib.suppress(OSError):
            path.unlink()
    with contextlib.suppress(OSError):
        os.rmdir(folder)
