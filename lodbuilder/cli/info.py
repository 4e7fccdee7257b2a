"""``lodbuilder info ARCHIVE [--json]``: scans, counts, radii, level sizes, parameters, provenance."""

from __future__ import annotations

import argparse
import math
from typing import Any


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "info",
        help="describe an archive",
        description="List the scans of ARCHIVE with point counts, radius range, the sizes of a few "
        "levels, the build parameters and the provenance.",
    )
    p.add_argument("archive", metavar="ARCHIVE")
    from .level_options import add_remote_options

    add_remote_options(p)
    p.add_argument("--scan", help="describe only this scan")
    from .output import add_json_option

    add_json_option(p)
    return p


def _round2(x: float) -> float:
    if x <= 0 or not math.isfinite(x):
        return x
    e = math.floor(math.log10(x))
    return round(x, -e + 1)


def scan_info(view: Any) -> dict[str, Any]:
    import numpy as np

    rad = view.radius[: view.n_ordered]
    finite = rad[np.isfinite(rad) & (rad > 0)]
    r_hi = float(finite.max()) if finite.size else 0.0
    r_lo = float(finite.min()) if finite.size else 0.0
    levels = []
    if finite.size and r_hi > 0:
        for rho in sorted(
            {_round2(x) for x in np.geomspace(r_hi, max(r_lo, r_hi * 1e-3), 5)}, reverse=True
        ):
            if rho >= view.stop_radius:  # a partial build has no finer level
                levels.append({"rho": rho, "size": view.size_for_rho(rho)})
    return {
        "name": view.name,
        "n_points": view.n_points,
        "n_ordered": view.n_ordered,
        "stop_radius": view.stop_radius,
        "n_seeds": int(np.isinf(rad).sum()),
        "coordinate_encoding": view.encoding,
        "bounds_min": view.bounds[0].tolist(),
        "bounds_max": view.bounds[1].tolist(),
        "radius_max_finite": r_hi,
        "radius_min_positive": r_lo,
        "levels": levels,
        "attributes": view.attribute_names,
        "importance": view.importance_names,
        "orderings": ["uniform"] + view.ordering_names,
        "build": view.build,
        "provenance": view.provenance,
        **crs_info(view),
    }


def crs_info(view: Any) -> dict[str, Any]:
    """``crs`` (WKT or None), ``crs_name`` and ``crs_epsg`` (pyproj; None without it), ``units``."""
    from ..io.crs import crs_name, epsg_code

    wkt = view.crs
    return {"crs": wkt, "crs_name": crs_name(wkt), "crs_epsg": epsg_code(wkt), "units": view.units}


def crs_line(s: dict[str, Any]) -> str:
    """``NAME (EPSG:N), units U`` for one scan of :func:`scan_info`."""
    if not s.get("crs"):
        return "none (units unknown)"
    name = s.get("crs_name") or (s["crs"][:60] + ("..." if len(s["crs"]) > 60 else ""))
    epsg = f" (EPSG:{s['crs_epsg']})" if s.get("crs_epsg") else ""
    return f"{name}{epsg}, units {s.get('units') or 'unknown'}"


def run(args: argparse.Namespace) -> int:
    from ..archive.reader import open_archive

    with open_archive(args.archive) as arc:
        names = [args.scan] if args.scan else arc.scans
        info: dict[str, Any] = {
            "path": str(arc.path),
            "file_size": arc.nbytes,
            "schema_version": arc.schema_version,
            "lodbuilder_version": arc.lodbuilder_version,
            "scans": [scan_info(arc.scan(n)) for n in names],
        }
    from .output import emit

    emit(args, info, lambda: _text(info))
    return 0


def _text(info: dict[str, Any]) -> str:
    """The text report; every line is one line whatever the names it shows hold."""
    from .output import one_line

    out = [
        f"{info['path']}: {len(info['scans'])} scan(s), {info['file_size']:,} bytes, schema "
        f"version {info['schema_version']} (written by lodbuilder {info['lodbuilder_version']})"
    ]
    for s in info["scans"]:
        prov = s["provenance"]
        left = s["n_points"] - s["n_ordered"]
        b = s["build"]
        if prov.get("source_name"):
            src = (
                f"{prov['source_name']} ({_count(prov.get('source_size'))} bytes, sha256 "
                f"{str(prov.get('source_sha256'))[:16]}...)"
            )
        else:
            src = "in-memory points (no source file)"
        out += [
            "",
            f"scan {s['name']!r}: {s['n_points']:,} points ({s['coordinate_encoding']} coordinates)"
            + (f", {left:,} left out of the ordering" if left > 0 else ""),
            f"  bounds     {_fmt(s['bounds_min'])} .. {_fmt(s['bounds_max'])}",
            f"  crs        {crs_line(s)}",
            f"  radius     {s['radius_max_finite']:.4g} .. {s['radius_min_positive']:.4g} "
            f"({s['n_seeds']} seed(s) with radius inf)",
            "  levels     " + ", ".join(f"rho {lv['rho']:g}: {lv['size']:,}" for lv in s["levels"]),
            *_stop_lines(s),
            f"  attributes {', '.join(s['attributes']) or '-'}",
            f"  importance {', '.join(s['importance']) or '-'}; "
            f"orderings {', '.join(s['orderings'])}",
            f"  build      {_build_line(b)}",
            f"  source     {src}, reader {prov.get('reader')}, "
            f"{prov.get('created_utc')}, lodbuilder {prov.get('lodbuilder_version')}",
        ]
    return "\n".join(one_line(line) for line in out)


def _stop_lines(s: dict[str, Any]) -> list[str]:
    """A partial build's limit: the covering radius where its ordering stops."""
    stop = s.get("stop_radius") or 0.0
    if stop <= 0.0:
        return []
    return [f"  stops at   covering radius {stop:.4g}: the ordering holds {s['n_ordered']:,} of "
            f"{s['n_points']:,} points (a partial build); no level is finer"]


def _build_line(b: dict) -> str:
    """How the ordering was built: the band's parameters, and for a tiled build its tiles and seams."""
    line = f"voxel_size {b.get('voxel_size')}, band_radius {b.get('band_radius')}, "
    tiled = b.get("tiled")
    if b.get("method") != "tiled" or not isinstance(tiled, dict):
        return line + f"engine {b.get('engine_stats', {}).get('engine', '?')}"
    alpha = float(tiled.get("seam_alpha", 0.0))
    if tiled.get("tiles") == 1:
        return line + "tiled (1 tile: no seams)"
    rounds = tiled.get("rounds") or {}
    how = f", in {rounds['rounds']} seam rounds of ratio {rounds['q']:g}" if rounds else ""
    return line + (f"tiled ({tiled.get('tiles')} tiles{how}, seam spacing {alpha:g}: points of different tiles "
                   f"at least {alpha / (1 + alpha):.2g} x the level's radius apart)")


def _fmt(v: list[float]) -> str:
    return "(" + ", ".join(f"{x:.6g}" for x in v) + ")"


def _count(value: Any) -> str:
    """An integer with thousands separated by commas (as every count the command line prints)."""
    return f"{value:,}" if isinstance(value, int) else str(value)
