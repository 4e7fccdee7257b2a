"""The input set of ``tools/bench_build.py --set``: synthetic surfaces of N points (each a different
kind of difficulty) and every real scan in ../shared/data, plus a survey LAZ from
tools/make_survey.py. All synthetic inputs are called synthetic in the report.

    uniform   a wavy sheet on a jittered grid (the range-scan sheet of bench_build)
    uneven    the same sheet with random points whose density grows 3 x from x = 0 to x = 1
    noisy     the uniform sheet with Gaussian noise of 0.5 point spacing along z
    bumpy     a closed bumpy surface (a sphere with radial bumps of 10 %), random points, density
              2 x from pole to pole and noise of 0.3 spacing along the normal (a closed scan-like
              surface)
    stack     four parallel sheets 5 point spacings apart joined by folds (an accordion)

Written as an .npy file (an input of any build or benchmark; synthetic):

    python tools/bench_inputs.py uneven 2000000 -o /work/bench_data/uneven_2M.npy
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SYNTHETIC = ("uniform", "uneven", "noisy", "bumpy", "stack")
REAL_SUFFIXES = (".ply", ".las", ".laz", ".e57")


def range_scan_sheet(n: int, seed: int = 0) -> np.ndarray:
    """About n points of a wavy sheet on a jittered grid (unit square, amplitude 0.08)."""
    rng = np.random.default_rng(seed)
    side = int(round(np.sqrt(n)))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2).astype(float)
    g = (g + rng.uniform(-0.3, 0.3, g.shape)) / side
    z = 0.08 * np.sin(4 * np.pi * g[:, 0]) * np.cos(4 * np.pi * g[:, 1])
    return np.c_[g, z]


def _wave(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.08 * np.sin(4 * np.pi * x) * np.cos(4 * np.pi * y)


def uneven_sheet(n: int, seed: int = 1) -> np.ndarray:
    """n random points of the wavy sheet, density (1 + 2 x) / 2: 3 x more at x = 1 than at x = 0."""
    rng = np.random.default_rng(seed)
    x = (np.sqrt(1.0 + 8.0 * rng.random(n)) - 1.0) / 2.0  # inverse of the CDF (x + x^2) / 2
    y = rng.random(n)
    return np.c_[x, y, _wave(x, y)]


def noisy_sheet(n: int, seed: int = 2) -> np.ndarray:
    pts = range_scan_sheet(n, seed)
    spacing = 1.0 / math.sqrt(len(pts))
    pts[:, 2] += np.random.default_rng(seed + 100).normal(0.0, 0.5 * spacing, len(pts))
    return pts


def bumpy_closed(n: int, seed: int = 3) -> np.ndarray:
    """n points of a closed bumpy surface, density 2 x from one pole to the other, with noise."""
    rng = np.random.default_rng(seed)
    c = 2.0 * (np.sqrt(1.0 + 3.0 * rng.random(n)) - 1.0) - 1.0  # cos(theta), density (2 + c) / ...
    phi = 2 * np.pi * rng.random(n)
    s = np.sqrt(1.0 - c * c)
    d = np.c_[s * np.cos(phi), s * np.sin(phi), c]
    r = 1.0 + 0.1 * np.sin(5 * np.arccos(c)) * np.cos(4 * phi)
    spacing = math.sqrt(4 * np.pi / n)
    r = r + rng.normal(0.0, 0.3 * spacing, n)
    return d * r[:, None]


def stack(n: int, seed: int = 4) -> np.ndarray:
    sys.path.insert(0, str(ROOT / "tests"))
    from surfaces import accordion

    sheets = 4
    return accordion(n, sheets, 5.0 * math.sqrt(sheets / n), seed=seed)[0]


def synthetic(kind: str, n: int) -> np.ndarray:
    return {"uniform": range_scan_sheet, "uneven": uneven_sheet, "noisy": noisy_sheet,
            "bumpy": bumpy_closed, "stack": stack}[kind](n)


def real_files(data: Path) -> list[Path]:
    return sorted(p for p in data.iterdir() if p.suffix.lower() in REAL_SUFFIXES)


def set_markdown(rows: list[dict], summary: dict) -> list[str]:
    """The set's table and its summary for docs/benchmarks.md."""

    def f(x: object, fmt: str = "{:.2f}") -> str:
        return fmt.format(x) if isinstance(x, float) else ("-" if x is None else str(x))

    def runs(values: list[float]) -> str:
        return "-" if not values else f"{min(values):.2f}-{max(values):.2f} ({len(values)})"

    lines = [
        "",
        "The input set (`--set`; synthetic inputs marked; CPU seconds are the better measure on a loaded "
        "machine; fpsample's full ordering runs in a forked child of the same process, alternating, then "
        "again in fresh processes alternating with the runs of the whole `lodbuilder build` process; each "
        "figure is the smallest of its runs, *runs* give the range of the CPU seconds and their count, "
        "each ratio is the ratio of the smallest):",
        "",
        "| input | N | thin points | lodbuilder s | CPU s | fpsample s | CPU s | fpsample CPU runs | ratio "
        "| CPU ratio | build s | build process CPU s | build process CPU runs | process CPU ratio "
        "| build peak RSS B/point |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "failed" in r:
            lines.append(f"| {r['input']} | failed: {r['failed']} | | | | | | | | | | | | | |")
            continue
        builds = [b["whole_process_cpu_s"] for b in r.get("build_runs", [])]
        lines.append(
            f"| {r['input']} | {r['n']:,} | {r['thin_points']:,} | {f(r['time_s'])} | {f(r['cpu_s'])} | "
            f"{f(r['fpsample_time_s'])} | {f(r.get('fpsample_cpu_s'))} | "
            f"{runs([x[1] for x in r.get('fpsample_runs', [])])} | {f(r['ratio_to_fpsample'])} | "
            f"{f(r.get('cpu_ratio_to_fpsample'))} | {f(r.get('build_s'), '{:.1f}')} | "
            f"{f(r.get('build_process_cpu_s'))} | {runs(builds)} | "
            f"{f(r.get('build_process_cpu_ratio_to_fpsample'))} | "
            f"{f(r.get('build_peak_rss_bytes_per_point'), '{:.0f}')} |"
        )
    lines += ["", "Summary: " + ", ".join(f"{k} {f(v, '{:.3g}')}" for k, v in summary.items()
                                          if not isinstance(v, list)) + "."]
    return lines


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(description="Write one synthetic input of the set as an .npy file (float64 x, y, z)")
    p.add_argument("kind", choices=SYNTHETIC)
    p.add_argument("n", type=int, help="about this many points")
    p.add_argument("-o", "--output", type=Path, required=True, help="the .npy file to write")
    args = p.parse_args(argv)
    if args.output.suffix.lower() != ".npy":
        p.error(f"--output must end in .npy, got {str(args.output)!r}")
    if args.n < 1000:
        p.error(f"n must be at least 1000, got {args.n}")
    from lodbuilder._atomic import replace_with

    pts = np.ascontiguousarray(synthetic(args.kind, args.n), dtype="<f8")

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:  # (a file object: np.save would add .npy to the temporary's name)
            np.save(f, pts)

    replace_with(args.output, write, durable=False)
    print(f"wrote {len(pts):,} points ({args.kind}, synthetic) to {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
