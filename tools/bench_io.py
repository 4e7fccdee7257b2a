"""LAZ size and coordinate error: the coordinate scale las_layout chooses vs the previous rule.

The previous writer (main at 50d94bc) chose the power-of-ten scale that fills int32 over the span
(10 ** ceil(log10(span / 2e9)): 1e-8 to 1e-9 for the real scans); las_layout takes the power of
ten at or below spacing / 100. For each real scan without a LAS source scale, both LAZ files are
written with laspy and compared: size in bytes and the largest coordinate error against the
source. Prints JSON (date, git commit, command, load); ``--markdown`` writes its section of
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchdoc import machine, measured, publish, stamp  # noqa: E402

from lodbuilder.io import read_scan  # noqa: E402
from lodbuilder.io.las import las_layout  # noqa: E402


def _previous_scale(points: np.ndarray) -> float:
    offsets = np.floor(points.min(axis=0))
    span = float(np.max(np.abs(points - offsets)))
    return 10.0 ** math.ceil(math.log10(max(span, 1e-300) / 2.0e9))


def bench_file(path: Path) -> dict:
    scan = read_scan(path)
    meta = {k: v for k, v in scan.metadata.items() if not k.startswith("las_")}  # no LAS source scale
    lay = las_layout(scan.points, scan.attributes, meta)
    out: dict = {"file": path.name, "points": len(scan)}
    with tempfile.TemporaryDirectory() as d:
        for label, scale in (("previous", _previous_scale(scan.points)), ("las_layout", float(lay.scales[0]))):
            lay.scales = np.full(3, scale)
            lay.offsets = np.floor(scan.points.min(axis=0) / (scale * 1000)) * (scale * 1000)
            las = lay.las_data(scan.points)
            p = Path(d) / f"{label}.laz"
            t0 = time.perf_counter()
            las.write(str(p), do_compress=True)
            t = time.perf_counter() - t0
            back = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
            out[label] = {"scale": scale, "bytes": p.stat().st_size, "write_s": round(t, 3),
                          "max_error": float(np.abs(back - scan.points).max())}
    out["size_ratio_previous_over_new"] = round(out["previous"]["bytes"] / out["las_layout"]["bytes"], 3)
    return out


def markdown(doc: dict) -> str:
    lines = [
        f"{measured(doc)}. Previous rule: "
        "10^ceil(log10(span / 2e9)); las_layout: the power of ten at or below spacing / 100.",
        "",
        "| file | points | previous scale | bytes | new scale | bytes | max error (new) | size ratio |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in doc["results"]:
        a, b = r["previous"], r["las_layout"]
        lines.append(f"| {r['file']} | {r['points']:,} | {a['scale']:g} | {a['bytes']:,} | {b['scale']:g} | "
                     f"{b['bytes']:,} | {b['max_error']:.2g} | {r['size_ratio_previous_over_new']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--files", nargs="+", default=["bun_zipper.ply", "igea.ply", "frag_115.ply",
                                                    "pumpAVisualReferenceImage.e57", "bunnyDouble.e57"])
    ap.add_argument("--markdown", help="also write the 'io' section of this markdown file")
    args = ap.parse_args()
    doc = stamp("bench_io", None, inputs="real scans " + ", ".join(args.files), synthetic=False)
    doc["machine"] = machine()
    doc["results"] = [bench_file(Path(args.data) / f) for f in args.files]
    publish(doc, section="io", render=markdown, markdown=args.markdown)


if __name__ == "__main__":
    main()
