"""One scan build as a self-contained job: what runs on a worker (a local process or a Dask worker).

``build_one(job)`` reads the scan, applies its pose, orders it with FastFPS and writes a one-scan
*part* archive with the archive writer (atomically: a killed worker leaves no part). The parent
merges finished parts into the collection archive. Workers need the part directory on a file
system they share with the parent (always true for a local pool or LocalCluster).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

@dataclass
class ScanJob:
    """Everything a worker needs to build one scan (picklable, no open handles)."""

    name: str
    path: str
    key: str
    part: str
    params: dict[str, Any] = field(default_factory=dict)
    pose: list[list[float]] | None = None
    scan_index: int | None = None
    sha256: str = ""
    size_bytes: int = 0


def job_key(sha256: str, params: dict[str, Any], pose: Any, scan_index: int | None, name: str) -> str:
    """Hash of everything that determines a built scan: source bytes, parameters, pose, scan index, name."""
    from .. import __version__

    payload = {
        "sha256": sha256,
        "params": {k: params.get(k) for k in sorted(params)},
        "pose": None if pose is None else np.asarray(pose, dtype=np.float64).round(15).tolist(),
        "scan_index": scan_index,
        "name": name,
        "schema": 1,
        "lodbuilder": __version__.split("+")[0],
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _read(job: ScanJob) -> Any:
    from ..io import read_scan, read_scans

    if job.scan_index is None:
        return read_scan(job.path, name=job.name)
    scans = read_scans(job.path)
    scan = scans[job.scan_index]
    scan.name = job.name
    return scan


def build_one(job: ScanJob) -> dict[str, Any]:
    """Build ``job`` into its part archive; return a summary (runs on a worker)."""
    from ..archive.writer import ScanRecord, write_archive
    from ..sampling.fastfps import fastfps
    from .inputs import apply_pose

    t0 = time.perf_counter()
    scan = _read(job)
    t_read = time.perf_counter() - t0
    if job.pose is not None:
        scan.points = np.ascontiguousarray(apply_pose(scan.points, np.asarray(job.pose)))
    p = job.params
    features = {k: v for k, v in (p.get("features") or {}).items() if v is not None}
    t1 = time.perf_counter()
    if p.get("size") is None and p.get("rho") is None:
        # the same path as a single-scan build (feature options included)
        from ..api import build_record

        rec = build_record(scan, voxel_size=p.get("voxel_size"), band_radius=p.get("band_radius"), **features)
        scan, ordering = rec.scan, rec.ordering
    else:
        size = None if p.get("size") is None else min(int(p["size"]), len(scan))
        ordering = fastfps(scan.points, voxel_size=p.get("voxel_size"), band_radius=p.get("band_radius"),
                           size=size, rho=p.get("rho"))
        rec = ScanRecord(scan=scan, ordering=ordering)
    t_order = time.perf_counter() - t1
    build = {
        "voxel_size_requested": p.get("voxel_size"),
        "band_radius_requested": p.get("band_radius"),
        "size_requested": p.get("size"),
        "rho_requested": p.get("rho"),
        "pose": job.pose,
        "scan_index": job.scan_index,
        "collection_key": job.key,
        "seconds_read": round(t_read, 4),
        "seconds_order": round(t_order, 4),
        "worker_pid": os.getpid(),
    }
    prov = {
        "source_name": Path(job.path).name,
        "source_size": job.size_bytes,
        "source_sha256": job.sha256,
        "reader": scan.reader,
    }
    rec.build.update(build)
    rec.provenance.update(prov)
    write_archive(job.part, [rec])
    return {
        "name": job.name,
        "part": job.part,
        "n_points": len(scan),
        "n_ordered": len(ordering),
        "seconds": round(time.perf_counter() - t0, 4),
        "seconds_order": round(t_order, 4),
        "worker_pid": os.getpid(),
    }
