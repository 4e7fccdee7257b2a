"""Quality reports of the levels stored in an archive (through the archive reader)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .._validate import check_fraction, check_positive, check_size, strict_keywords, strict_methods
from ..errors import InputError
from ..levels import LevelQuery
from ..progress import ProgressCallback, report
from ..query import read_level
from .report import LevelReport, default_sizes, evaluate_level


@strict_methods
@dataclass
class ScanEvaluation:
    """The reports of one scan's levels, with what is needed to plot them."""

    scan: str
    n_points: int
    ordering: str
    reports: list[LevelReport]
    radius: np.ndarray = field(repr=False)
    build: dict[str, Any] = field(default_factory=dict)
    #: linear unit of the coordinates (``ScanView.units``), None when unknown
    units: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "scan": self.scan,
            "n_points": self.n_points,
            "ordering": self.ordering,
            "units": self.units,
            "build": self.build,
            "levels": [r.as_dict() for r in self.reports],
        }


def _level_queries(n_ordered: int, sizes: Any, rhos: Any, fractions: Any,
                   extra: str | None) -> list[tuple[str, LevelQuery]]:
    """``(label, query)`` of every level to evaluate, checked (default: ten log-spaced sizes); an
    ``extra`` ordering's levels are asked by size or fraction only."""
    if extra and rhos:
        raise InputError(
            f"levels of ordering {extra!r} are asked by --sizes or --fractions: its radii are not "
            "Euclidean, so a rho does not name a level of it"
        )
    queries: list[tuple[str, Any]] = []  # (kind, value)
    queries += [("size", check_size(s, n_ordered)) for s in sizes or ()]
    queries += [("fraction", check_fraction(f)) for f in fractions or ()]
    queries += [("rho", check_positive(r, "rho", allow_none=False)) for r in rhos or ()]
    queries = queries or [("size", s) for s in default_sizes(n_ordered)]
    return [(f"{kind}={value:g}", LevelQuery(**{kind: value}, ordering=extra)) for kind, value in queries]


@strict_keywords
def evaluate_scan(
    scan: Any,
    *,
    sizes=None,
    rhos=None,
    fractions=None,
    ordering: str | None = None,
    surface: str = "plane",
    k: int | None = None,
    progress: ProgressCallback = None,
) -> ScanEvaluation:
    """Evaluate levels of an archive scan (a :class:`lodbuilder.archive.scanview.ScanView`).

    The input is every stored point of the scan. Levels come from ``sizes``, ``rhos`` or
    ``fractions`` (default: ten sizes log-spaced from 0.1 % to 100 %). For the stored (uniform)
    ordering a level claims the archive's covering bound rho, which is checked against the measured
    Euclidean covering radius. An extra ``ordering`` (e.g. a weighted one) claims no Euclidean rho:
    its radii live in another metric.
    """
    pts = scan.points()
    n = pts.shape[0]
    extra = ordering not in (None, "uniform")
    queries = _level_queries(scan.n_ordered, sizes, rhos, fractions, ordering if extra else None)
    tree = cKDTree(pts)
    reports = []
    for i, (label, query) in enumerate(queries):
        level = read_level(scan, query, attributes=False).level
        claim = None if extra else float(level.rho)
        reports.append(
            evaluate_level(
                pts,
                level.points,
                rho=claim,
                surface=surface,
                k=k,
                label=label,
                input_tree=tree,
            )
        )
        report(progress, "evaluate", i + 1, len(queries))
    if extra:
        radius = np.asarray(scan.dataset(f"orderings/{ordering}/radius")[:])
    else:
        radius = np.asarray(scan.radius)
    return ScanEvaluation(
        scan=scan.name,
        n_points=n,
        ordering=ordering or "uniform",
        reports=reports,
        radius=radius,
        build=scan.build,
        units=getattr(scan, "units", None),
    )


def _scan_keywords() -> list[str]:
    import inspect

    return [k for k in inspect.signature(evaluate_scan).parameters if k != "scan"]


@strict_keywords(extra=_scan_keywords)
def evaluate_archive(
    path: str | os.PathLike[str],
    scan: str | None = None,
    **kw: Any,
) -> ScanEvaluation:
    """Open the archive at ``path`` and evaluate one scan (see :func:`evaluate_scan`)."""
    from ..archive.reader import open_archive

    with open_archive(path) as arc:
        return evaluate_scan(arc.scan(scan), **kw)
