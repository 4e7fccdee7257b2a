"""One CRS per archive (issue 20, item 4): the scans of one build, and the scans added to an archive
whose scans have a CRS, are refused before any work when their CRSs differ, unless ``--to-crs``
reprojects the new ones to the archive's CRS or ``--crs`` gives a scan without one a CRS."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import InputError, LodbuilderError


def source_crss(sources: list[Any], options: Any) -> list[tuple[str, str | None]]:
    """(name, WKT or None) of each scan to build, as its job will see it (``--crs`` given to the
    scans without one, or to every scan with ``crs_override``), read from its file's header (no
    points); a file that cannot be read is left out (its own job reports it)."""
    from ..io.crs import KEY_WKT
    from ..io.stream import declared_crs

    named = []
    for src in sources:
        try:
            own = src.scan.metadata.get(KEY_WKT) if src.scan is not None else declared_crs(src.path)
        except (LodbuilderError, OSError):
            continue
        given = options.crs if options.crs and (options.crs_override or not own) else None
        named.append((src.path.name if src.path is not None else src.name, given or own))
    return named


def check_build_crs(sources: list[Any], archive: Path, options: Any, joint_name: str | None) -> None:
    """Refuse (InputError) scans of one collection in different CRSs (:func:`lodbuilder.io.crs.common_crs`;
    a joint build checks its inputs in its job), and scans whose CRS is not the one of the scans
    already in ``archive`` (those of the names built now are rebuilt or skipped: not counted)."""
    from ..io.crs import common_crs

    collection = len(sources) > 1 and joint_name is None
    named = source_crss(sources, options) if collection or archive.exists() else []
    if collection:
        common_crs(named, options.to_crs)
    if archive.exists():
        built = {joint_name} if joint_name is not None else {s.name for s in sources}
        check_append_crs(named, archive_crss(archive, built), archive, options.to_crs)


def archive_crss(archive: Path, leave_out: set[str]) -> list[tuple[str, str | None]]:
    """(name, WKT or None) of the scans of ``archive`` but those named in ``leave_out``; none when it
    cannot be read (the build's own checks say why)."""
    from ..archive.reader import open_archive

    try:
        with open_archive(archive) as arc:
            return [(n, arc.scan(n).crs or None) for n in arc.scans if n not in leave_out]
    except (LodbuilderError, OSError):
        return []


def check_append_crs(new: list[tuple[str, str | None]], scans: list[tuple[str, str | None]], archive: Path,
                     to_crs: str | None) -> None:
    """Refuse scans added to an archive (``scans``: (name, WKT or None) of those it keeps) when a new
    scan (``new``: (name, WKT or None), before any ``to_crs``) would be in another CRS than the
    archive's scans, in none while they have one, or in one while they have none."""
    from ..io.crs import describe_crs, same_crs

    have = [(n, w) for n, w in scans if w]
    if not have:
        _check_crs_free(new, scans, archive, to_crs)
        return
    theirs, first = have[0][1], have[0][0]
    where = f"the scans of archive {archive.name!r} are in {describe_crs(theirs)} (scan {first!r})"
    if to_crs is not None:
        if not any(same_crs(to_crs, w) for _, w in have):
            raise InputError(
                f"--to-crs would put the new scans in {describe_crs(to_crs)}, but {where}; ask --to-crs for "
                "their CRS, or build the new scans into another archive"
            )
        missing = [n for n, w in new if not w]
        if missing:
            raise InputError(
                f"scan {missing[0]!r} has no CRS to reproject from, while {where}; give it its CRS with "
                "--crs EPSG:XXXX (or WKT), or build it into another archive"
            )
        return
    for n, w in new:
        if not w:
            raise InputError(
                f"scan {n!r} has no CRS while {where}; give it a CRS with --crs EPSG:XXXX (or WKT), or "
                "build it into another archive"
            )
        if not any(same_crs(w, x) for _, x in have):
            raise InputError(
                f"scan {n!r} is in {describe_crs(w)} while {where}; reproject it to theirs with --to-crs "
                "EPSG:XXXX or a WKT file of that CRS (needs pyproj), or build it into another archive"
            )


def _check_crs_free(new: list[tuple[str, str | None]], scans: list[tuple[str, str | None]], archive: Path,
                    to_crs: str | None) -> None:
    """Refuse a scan in a CRS (its own, ``--crs`` or ``--to-crs``) added to an archive whose scans
    have none: the archive would mix coordinates that cannot be told apart (issue 20, item 4)."""
    from ..io.crs import describe_crs

    if not scans:
        return
    named = [(n, to_crs or w) for n, w in new if to_crs or w]
    if named:
        n, w = named[0]
        raise InputError(
            f"scan {n!r} is in {describe_crs(w)} while the scans of archive {archive.name!r} have no CRS "
            f"(scan {scans[0][0]!r}); build it into another archive, or rebuild those scans with their "
            "CRS (--crs EPSG:XXXX --overwrite) first"
        )
