"""Build small valid archives and edit them into hostile or damaged ones (for the safety tests)."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np

SCAN = "wavy"
N = 300


def make_archive(path: Path) -> Path:
    """A valid 300-point archive with one scan 'wavy' (normals, colours and a uint16 intensity)."""
    import lodbuilder
    from lodbuilder.archive.writer import ScanRecord, update_archive
    from lodbuilder.datasets import demo_scan

    scan = demo_scan(N, seed=3, name=SCAN)
    scan.attributes["intensity"] = np.arange(N, dtype=np.uint16) * 7
    ordg = lodbuilder.fastfps(scan.points)
    update_archive(path, [ScanRecord(scan, ordg, provenance={"source_name": "gen.ply"})])
    return path


def small_ply(path: Path) -> Path:
    """A binary PLY of 100 random points (x, y, z only), written by hand: an input to build into
    a damaged or hostile archive."""
    rows = np.random.default_rng(0).random((100, 3)).astype("<f4")
    head = "ply\nformat binary_little_endian 1.0\nelement vertex 100\n"
    head += "".join(f"property float {c}\n" for c in "xyz") + "end_header\n"
    path.write_bytes(head.encode() + rows.tobytes())
    return path


def copy(src: Path, dst: Path) -> Path:
    shutil.copyfile(src, dst)
    return dst


def _replace(f: h5py.File, rel: str) -> tuple[h5py.Group, str, h5py.Dataset | None]:
    parent, name = rel.rsplit("/", 1)
    g = f[parent]
    old = g[name][()] if name in g and isinstance(g[name], h5py.Dataset) else None
    if name in g:
        del g[name]
    return g, name, old


def external_storage(
    arc: Path, target: str | Path, rel: str = f"scans/{SCAN}/attributes/intensity"
):
    """Store dataset ``rel`` as HDF5 external raw storage in ``target`` (e.g. /etc/passwd)."""
    with h5py.File(arc, "r+") as f:
        g, name, old = _replace(f, rel)
        shape = old.shape if old is not None else (N,)
        dtype = old.dtype if old is not None else np.uint8
        nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        g.create_dataset(name, shape=shape, dtype=dtype, external=[(str(target), 0, nbytes)])


def external_link(arc: Path, target_file: str | Path, target_obj: str, rel: str) -> None:
    """Replace ``rel`` with an HDF5 external link to ``target_obj`` in ``target_file``."""
    with h5py.File(arc, "r+") as f:
        g, name, _ = _replace(f, rel)
        g[name] = h5py.ExternalLink(str(target_file), target_obj)


def virtual(arc: Path, source_file: str | Path, source_obj: str, rel: str) -> None:
    """Replace ``rel`` with a virtual dataset mapping ``source_obj`` of ``source_file``."""
    with h5py.File(arc, "r+") as f:
        g, name, old = _replace(f, rel)
        shape = old.shape if old is not None else (N,)
        dtype = old.dtype if old is not None else np.uint8
        layout = h5py.VirtualLayout(shape=shape, dtype=dtype)
        layout[...] = h5py.VirtualSource(str(source_file), source_obj, shape=shape)
        g.create_virtual_dataset(name, layout)


def foreign_file(path: Path, n: int = N, dtype=np.uint16) -> Path:
    """An HDF5 file that is not the archive's, holding /data of n values."""
    with h5py.File(path, "w") as f:
        f["data"] = (np.arange(n) % 251).astype(dtype)
        f["points"] = np.zeros((n, 3), dtype=np.float32)
    return path


def edit(arc: Path, fn) -> None:
    """Apply ``fn(scan_group, file)`` to the archive in place."""
    with h5py.File(arc, "r+") as f:
        fn(f[f"scans/{SCAN}"], f)


def rewrite(g: h5py.Group, rel: str, data, **kw) -> None:
    """Replace dataset ``rel`` of ``g`` with ``data`` (checksummed, so only the value is wrong)."""
    from lodbuilder.archive import layout as L

    parent, name = rel.rsplit("/", 1) if "/" in rel else ("", rel)
    grp = g[parent] if parent else g
    del grp[name]
    L.create_dataset(grp, name, np.asarray(data), **kw)


def vlen_strings(arc: Path) -> Path:
    """Store every text attribute as a variable-length string, as lodbuilder 0.1 wrote them
    (schema 1 archives): their bytes then live in a global heap collection (no checksum)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "lodbuilder_fuzz", Path(__file__).resolve().parents[1] / "tools" / "fuzz.py"
    )
    assert spec is not None and spec.loader is not None
    fuzz = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fuzz)
    return fuzz.variable_length_strings(arc)
