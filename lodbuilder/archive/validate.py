"""Check an archive: schema, checksums and the ordering invariants. Each fault is one line."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ArchiveError, CorruptArchiveError, LodbuilderError
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
                f"{where}: radius increases at position {i} ({radius[i - 1]!r} -> {radius[i]!r}); "
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
    return faults


def _check_scan(view: Any) -> list[str]:
    name, g = view.name, view._g
    where = f"scan {name!r}"
    faults: list[str] = []
    n, k = view.n_points, view.n_ordered
    # read every dataset in full: fletcher32 is verified on read
    data: dict[str, np.ndarray] = {}

    def visit(rel: str, obj: Any) -> None:
        import h5py

        if isinstance(obj, h5py.Dataset):
            try:
                data[rel] = view._read(obj)
            except CorruptArchiveError as exc:
                faults.append(str(exc))

    g.visititems(visit)
    for rel, arr in data.items():
        top = rel.split("/")[0]
        if top in (
            L.G_ATTRIBUTES,
            L.G_IMPORTANCE,
            L.D_POINTS,
            L.D_SOURCE_INDEX,
            L.D_RADIUS,
            L.D_PARENT,
        ) and arr.shape[:1] != (n,):
            faults.append(f"{where}: dataset {rel} has {arr.shape[0]} rows, expected n_points={n}")
    if faults:
        return faults
    if not 1 <= k <= n:
        faults.append(f"{where}: n_ordered={k} must be in [1, n_points={n}]")
        return faults
    src = data[L.D_SOURCE_INDEX]
    if not np.array_equal(np.sort(src), np.arange(n)):
        faults.append(f"{where}: source_index is not a permutation of 0..{n - 1}")
    radius, parent = data[L.D_RADIUS], data[L.D_PARENT]
    faults += _check_order_arrays(where, radius[:k], parent[:k])
    if k < n and ((radius[k:] != 0).any() or (parent[k:] != -1).any()):
        faults.append(f"{where}: points beyond n_ordered={k} must have radius 0 and parent -1")
    seeds = data.get(L.D_SEEDS)
    if seeds is not None and seeds.size and (seeds.min() < 0 or seeds.max() >= n):
        faults.append(f"{where}: seeds must be input indices in [0, {n})")
    for key in (L.S_BUILD, L.S_PROVENANCE, L.S_FORMAT_METADATA):
        try:
            L.from_json(g.attrs.get(key, ""))
        except ValueError as exc:
            faults.append(f"{where}: attribute {key!r} is not valid JSON ({exc})")
    step = view._step
    if not np.array_equal(data[L.D_RADIUS_INDEX], radius[::step]):
        faults.append(f"{where}: radius_index does not match radius[::{step}]; rebuild the archive")
    pts = view.points()
    if not np.isfinite(pts).all():
        faults.append(f"{where}: points hold NaN or inf")
    elif not (np.allclose(pts.min(0), view.bounds[0]) and np.allclose(pts.max(0), view.bounds[1])):
        faults.append(f"{where}: bounds_min/bounds_max attributes do not match the points")
    for rel, arr in data.items():
        parts = rel.split("/")
        if parts[0] == L.G_ORDERINGS and len(parts) == 3 and parts[2] == L.D_ORDER:
            oname = parts[1]
            ow = f"{where} ordering {oname!r}"
            rad = data.get(f"{L.G_ORDERINGS}/{oname}/{L.D_RADIUS}")
            par = data.get(f"{L.G_ORDERINGS}/{oname}/{L.D_PARENT}")
            if rad is None or par is None or not (arr.shape == rad.shape == par.shape):
                faults.append(f"{ow}: order, radius and parent must have the same length")
                continue
            if arr.size and (arr.min() < 0 or arr.max() >= n or np.unique(arr).size != arr.size):
                faults.append(f"{ow}: order must hold distinct positions in [0, {n})")
            faults += _check_order_arrays(ow, rad, par)
    return faults


def validate_archive(path: str | os.PathLike[str], *, schema: bool = True) -> list[str]:
    """All faults found in the archive at ``path`` (empty list: valid).

    Raises the usual one-line errors when ``path`` is missing or not an archive at all."""
    from .reader import open_archive
    from .schema import validate_description

    path = Path(path)
    faults: list[str] = []
    with open_archive(path) as arc:
        if schema:
            faults += validate_description(L.describe(arc.file))
        for name in arc.scans:
            try:
                view = arc.scan(name)
                if schema and view._g.file != arc.file:  # a scan in a part file of the archive
                    faults += [f"part of scan {name!r}: {x}" for x in validate_description(L.describe(view._g.file))]
                faults += _check_scan(view)
            except (LodbuilderError, KeyError, OSError, ValueError) as exc:
                faults.append(f"scan {name!r}: cannot be checked: {exc}")
        try:
            index = arc.index()
        except (OSError, KeyError) as exc:
            faults.append(f"index: cannot be read: {exc}")
            index = []
        names = [row["name"] for row in index]
        if names != arc.scans:
            faults.append(f"index: lists scans {names} but the archive holds {arc.scans}")
        else:
            for row in index:
                n = arc.scan(row["name"]).n_points
                if row["n_points"] != n:
                    faults.append(
                        f"index: scan {row['name']!r} has n_points {row['n_points']}, scan says {n}"
                    )
    return faults


def check_valid(path: str | os.PathLike[str]) -> None:
    """Raise CorruptArchiveError naming the first fault (and the count) if the archive is invalid."""
    faults = validate_archive(path)
    if faults:
        more = f" (and {len(faults) - 1} more)" if len(faults) > 1 else ""
        raise CorruptArchiveError(f"archive {path} is invalid: {faults[0]}{more}")


__all__ = ["validate_archive", "check_valid", "ArchiveError"]
