"""Batch builds of many scans into one archive (process pool or Dask) and queries across scans.

    from lodbuilder.collection import build_collection, collection_level
    res = build_collection(["scans/"], "site.h5", workers=4)       # or dask_local=4 / scheduler=...
    lvl = collection_level("site.h5", rho=0.01)                   # every scan, with a scan_id

Dask is imported only when a scheduler or dask_local is given.
"""

from __future__ import annotations

from ..api import build_collection
from ..build.inputs import ScanSource, expand_inputs, read_manifest
from ..build.result import CollectionResult, ScanStatus
from .query import CollectionLevel, collection_level, list_scans, scan_level, total_points

__all__ = [
    "CollectionLevel", "CollectionResult", "ScanSource", "ScanStatus", "build_collection",
    "collection_level", "expand_inputs", "list_scans", "read_manifest", "scan_level", "total_points",
]
