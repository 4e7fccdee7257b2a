"""Generate a large airborne survey from the real autzen_trim.laz (110,000 points) tiled NX x NY
times side by side with offsets (no overlap): as one LAZ file (``-o FILE``) or as one LAZ file per
copy (``--files DIR``: NX x NY files, the form in which survey teams receive their data).

    python tools/make_survey.py -o /work/bench_data/survey_14x14.laz            # 14 x 14: 21,560,000 points
    python tools/make_survey.py --nx 4 --ny 4 -o /work/bench_data/survey_4x4.laz
    python tools/make_survey.py --nx 14 --ny 14 --files /work/bench_data/survey_14x14   # 196 files
    python tools/make_survey.py --nx 30 --ny 30 --files /work/bench_data/survey_30x30   # 900 files, 99M points

Every copy keeps the source's attributes (intensity, returns, classification, GPS time, RGB...),
its scale and its CRS (the source's VLRs); copy (i, j) is shifted by (i * width, j * height) of the
source's bounding box plus a gap of 1 % (so the copies do not touch). Memory stays bounded: one copy
of the source is in memory at a time, whatever NX x NY. Files are written under a temporary name and
renamed when complete (a file of the directory is whole or absent; an existing one is rewritten).
The output is outside the repository (it is data, not code). Prints a JSON line: the file (or the
directory and its file count), the point count, the size, the seconds.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT.parent / "shared" / "data" / "autzen_trim.laz"
if not SOURCE.exists():  # a worktree under /work/wt/NAME: the data lives beside the main tree
    SOURCE = Path("/work/shared/data/autzen_trim.laz")


def _header(hdr: Any) -> Any:
    import laspy

    header = laspy.LasHeader(point_format=hdr.point_format, version=hdr.version)
    header.scales = hdr.scales
    header.offsets = hdr.offsets
    for vlr in hdr.vlrs:
        header.vlrs.append(vlr)
    header.system_identifier = "lodbuilder make_survey"
    return header


def _read(source: Path, thin: int = 1) -> Any:
    """The source (every ``thin``-th point: tiny surveys for tests)."""
    import laspy

    src = laspy.read(str(source))
    if thin > 1:
        src.points = laspy.ScaleAwarePointRecord(src.points.array[::thin].copy(), src.header.point_format,
                                                 src.header.scales, src.header.offsets)
        src.update_header()
    return src


def _copies(src: Any, nx: int, ny: int) -> Iterator[tuple[int, int, Any]]:
    """(i, j, points of copy (i, j)), one copy in memory at a time."""
    hdr = src.header
    step = (hdr.maxs - hdr.mins) * 1.01
    x, y = np.asarray(src.points.X), np.asarray(src.points.Y)
    for j in range(ny):
        for i in range(nx):
            pts = src.points.copy()
            pts.X = x + int(round(i * step[0] / hdr.scales[0]))
            pts.Y = y + int(round(j * step[1] / hdr.scales[1]))
            yield i, j, pts


def _write(out: Path, header: Any, chunks: Iterator[Any]) -> int:
    """Write the point chunks to ``out`` (through ``out.part``, renamed when complete)."""
    import laspy

    tmp = out.with_name(out.name + ".part")
    n = 0
    with laspy.open(str(tmp), mode="w", header=header, do_compress=out.suffix.lower() == ".laz") as w:
        for pts in chunks:
            w.write_points(pts)
            n += len(pts)
    tmp.replace(out)
    return n


def make(out: Path, nx: int, ny: int, source: Path = SOURCE, thin: int = 1) -> dict:
    """One file of NX x NY copies."""
    t0 = time.perf_counter()
    src = _read(source, thin)
    out.parent.mkdir(parents=True, exist_ok=True)
    n = _write(out, _header(src.header), (pts for _, _, pts in _copies(src, nx, ny)))
    return {"output": str(out), "points": n, "copies": [nx, ny], "source": source.name,
            "bytes": out.stat().st_size, "seconds": round(time.perf_counter() - t0, 1)}


def file_name(i: int, j: int, nx: int, ny: int) -> str:
    """The name of copy (i, j) in ``--files`` mode (zero-padded: the files sort in row order)."""
    w = len(str(max(nx, ny) - 1))
    return f"survey_{j:0{w}d}_{i:0{w}d}.laz"


def make_files(out_dir: Path, nx: int, ny: int, source: Path = SOURCE, thin: int = 1) -> dict:
    """NX x NY files, one per copy, in ``out_dir`` (same CRS, scale and point format)."""
    t0 = time.perf_counter()
    src = _read(source, thin)
    out_dir.mkdir(parents=True, exist_ok=True)
    n, size = 0, 0
    for i, j, pts in _copies(src, nx, ny):
        f = out_dir / file_name(i, j, nx, ny)
        n += _write(f, _header(src.header), iter([pts]))
        size += f.stat().st_size
    return {"output": str(out_dir), "files": nx * ny, "points": n, "copies": [nx, ny], "source": source.name,
            "bytes": size, "seconds": round(time.perf_counter() - t0, 1)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--nx", type=int, default=14)
    p.add_argument("--ny", type=int, default=14)
    dest = p.add_mutually_exclusive_group(required=True)
    dest.add_argument("-o", "--output", help="one LAZ file holding every copy")
    dest.add_argument("--files", metavar="DIR", help="a directory of NX x NY LAZ files, one per copy")
    p.add_argument("--source", default=str(SOURCE), help="the LAS/LAZ file to copy (default: autzen_trim.laz)")
    p.add_argument("--thin", type=int, default=1, help="keep every THIN-th point of the source (tiny surveys for tests)")
    args = p.parse_args(argv)
    if args.nx < 1 or args.ny < 1 or args.thin < 1:
        p.error(f"--nx, --ny and --thin must be >= 1, got {args.nx}, {args.ny} and {args.thin}")
    if args.files:
        doc = make_files(Path(args.files), args.nx, args.ny, Path(args.source), args.thin)
    else:
        doc = make(Path(args.output), args.nx, args.ny, Path(args.source), args.thin)
    json.dump(doc, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
