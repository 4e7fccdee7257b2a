"""Expand build inputs (files, directories, globs, manifests) into a list of scan sources.

A **manifest** is a text file listing scans, one per line, paths relative to the manifest:

    # comments and blank lines are ignored
    scans/a.ply                                   # no pose
    scans/b.laz  1 0 0 10  0 1 0 0  0 0 1 0  0 0 0 1   # a 4x4 matrix, row-major: world = M @ [p, 1]
    bmesh bun045.ply  tx ty tz  qx qy qz qw       # the Stanford bun.conf convention
    camera ...                                    # (bun.conf) ignored

``bmesh FILE tx ty tz qx qy qz qw`` means world = p @ R(q) + t with row vectors p, where R(q) is the
rotation matrix of the unit quaternion (x, y, z, w) (equivalently world = R(q)^T p + t). Paths may be
quoted. Files named ``*.conf``, ``*.manifest`` or ``*.lst`` given as inputs are read as manifests.

A 4x4 pose must be invertible (a singular matrix would collapse the scan onto a plane, a line or a
point): it is refused with the manifest line. A pose that is not rigid (its 3x3 part scales or
shears) is applied as given, with a warning naming the line and its scale factors, and the build
record of the scan says ``pose_kind: "affine"`` (``"rigid"`` otherwise).
"""

from __future__ import annotations

import glob
import logging
import os
import re
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import strict_keywords, strict_methods
from ..errors import InputError, ScanFileError
from ..io.pose import bmesh_pose, check_pose

log = logging.getLogger(__name__)

MANIFEST_SUFFIXES = (".conf", ".manifest", ".lst")


@strict_methods
@dataclass
class ScanSource:
    """One scan to build: a file (and, for multi-scan E57 files, which scan) with an optional pose,
    or an in-memory ``scan`` (then ``path`` is None).

    ``pose`` is a 4x4 matrix acting on column vectors: world = pose[:3, :3] @ p + pose[:3, 3].
    """

    path: Path | None
    name: str
    pose: np.ndarray | None = None
    scan_index: int | None = None
    scan: Any = None

    def describe(self) -> dict[str, Any]:
        return {"path": str(self.path), "name": self.name, "scan_index": self.scan_index,
                "pose": None if self.pose is None else self.pose.tolist()}


def _numbers(tokens: list[str], where: str) -> list[float]:
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        raise InputError(f"{where}: expected numbers after the file name, got {' '.join(tokens)!r}") from None
    if not all(np.isfinite(vals)):
        raise InputError(f"{where}: pose holds NaN or inf; fix the manifest")
    return vals


@strict_keywords
def read_manifest(path: str | os.PathLike[str]) -> list[tuple[Path, np.ndarray | None]]:
    """(file, pose) pairs listed in a manifest; see the module docstring for the format."""
    mpath = Path(path)
    if not mpath.is_file():
        raise ScanFileError(f"manifest {mpath}: no such file; check the path")
    base = mpath.parent
    out: list[tuple[Path, np.ndarray | None]] = []
    for lineno, raw in enumerate(mpath.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"manifest {mpath} line {lineno}"
        try:
            tokens = shlex.split(line)
        except ValueError as exc:
            raise InputError(f"{where}: {exc}; fix the quoting") from None
        if tokens[0] == "camera":
            continue
        if tokens[0] == "bmesh":
            if len(tokens) != 9:
                raise InputError(f"{where}: 'bmesh' needs FILE tx ty tz qx qy qz qw, got {len(tokens) - 1} fields")
            vals = _numbers(tokens[2:], where)
            out.append((base / tokens[1], bmesh_pose(vals[:3], vals[3:], where)))
            continue
        file, rest = tokens[0], tokens[1:]
        if not rest:
            out.append((base / file, None))
            continue
        if len(rest) != 16:
            raise InputError(f"{where}: a pose is 16 numbers (a row-major 4x4 matrix), got {len(rest)}")
        m = np.array(_numbers(rest, where)).reshape(4, 4)
        if not np.allclose(m[3], [0, 0, 0, 1]):
            raise InputError(f"{where}: the last row of the 4x4 pose must be 0 0 0 1, got {m[3].tolist()}")
        out.append((base / file, check_pose(m, where)))
    if not out:
        raise InputError(f"manifest {mpath} lists no scans; add one file per line")
    return out


_UNSAFE = re.compile(r"[^A-Za-z0-9_.+\-]+")


def safe_name(text: str) -> str:
    """A scan name from free text: no path separators or odd characters, not starting with '.'."""
    name = _UNSAFE.sub("_", text).strip("._") or "scan"
    return name[:200]


def scan_name(path: Path) -> str:
    """The one naming rule: a scan is named after its file, without the suffix (``.copc.laz``
    counts as one suffix), made safe (:func:`safe_name`)."""
    from ..io.base import file_stem

    return safe_name(file_stem(path))


def unique_names(names: list[str]) -> list[str]:
    """Make names unique by appending _2, _3, ... to repeats (the first occurrence keeps its name)."""
    used: set[str] = set()
    out = []
    for n in names:
        cand, k = n, 1
        while cand in used:
            k += 1
            cand = f"{n}_{k}"
        used.add(cand)
        out.append(cand)
    return out


def _has_magic(s: str) -> bool:
    return any(c in s for c in "*?[")


def _scan_files_in(directory: Path) -> list[Path]:
    from ..io.registry import READERS

    files = []
    for p in sorted(directory.rglob("*")):
        rel = p.relative_to(directory)
        if any(part.startswith(".") for part in rel.parts):
            continue  # hidden files and the build's own part files
        if p.is_file() and p.suffix.lower() in READERS:
            files.append(p)
    return files


def _e57_scan_names(path: Path) -> list[str] | None:
    """Names of the scans of an E57 file when it holds several, else None."""
    try:
        import pye57
    except ImportError:
        return None  # the reader reports the missing dependency when the job runs
    try:
        e = pye57.E57(str(path), mode="r")
    except Exception:
        return None  # a broken file fails in its job, with its cause
    try:
        count = e.scan_count
        if count <= 1:
            return None
        names = []
        for i in range(count):
            try:
                names.append(str(e.get_header(i).node["name"].value()))
            except Exception:
                names.append(str(i))
        return names
    finally:
        e.close()


@strict_keywords
def expand_inputs(inputs: Any = (), manifest: str | os.PathLike[str] | None = None) -> list[ScanSource]:
    """Scan sources from files, directories (recursive, hidden entries skipped), glob patterns and
    manifests, in the order given (directories and globs sorted). Names are the file stems, made
    safe and unique; an E57 file holding several scans gives one source per scan."""
    if isinstance(inputs, (str, Path)):
        inputs = [inputs]
    pairs: list[tuple[Path, np.ndarray | None]] = []
    for item in list(inputs or []):
        s = str(item)
        p = Path(s)
        if p.is_dir():
            found = _scan_files_in(p)
            if not found:
                raise InputError(f"directory {p} holds no scan files; known suffixes are listed by --help")
            pairs.extend((f, None) for f in found)
        elif p.is_file():
            if p.suffix.lower() in MANIFEST_SUFFIXES:
                pairs.extend(read_manifest(p))
            else:
                pairs.append((p, None))
        elif _has_magic(s) and not p.exists():
            hits = sorted(Path(h) for h in glob.glob(s, recursive=True) if Path(h).is_file())
            if not hits:
                raise InputError(f"pattern {s!r} matches no files; check the pattern (quote it in the shell)")
            pairs.extend((h, None) for h in hits)
        elif p.exists() or p.is_symlink():
            from ..io._files import check_input_file

            check_input_file(p)  # the reader's own message: a FIFO, a device, a symlink loop...
            pairs.append((p, None))
        else:
            raise ScanFileError(f"{p}: no such file or directory; check the path")
    if manifest is not None:
        pairs.extend(read_manifest(manifest))
    if not pairs:
        raise InputError("no input scans given; pass files, directories, globs or --manifest")
    sources: list[ScanSource] = []
    for path, pose in pairs:
        sub = _e57_scan_names(path) if path.suffix.lower() == ".e57" and path.is_file() else None
        if sub is None:
            sources.append(ScanSource(path=path, name=scan_name(path), pose=pose))
        else:
            sources.extend(ScanSource(path=path, name=safe_name(f"{scan_name(path)}-{n}"), pose=pose, scan_index=i)
                           for i, n in enumerate(sub))
    for src, name in zip(sources, unique_names([s.name for s in sources]), strict=True):
        src.name = name
    return sources
