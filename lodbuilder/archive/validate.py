"""Check an archive: schema, checksums and the ordering invariants. Each fault is one line.

The file is opened like every reader opens it (:func:`lodbuilder.archive.reader.open_archive`):
anything pointing outside the archive, a hard-link cycle, sizes the file cannot hold or metadata
HDF5 cannot read are refused there with a one-line error (the CLI exits 2). What is found after
that is listed as faults (exit 1). Every dataset is read in full (which verifies its fletcher32
checksums), but only after :mod:`.safety` has checked that its declared size is backed by the file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ArchiveError, CorruptArchiveError, LodbuilderError
from . import checks, safety
from . import layout as L


def _check_order_arrays(where: str, radius: np.ndarray, parent: np.ndarray) -> list[str]:
    faults = []
    k = radius.shape[0]
    if np.isnan(radius).any():
        faults.append(
            f"{where}: radius holds NaN at position {int(np.flatnonzero(np.isnan(radius))[0])}"
        )
    elif k > 1:
        inc = np.flatnonzero(radius[1:] > radius[:-1])
        if inc.size:
            i = int(inc[0]) + 1
            faults.append(
                f"{where}: radius increases at position {i} ({float(radius[i - 1])!r} -> {float(radius[i])!r}); "
                "radii must be non-increasing"
            )
    if k and (radius < 0).any():
        faults.append(f"{where}: radius has negative values")
    idx = np.arange(k)
    bad = np.flatnonzero((parent >= idx) | (parent < -1))
    if bad.size:
        i = int(bad[0])
        faults.append(
            f"{where}: parent of position {i} is {int(parent[i])}; parents must come earlier "
            f"({bad.size} bad)"
        )
    roots = np.isinf(radius) != (parent == -1)
    if roots.any():
        i = int(np.argmax(roots))
        faults.append(
            f"{where}: position {i} has radius {float(radius[i])!r} and parent {int(parent[i])}; radius "
            f"is inf exactly for the roots (parent -1) ({int(roots.sum())} bad)"
        )
    return faults


def _read_all(meta: checks.ScanMeta, g: Any) -> tuple[dict[str, np.ndarray], list[str]]:
    """Every dataset of the scan group ``g``, read in full (checksums verified)."""
    import h5py

    data: dict[str, np.ndarray] = {}
    faults: list[str] = []

    def visit(rel: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            try:
                data[rel] = checks.read(meta, obj)
            except CorruptArchiveError as exc:
                faults.append(str(exc))

    g.visititems(visit)  # safe: the file has no links other than hard links, and no cycles
    return data, faults


def _check_scan(meta: checks.ScanMeta, g: Any) -> list[str]:
    where = f"scan {meta.name!r}"
    n, k = meta.n_points, meta.n_ordered
    data, faults = _read_all(meta, g)
    if faults:
        return faults
    src = data[L.D_SOURCE_INDEX]
    if not np.array_equal(np.sort(src), np.arange(n)):
        faults.append(f"{where}: source_index is not a permutation of 0..{n - 1}")
    radius, parent = data[L.D_RADIUS], data[L.D_PARENT]
    faults += _check_order_arrays(where, radius[:k], parent[:k])
    if k and not meta.stop_radius <= radius[k - 1]:
        faults.append(
            f"{where}: stop_radius {meta.stop_radius!r} is above the last radius {float(radius[k - 1])!r}; "
            "radii must be non-increasing"
        )
    if k < n and ((radius[k:] != 0).any() or (parent[k:] != -1).any()):
        faults.append(f"{where}: points beyond n_ordered={k} must have radius 0 and parent -1")
    seeds = data.get(L.D_SEEDS)
    if seeds is not None and seeds.size and (seeds.min() < 0 or seeds.max() >= n):
        faults.append(f"{where}: seeds must be input indices in [0, {n})")
    for key in (L.S_BUILD, L.S_PROVENANCE, L.S_FORMAT_METADATA):
        try:
            checks.json_attr(meta, g.attrs, key)
        except CorruptArchiveError:
            faults.append(f"{where}: attribute {key!r} is not valid JSON")
    step = meta.step
    if not np.array_equal(data[L.D_RADIUS_INDEX], radius[::step]):
        faults.append(f"{where}: radius_index does not match radius[::{step}]; rebuild the archive")
    pts = L.decode_points(data[L.D_POINTS], meta.encoding, meta.offset, meta.scale)
    if not np.isfinite(pts).all():
        faults.append(f"{where}: points hold NaN or inf")
    elif not (
        np.allclose(pts.min(0), meta.bounds_min) and np.allclose(pts.max(0), meta.bounds_max)
    ):
        faults.append(f"{where}: bounds_min/bounds_max attributes do not match the points")
    else:
        faults += _check_covering(where, pts, radius, k, meta.stop_radius)
    for rel, arr in data.items():
        parts = rel.split("/")
        if parts[0] == L.G_ORDERINGS and len(parts) == 3 and parts[2] == L.D_ORDER:
            oname = parts[1]
            ow = f"{where} ordering {oname!r}"
            rad = data[f"{L.G_ORDERINGS}/{oname}/{L.D_RADIUS}"]
            par = data[f"{L.G_ORDERINGS}/{oname}/{L.D_PARENT}"]
            if arr.size and (arr.min() < 0 or arr.max() >= n or np.unique(arr).size != arr.size):
                faults.append(f"{ow}: order must hold distinct positions in [0, {n})")
            faults += _check_order_arrays(ow, rad, par)
    return faults


COVER_SAMPLE = 20_000  # stored points checked against each prefix
COVER_PREFIX_MAX = 2_000_000  # prefixes up to this size get a k-d tree
COVER_TOLERANCE = 1e-12  # relative: the check's own rounding (cKDTree's distances in float64)


def cover_prefixes(k: int) -> list[int]:
    """The prefix lengths the guarantee is checked at: 1, 10, 100, ... below ``k``, and ``k``."""
    sizes = [10**j for j in range(7) if 10**j < k]
    return [s for s in sizes + [k] if s <= COVER_PREFIX_MAX]


def _check_covering(where: str, pts: np.ndarray, radius: np.ndarray, k: int, stop: float) -> list[str]:
    """The guarantee itself, by brute force: a sample of the stored points (every one of a small
    scan; points beyond ``n_ordered`` too unless the ordering is complete, as outliers are left
    out of it by design) is no farther from each checked prefix than the prefix's covering
    bound (``radius[s]``, ``stop`` for the whole ordering). One fault per lying radius."""
    from scipy.spatial import cKDTree

    from ..levels import covering_bound

    n = pts.shape[0]
    pool = n if stop > 0 else k  # a complete ordering does not cover the outliers it left out
    rng = np.random.default_rng(0)
    sample = np.sort(rng.choice(pool, COVER_SAMPLE, replace=False)) if pool > COVER_SAMPLE else np.arange(pool)
    q = pts[sample]
    faults = []
    for s in cover_prefixes(k):
        bound = covering_bound(s, k, radius.__getitem__, stop)
        if not np.isfinite(bound):
            continue
        dist, _ = cKDTree(pts[:s]).query(q)
        far = np.flatnonzero(dist > bound * (1 + COVER_TOLERANCE))
        if far.size:
            i = int(far[np.argmax(dist[far])])
            d = float(dist[i])
            faults.append(
                f"{where}: the first {s:,} points claim to cover every point within {bound:.6g}, but the "
                f"point at stored position {int(sample[i])} is {d:.6g} from them; the radii lie, "
                "rebuild the scan from its source"
            )
    return faults


def validate_archive(path: str | os.PathLike[str], *, schema: bool = True) -> list[str]:
    """All faults found in the archive at ``path`` (empty list: valid).

    Raises the usual one-line errors when ``path`` is missing, not an archive at all, refers to
    anything outside itself, or cannot be walked (see :mod:`lodbuilder.archive.safety`)."""
    from .reader import open_archive
    from .schema import validate_description

    path = Path(path)
    faults: list[str] = []
    with open_archive(path) as arc:
        with safety.h5_errors(path, "its metadata"):
            if schema:
                faults += validate_description(L.describe(arc.file))
            counts: dict[str, int] = {}
            bounds: dict[str, Any] = {}
            for name in arc.scans:
                try:
                    view = arc.scan(name)  # the scan's header is checked here
                    g = view._g
                    counts[name] = view.n_points
                    bounds[name] = view.bounds
                    if g.file != arc.file:  # a scan in a part file of the archive
                        faults += _check_part_holds(arc, name, g.file)
                    if schema and g.file != arc.file:
                        faults += [
                            f"part of scan {name!r}: {x}"
                            for x in validate_description(L.describe(g.file))
                        ]
                    faults += _check_scan(view._meta, g)
                except LodbuilderError as exc:
                    faults.append(f"scan {name!r}: cannot be checked: {exc}")
            try:
                index = arc.index()
            except LodbuilderError as exc:
                faults.append(f"index: cannot be read: {exc}")
                index = []
        names = [row["name"] for row in index]
        if names != arc.scans:
            faults.append(f"index: lists scans {names} but the archive holds {arc.scans}")
        else:
            for row in index:
                n = counts.get(row["name"])
                if n is not None and row["n_points"] != n:
                    faults.append(
                        f"index: scan {row['name']!r} has n_points {row['n_points']}, scan says {n}"
                    )
                b = bounds.get(row["name"])
                if b is not None and not _same_bounds(row, b):
                    faults.append(
                        f"index: scan {row['name']!r} has bounds {_box(row['bounds_min'], row['bounds_max'])}, "
                        f"the scan's points span {_box(*b)}"
                    )
    return faults


def _check_part_holds(arc: Any, name: str, f: Any) -> list[str]:
    """A part file holds exactly the one scan its index row names."""
    row = next(r for r in arc.rows if r.name == name)
    held = sorted(f[L.G_SCANS]) if L.G_SCANS in f else []
    if held != [name]:
        return [f"part {row.part} of scan {name!r} holds scans {held}; a part holds its one scan only"]
    return []


def _same_bounds(row: dict[str, Any], b: Any) -> bool:
    lo, hi = (np.asarray(x, dtype=float) for x in b)
    return bool(np.allclose(row["bounds_min"], lo, rtol=1e-9, atol=0, equal_nan=True)
                and np.allclose(row["bounds_max"], hi, rtol=1e-9, atol=0, equal_nan=True))


def _box(lo: Any, hi: Any) -> str:
    return "[" + ", ".join(f"{float(x):.6g}" for x in lo) + "] .. [" + ", ".join(f"{float(x):.6g}" for x in hi) + "]"


def check_valid(path: str | os.PathLike[str]) -> None:
    """Raise CorruptArchiveError naming the first fault (and the count) if the archive is invalid."""
    faults = validate_archive(path)
    if faults:
        more = f" (and {len(faults) - 1} more)" if len(faults) > 1 else ""
        raise CorruptArchiveError(f"archive {path} is invalid: {faults[0]}{more}")


__all__ = ["validate_archive", "check_valid", "ArchiveError"]
