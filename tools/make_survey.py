"""Generate a large airborne survey as one LAZ file: the real autzen_trim.laz (110,000 points)
tiled NX x NY times side by side with offsets (no overlap), written chunk by chunk with laspy.

    python tools/make_survey.py -o /work/bench_data/survey_14x14.laz            # 14 x 14: 21,560,000 points
    python tools/make_survey.py --nx 4 --ny 4 -o /work/bench_data/survey_4x4.laz

Every copy keeps the source's attributes (intensity, returns, classification, GPS time, RGB...),
its scale and its CRS; copy (i, j) is shifted by (i * width, j * height) of the source's bounding
box plus a gap of 1 % (so the copies do not touch). The output is outside the repository (it is
data, not code). Prints a JSON line: the file, the point count, the size, the seconds.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT.parent / "shared" / "data" / "autzen_trim.laz"


def make(out: Path, nx: int, ny: int, source: Path = SOURCE) -> dict:
    import laspy

    t0 = time.perf_counter()
    src = laspy.read(str(source))
    hdr = src.header
    size = hdr.maxs - hdr.mins
    step = size * 1.01
    header = laspy.LasHeader(point_format=hdr.point_format, version=hdr.version)
    header.scales = hdr.scales
    header.offsets = hdr.offsets
    for vlr in hdr.vlrs:
        header.vlrs.append(vlr)
    header.system_identifier = "lodbuilder make_survey"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    n = 0
    with laspy.open(str(tmp), mode="w", header=header, do_compress=out.suffix.lower() == ".laz") as w:
        for j in range(ny):
            for i in range(nx):
                pts = src.points.copy()
                dx = int(round(i * step[0] / hdr.scales[0]))
                dy = int(round(j * step[1] / hdr.scales[1]))
                pts.X = np.asarray(src.points.X) + dx
                pts.Y = np.asarray(src.points.Y) + dy
                w.write_points(pts)
                n += len(pts)
    tmp.replace(out)
    return {"output": str(out), "points": n, "copies": [nx, ny], "source": source.name,
            "bytes": out.stat().st_size, "seconds": round(time.perf_counter() - t0, 1)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--nx", type=int, default=14)
    p.add_argument("--ny", type=int, default=14)
    p.add_argument("-o", "--output", required=True)
    args = p.parse_args(argv)
    json.dump(make(Path(args.output), args.nx, args.ny), sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
