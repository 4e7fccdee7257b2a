"""Answering a :class:`~lodbuilder.levels.LevelQuery` on a stored scan: the one place where a query
becomes a level (a prefix, a refined level, a density floor, a filled level), with the sentence that
states what the level guarantees.

    from lodbuilder.levels import LevelQuery
    from lodbuilder.query import read_level
    with lodbuilder.open_archive("bunny.h5") as arc:
        answer = read_level(arc.scan(), LevelQuery(rho=0.002))
        answer.level, answer.guarantee          # Level, "covering radius <= 0.002"
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ._validate import strict_methods
from .errors import InputError
from .levels import Level, LevelQuery


@strict_methods
@dataclass
class LevelAnswer:
    """The level a query asked for, what it guarantees (``guarantee``, a sentence), and for a filled
    level the fill's result (``filled``: :class:`~lodbuilder.fill.FilledLevel`, else None)."""

    level: Level
    guarantee: str
    filled: Any = None


def read_level(view: Any, query: LevelQuery, *, attributes: Any = True) -> LevelAnswer:
    """The level of the stored scan ``view`` (a :class:`~lodbuilder.archive.scanview.ScanView`)
    that ``query`` asks for, reading only what it needs. ``attributes`` (a prefix only): which
    attributes to read, as for ``ScanView.level`` (True: all, False: none, or names)."""
    if attributes is not True and query.kind != "prefix":
        raise InputError(f"attributes= applies to a prefix level, not to a {query.kind} level")
    filled = None
    if query.kind == "fill":
        from .fill import fill_level

        filled = fill_level(view, query.rho, max_hole=query.fill)
        level = filled.level
    elif query.kind == "box":
        level = view.refine_box(query.box, query.box_rho, query.rho)
    elif query.kind == "viewpoint":
        level = view.refine_viewpoint(query.viewpoint, query.rho, query.slope, query.rho_max)
    elif query.kind == "floor":
        level = floor_level(view, query.floor_rho, query.size, query.ordering)  # type: ignore[arg-type]
    else:
        level = view.level(query.rho, size=query.size, fraction=query.fraction, ordering=query.ordering,
                           attributes=attributes)
    return LevelAnswer(level=level, guarantee=guarantee(view, level), filled=filled)


def floor_level(view: Any, rho: float, size: int, ordering: str | None = None) -> Level:
    """The level of a stored scan for a density floor chosen at query time: the uniform prefix
    covering within ``rho`` united with the ``ordering``'s prefix, exactly ``size`` points."""
    from .levels import covering_bound
    from .sampling.adaptive import floor_positions

    name = ordering or "weighted"
    pos = floor_positions(view.radius, view.n_ordered, view.ordering_positions(name), rho, size)
    bound = covering_bound(view.size_for_rho(rho), view.n_ordered, view.radius.__getitem__)
    return view.positions_level(pos, rho=bound, ordering=f"{name}+floor")


def guarantee(view: Any, level: Any) -> str:
    """What the level's radius guarantees, as a sentence.

    A prefix of the uniform ordering (or a floor query) covers within its radius; a prefix of a
    weighted ordering only within its *weighted* radius (see :mod:`lodbuilder.sampling.adaptive`);
    a prefix of a density-floor ordering past its uniform part covers within rho0."""
    name = getattr(level, "ordering", None)
    if name in (None, "uniform") or str(name).endswith("+floor"):
        return f"covering radius <= {level.rho:.6g}"
    params = view.ordering_parameters(name)
    kind = params.get("kind")
    if kind == "density_floor" and level.size > int(params.get("n_floor", 0)):
        return (
            f"covering radius <= {float(params['rho0']):.6g} (the density floor); weighted radius "
            f"{level.rho:.6g}"
        )
    if kind == "weighted":
        return f"weighted radius {level.rho:.6g}, not a Euclidean covering radius"
    return f"covering radius <= {level.rho:.6g}"
