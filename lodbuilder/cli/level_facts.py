"""What a level is, in words for ``slice`` and ``evaluate``: the pieces of the scan it reaches,
and a rho so coarse that the level is the first point only."""

from __future__ import annotations

from typing import Any


def piece_counts(build: dict[str, Any], size: int) -> tuple[int, int, bool] | None:
    """``(pieces reached, pieces in the scan, exact)`` for the prefix of ``size`` points of an
    ordering whose build record lists its pieces' entry ranks (in-memory and tiled builds); None when
    it does not (archives built before it did). ``exact`` is False where the record keeps only the first entries."""
    from ..levels import pieces_reached

    stats = (build or {}).get("engine_stats") or {}
    entries, total = stats.get("piece_entries"), stats.get("pieces")
    if entries is None or not total:
        return None
    p = pieces_reached(entries, size)
    return p, int(total), p < len(entries) or len(entries) == total


def level_facts(view: Any, level: Any, rho: float | None) -> dict[str, Any]:
    """Facts about a level of ``view`` (a ScanView) asked by ``rho`` (None: by size or fraction):
    ``pieces_reached``/``pieces`` (None when unknown) and ``first_point_only`` with the scan's
    largest finite radius, for :func:`facts_text`."""
    out: dict[str, Any] = {"pieces_reached": None, "pieces": None, "first_point_only": False}
    if getattr(level, "ordering", None) in (None, "uniform") and not getattr(level, "region", None):
        counts = piece_counts(view.build, level.size)
        if counts is not None:
            out["pieces_reached"], out["pieces"] = counts[0], counts[1]
            out["pieces_exact"] = counts[2]
    if rho is not None:
        top = view.largest_finite_radius()
        out["largest_finite_radius"] = top
        out["first_point_only"] = bool(top > 0 and rho >= top)
    return out


def facts_text(facts: dict[str, Any], rho: float | None) -> list[str]:
    """The facts as phrases for a message."""
    out = []
    if facts.get("pieces") and facts["pieces"] > 1:
        more = "" if facts.get("pieces_exact", True) else "at least "
        out.append(f"reaches {more}{facts['pieces_reached']:,} of the scan's {facts['pieces']:,} pieces")
    if facts.get("first_point_only"):
        out.append(
            f"rho {rho:g} is at least the scan's largest finite radius {facts['largest_finite_radius']:.4g}: "
            "the level is the first point only; ask for a smaller rho for more"
        )
    return out
