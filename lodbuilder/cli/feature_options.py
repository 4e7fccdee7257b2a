"""Command-line options of feature sensitivity, shared by ``lodbuilder build`` and ``slice``.

The command modules call :func:`add_build_options` / :func:`build_kwargs` and
:func:`add_slice_options` (the query itself: :func:`lodbuilder.query.floor_level`).
"""

from __future__ import annotations

import argparse
from typing import Any


def add_build_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "feature sensitivity",
        "Importance maps and adaptive orderings stored beside the uniform ordering "
        "(slice them with --ordering weighted|floor).",
    )
    g.add_argument(
        "--importance",
        metavar="MAPS",
        help="comma-separated importance maps to compute and store: curvature, normal, colour, "
        "noise, attr:NAME (a scan attribute) or FILE.npy (default with --adaptive or "
        "--density-floor: curvature)",
    )
    g.add_argument(
        "--adaptive",
        type=float,
        metavar="A",
        help="adaptivity in [0, 1]: store the 'weighted' ordering with cost (1 - A) + A * importance "
        "(0.5 is a good start: on the Igea scan it lowered the point-to-plane error by 3-13 %%; "
        "1 starves flat regions)",
    )
    g.add_argument(
        "--density-floor",
        type=float,
        metavar="RHO0",
        help="store the 'floor' ordering: uniform until RHO0, then by importance "
        "(every prefix past n(RHO0) still covers within RHO0)",
    )
    g.add_argument(
        "--outlier-threshold",
        type=float,
        metavar="T",
        help="leave points with a noise score above T (about 1 on evenly noisy surfaces; try 10-20) "
        "out of every ordering; they stay in the archive, flagged by the attribute 'outlier'",
    )
    g.add_argument(
        "--importance-k",
        type=int,
        default=None,
        metavar="K",
        help="neighbours per point for the importance maps (default 16)",
    )
    g.add_argument(
        "--combine",
        choices=("mean", "max"),
        default=None,
        help="how several importance maps combine (default mean)",
    )


def build_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """Validated keyword arguments for ``build_archive`` (empty when no option was given)."""
    from .._validate import check_positive
    from ..errors import InputError
    from ..features.neighbours import check_k
    from ..features.registry import map_name, parse_names
    from ..features.weights import check_adaptivity

    out: dict[str, Any] = {}
    if getattr(args, "importance", None) is not None:
        for spec in parse_names(args.importance):
            map_name(spec)  # unknown names fail before the scan is read
        out["importance"] = args.importance
    if getattr(args, "adaptive", None) is not None:
        out["adaptive"] = check_adaptivity(args.adaptive)
    if getattr(args, "density_floor", None) is not None:
        out["density_floor"] = check_positive(args.density_floor, "--density-floor")
    if getattr(args, "outlier_threshold", None) is not None:
        out["outlier_threshold"] = check_positive(args.outlier_threshold, "--outlier-threshold")
    if getattr(args, "importance_k", None) is not None:
        out["importance_k"] = check_k(args.importance_k, "--importance-k")
    if getattr(args, "combine", None) is not None:
        if "adaptive" not in out and "density_floor" not in out:
            raise InputError("--combine needs --adaptive or --density-floor")
        out["combine"] = args.combine
    return out


def add_slice_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--floor-rho",
        type=float,
        metavar="R",
        help="with --size N and --ordering NAME: keep the uniform level that covers within R and "
        "fill it to exactly N points from ordering NAME (default: weighted)",
    )
