"""Coordinate reference systems: one text form (WKT), names and linear units through pyproj.

A scan's CRS travels as WKT text in ``Scan.metadata["crs_wkt"]`` (None when unknown) and is stored
with the scan in the archive's ``format_metadata``; ``crs_units`` beside it holds the linear unit
name that pyproj gave when the scan was read (so that archives answer ``ScanView.units`` without
pyproj). Where the CRS comes from:

* LAS/LAZ/COPC: the WKT VLR (record 2112) as written; without one, the GeoTIFF keys parsed by
  laspy's ``header.parse_crs()`` (needs pyproj).
* E57: the root ``coordinateMetadata`` string when it is not empty (WKT kept as written; other
  text such as ``EPSG:32633`` converted to WKT by pyproj).
* PLY: a header line ``comment crs <WKT>`` (what the PLY writer puts there).
* CSV/XYZ/NPY: a sidecar ``<file>.prj`` (e.g. ``level.csv.prj``) holding the WKT (what the
  writers put there). NPZ: the ``crs_wkt`` key of its JSON metadata.
* ``lodbuilder build --crs EPSG:XXXX|WKT|FILE`` (:func:`crs_from_user`) for files without one.

WKT is kept on one line: line breaks (and the indentation after them) become one space, which
the WKT grammar ignores, so a CRS is identical text after any round trip. pyproj is optional
(``pip install lodbuilder[crs]``): without it WKT still travels unchanged, but EPSG codes cannot
be resolved and :func:`linear_units` reports None (unknown) rather than guessing from the text.
"""

from __future__ import annotations

import functools
import logging
import os
import re
from pathlib import Path
from typing import Any

from ..errors import InputError, MissingDependencyError
from ._files import exc_line

log = logging.getLogger(__name__)

#: metadata keys every reader and writer uses
KEY_WKT = "crs_wkt"
KEY_UNITS = "crs_units"
#: how the scan got its CRS: "file" (read from the scan file), "assigned" (build --crs) or
#: "reprojected" (build --to-crs)
KEY_SOURCE = "crs_source"
#: the transform of a reprojected scan (build --to-crs): Reprojection.record
KEY_REPROJECTION = "crs_reprojection"

_WKT_START = re.compile(
    r"^\s*(PROJCS|GEOGCS|GEOCCS|COMPD_CS|VERT_CS|LOCAL_CS|PROJCRS|GEOGCRS|GEODCRS|BOUNDCRS|"
    r"COMPOUNDCRS|VERTCRS|ENGCRS|PROJECTEDCRS|GEODETICCRS|BASEGEOGCRS)\s*[\[(]",
    re.IGNORECASE,
)
_HINT = "pip install 'lodbuilder[crs]'"


def _pyproj() -> Any | None:
    try:
        import pyproj
    except ImportError:
        return None
    return pyproj


def normalise_wkt(text: Any) -> str | None:
    """WKT on one line (line breaks and the indentation after them become one space), trailing
    NULs (LAS VLR padding) and surrounding blanks removed; None for empty text."""
    if text is None:
        return None
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    s = re.sub(r"[ \t]*[\r\n]+[ \t]*", " ", str(text).replace("\x00", "")).strip()
    return s or None


def looks_like_wkt(text: str) -> bool:
    """True when ``text`` starts with a WKT CRS keyword and a bracket (not a parse: pyproj checks)."""
    return bool(_WKT_START.match(text))


def to_wkt(text: Any, *, what: str) -> str | None:
    """The WKT of a CRS description found in a file (``what`` names it for messages).

    WKT is kept as written (normalised to one line); anything else (``EPSG:2992``, a PROJ string)
    is converted by pyproj. Text that cannot be understood gives None and a warning: a CRS that
    cannot be read is reported unknown, never guessed."""
    s = normalise_wkt(text)
    if s is None:
        return None
    pyproj = _pyproj()
    if looks_like_wkt(s):
        return s
    if pyproj is None:
        log.warning("%s: CRS %r is not WKT and pyproj is not installed to read it; CRS unknown (%s)", what, s[:80], _HINT)
        return None
    try:
        return pyproj_wkt(pyproj.CRS.from_user_input(s))
    except Exception as exc:  # pyproj.exceptions.CRSError and friends
        log.warning("%s: CRS %r is not understood (%s); CRS unknown", what, s[:80], exc_line(exc))
        return None


def crs_from_user(spec: Any) -> str:
    """WKT of a CRS given by a user: ``EPSG:XXXX`` (needs pyproj), WKT text, or a file holding WKT.

    Raises InputError for anything pyproj (when installed) does not accept, and
    MissingDependencyError for an EPSG code or PROJ string without pyproj."""
    if not isinstance(spec, str) or not spec.strip():
        raise InputError(f"crs must be EPSG:XXXX, WKT text or a file holding WKT, got {spec!r}")
    text = spec.strip()
    if not looks_like_wkt(text) and os.path.isfile(text):
        try:
            text = Path(text).read_text(encoding="utf-8", errors="replace").strip()
        except OSError as exc:
            raise InputError(f"crs file {spec}: cannot be read ({exc.strerror}); check the path") from None
    s = normalise_wkt(text)
    assert s is not None
    pyproj = _pyproj()
    if pyproj is None:
        if looks_like_wkt(s):
            return s
        raise MissingDependencyError(f"crs {spec!r}: EPSG codes need pyproj; {_HINT}, or pass the WKT text")
    try:
        crs = pyproj.CRS.from_user_input(s)
    except Exception as exc:
        raise InputError(
            f"crs {spec[:80]!r} is not a CRS pyproj understands ({exc_line(exc)[:200]}); "
            "give EPSG:XXXX or WKT text"
        ) from None
    return s if looks_like_wkt(s) else pyproj_wkt(crs)


def pyproj_wkt(crs: Any) -> str:
    """WKT of a pyproj CRS: WKT1 (GDAL flavour, what LAS readers expect) when the CRS can be
    written so, else WKT2_2019; on one line."""
    text = None
    try:
        text = crs.to_wkt("WKT1_GDAL")
    except Exception:
        text = None
    return str(normalise_wkt(text or crs.to_wkt()))


def _crs(wkt: str | None) -> Any | None:
    pyproj = _pyproj() if wkt else None
    return None if pyproj is None else _parsed(pyproj, wkt)


@functools.lru_cache(maxsize=64)
def _parsed(pyproj: Any, wkt: str) -> Any | None:
    """pyproj's CRS of a WKT text, parsed once per process (a survey's files share one CRS, and
    parsing costs about 30 ms)."""
    try:
        return pyproj.CRS.from_wkt(wkt)
    except Exception:
        return None


def same_crs(a: str, b: str) -> bool:
    """Whether two WKTs name one CRS: the same text, or the same CRS to pyproj (when installed;
    axis order aside)."""
    if a == b:
        return True
    ca, cb = _crs(a), _crs(b)
    return bool(ca is not None and cb is not None and ca.equals(cb, ignore_axis_order=True))


def linear_units(wkt: str | None) -> str | None:
    """Unit name of the CRS's first axis (``metre``, ``US survey foot``, ``foot``, ``degree``...),
    or None when the CRS is unknown or pyproj is not installed."""
    crs = _crs(wkt)
    if crs is None:
        return None
    axes = crs.axis_info or (crs.sub_crs_list[0].axis_info if crs.sub_crs_list else [])
    if not axes:
        return None
    return str(axes[0].unit_name) or None


def crs_name(wkt: str | None) -> str | None:
    """The CRS's name (``NAD83(HARN) / Oregon GIC Lambert (ft)``...), or None without pyproj."""
    crs = _crs(wkt)
    return None if crs is None else str(crs.name)


def epsg_code(wkt: str | None) -> int | None:
    """The EPSG code pyproj finds for the CRS (exact match only), or None."""
    crs = _crs(wkt)
    if crs is None:
        return None
    try:
        code = crs.to_epsg(min_confidence=100)
    except Exception:
        return None
    return None if code is None else int(code)


def set_crs(metadata: dict[str, Any], wkt: str | None, source: str) -> None:
    """Record ``wkt`` (and its units, when pyproj is there) in a scan's metadata."""
    wkt = normalise_wkt(wkt)
    metadata[KEY_WKT] = wkt
    metadata[KEY_SOURCE] = source if wkt else None
    units = linear_units(wkt)
    if units:
        metadata[KEY_UNITS] = units
    else:
        metadata.pop(KEY_UNITS, None)


def assign_crs(metadata: dict[str, Any], spec: Any, *, override: bool = False, what: str = "scan") -> None:
    """Give a scan the CRS ``spec`` (see :func:`crs_from_user`).

    A scan whose file already declares a different CRS is refused unless ``override``: that
    CRS describes the coordinates, and replacing it silently would mislabel them."""
    wkt = crs_from_user(spec)
    own = metadata.get(KEY_WKT)
    if own and own != wkt and not override:
        name = crs_name(own)
        raise InputError(
            f"{what} already has a CRS ({name or own[:60]}); --crs would replace it: pass "
            "--crs-override (crs_override=True) to replace it, or leave --crs out"
        )
    if own == wkt:
        return
    set_crs(metadata, wkt, "assigned")


def sidecar(path: str | os.PathLike[str]) -> Path:
    """Path of the ``.prj`` sidecar that carries the CRS of a CSV/XYZ/NPY file: ``<file>.prj``."""
    p = Path(path)
    return p.with_name(p.name + ".prj")


def read_sidecar(path: str | os.PathLike[str]) -> str | None:
    """WKT from ``<file>.prj`` beside a scan file, or None."""
    side = sidecar(path)
    if not side.is_file():
        return None
    try:
        text = side.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return None
    return to_wkt(text, what=str(side))


def describe_crs(wkt: str | None) -> str:
    """A CRS for a message: its name and EPSG code when pyproj knows them, else the WKT's start."""
    if not wkt:
        return "no CRS"
    name, code = crs_name(wkt), epsg_code(wkt)
    text = name or (wkt[:60] + ("..." if len(wkt) > 60 else ""))
    return f"{text} (EPSG:{code})" if code else text


def common_crs(inputs: list[tuple[str, str | None]], to_crs: str | None = None) -> str | None:
    """The one CRS of scans joined into one ordering (``inputs``: (name, WKT or None) each), or
    ``to_crs`` (WKT) when they are to be reprojected to it.

    Scans in different CRSs are refused naming both, unless ``to_crs`` is given (one CRS written
    two ways is one, :func:`same_crs`: the first scan's WKT is returned); a scan without a CRS
    among scans with one is refused (its coordinates cannot be placed), even with ``to_crs``:
    ``--crs`` assigns it one."""
    have = [(n, w) for n, w in inputs if w]
    missing = [n for n, w in inputs if not w]
    if have and missing:
        raise InputError(
            f"scan {missing[0]!r} has no CRS while {have[0][0]!r} is in {describe_crs(have[0][1])}; "
            "give the scans without one a CRS with --crs EPSG:XXXX (or WKT), or build them separately"
        )
    if to_crs:
        if not have:
            raise InputError("--to-crs needs scans with a CRS to reproject from; give them one with --crs")
        return to_crs
    for n, w in have[1:]:
        if not same_crs(w, have[0][1]):  # (one CRS written two ways: WKT1 and 2, ESRI and OGC, GeoTIFF keys)
            raise InputError(
                f"scans {have[0][0]!r} and {n!r} are in different CRSs ({describe_crs(have[0][1])} and "
                f"{describe_crs(w)}); reproject them to one with --to-crs EPSG:XXXX (needs pyproj), or "
                "build them separately"
            )
    return have[0][1] if have else None


class Reprojection:
    """Coordinates from one CRS to another (pyproj, x/y in the CRSs' own axis units and order
    "x east, y north" whatever the CRS's declared axis order; z passes through the transform,
    unchanged unless the CRSs have vertical parts). ``record`` is what provenance stores."""

    def __init__(self, src_wkt: str, dst_wkt: str) -> None:
        pyproj = _pyproj()
        if pyproj is None:
            raise MissingDependencyError(f"--to-crs reprojects with pyproj; {_HINT}")
        self.src, self.dst = src_wkt, dst_wkt
        self._t = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(src_wkt), pyproj.CRS.from_wkt(dst_wkt),
                                              always_xy=True)
        self.record = {"from": describe_crs(src_wkt), "to": describe_crs(dst_wkt),
                       "from_units": linear_units(src_wkt), "to_units": linear_units(dst_wkt),
                       "transform": self._t.description, "pipeline": self._pipeline(), "always_xy": True}

    def _pipeline(self) -> str:
        """The PROJ pipeline (pyproj names it only once it has chosen one operation; where several
        apply, it chooses per point and says so)."""
        try:
            text = self._t.to_proj4()
        except Exception:
            text = None
        return str(text or self._t.definition)

    def __call__(self, points: Any) -> Any:
        import numpy as np

        pts = np.asarray(points, dtype=np.float64)
        x, y, z = self._t.transform(pts[:, 0], pts[:, 1], pts[:, 2])
        out = np.ascontiguousarray(np.stack([x, y, z], axis=1), dtype=np.float64)
        if not np.isfinite(out).all():
            raise InputError(
                f"reprojecting from {self.record['from']} to {self.record['to']} gave non-finite "
                "coordinates (points outside the target CRS's area?); choose another --to-crs"
            )
        return out


def reproject_metadata(metadata: dict[str, Any], rep: Reprojection) -> dict[str, Any]:
    """The metadata of a scan reprojected by ``rep``: the target CRS, its units, the transform;
    LAS scale/offset dropped (they described the old coordinates)."""
    meta = {k: v for k, v in metadata.items() if k not in ("scale", "offset", "las_scales", "las_offsets")}
    set_crs(meta, rep.dst, "reprojected")
    meta[KEY_REPROJECTION] = rep.record
    return meta


def reproject_scan(scan: Any, to_crs: str) -> None:
    """Reproject an in-memory Scan (points and metadata) to ``to_crs`` (WKT), in place; nothing
    to do when it is in that CRS already. A scan without a CRS is refused (nothing to reproject
    from: --crs assigns one)."""
    src = scan.metadata.get(KEY_WKT)
    if not src:
        raise InputError(f"scan {scan.name!r} has no CRS to reproject from; give it one with --crs EPSG:XXXX")
    if src == to_crs:
        return
    rep = Reprojection(src, to_crs)
    scan.points = rep(scan.points)
    scan.metadata = reproject_metadata(scan.metadata, rep)
