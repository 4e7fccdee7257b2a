"""Quality plots (matplotlib, Agg backend, imported only here): error vs size, radius vs rank."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import strict_keywords
from ..errors import InputError
from .report import LevelReport


def _pyplot():
    from .._optional import require

    matplotlib = require("matplotlib", "plot_quality")
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


@strict_keywords
def plot_quality(
    reports: Sequence[LevelReport],
    out: str | os.PathLike,
    *,
    radius: np.ndarray | None = None,
    title: str = "",
    units: str | None = None,
) -> Path:
    """Write a PNG with error vs size (log-log) and, when ``radius`` is given, insertion radius vs rank.

    Distances are labelled in ``units`` (the scan's linear unit, e.g. ``metre``), or in "scan
    units" when the unit is not known.

    The file is written to a temporary name in the destination directory and renamed into place.
    """
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise InputError(f"plot output {out} must end in .png")
    if not reports:
        raise InputError("no level to plot: give at least one size or rho")
    plt = _pyplot()
    unit = units or "scan units"
    ncols = 2 if radius is not None else 1
    fig, axes = plt.subplots(1, ncols, figsize=(6.0 * ncols, 4.5), squeeze=False)
    _plot_errors(axes[0, 0], reports, unit)
    if radius is not None:
        _plot_radius(axes[0, 1], radius, unit)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    from ..io._files import atomic_output

    try:
        with atomic_output(out) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    finally:
        plt.close(fig)
    return out


def _plot_errors(ax: Any, reports: Sequence[LevelReport], unit: str) -> None:
    """Error measures against level size (log-log), the claimed rho and the levels that violate it."""
    reps = sorted(reports, key=lambda r: r.size)
    size = np.array([r.size for r in reps], dtype=float)
    series = {
        "covering radius": [r.covering_radius for r in reps],
        "Hausdorff": [r.hausdorff for r in reps],
        "Chamfer": [r.chamfer for r in reps],
        f"surface error RMS ({reps[0].surface_method})": [r.surface_error["rms"] for r in reps],
        "min spacing": [r.min_spacing for r in reps],
    }
    for name, vals in series.items():
        v = np.asarray(vals, dtype=float)
        ok = np.isfinite(v) & (v > 0)
        if ok.any():
            ax.plot(size[ok], v[ok], marker="o", ms=3, label=name)
    claimed = [(r.size, r.rho) for r in reps if r.rho]
    if claimed:
        cs, cr = zip(*claimed, strict=True)
        ax.plot(cs, cr, ls="--", color="k", lw=0.8, label="claimed rho")
    bad = [(r.size, r.covering_radius) for r in reps if r.meets_rho is False]
    if bad:
        bs, br = zip(*bad, strict=True)
        ax.scatter(bs, br, marker="x", s=60, color="red", zorder=5, label="violates rho")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("level size (points)")
    ax.set_ylabel(f"distance ({unit})")
    ax.set_title("error vs size")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)


def _plot_radius(ax: Any, radius: np.ndarray, unit: str) -> None:
    """Insertion radius against rank (log-log)."""
    r = np.asarray(radius, dtype=float)
    rank = np.arange(1, r.size + 1)
    ok = np.isfinite(r) & (r > 0)
    ax.plot(rank[ok], r[ok], lw=1)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("rank (position in the ordering, 1-based)")
    ax.set_ylabel(f"insertion radius ({unit})")
    ax.set_title("insertion radius vs rank")
    ax.grid(True, which="both", alpha=0.3)
