"""What tests/test_archive_remote.py and tools/bench_remote.py (and tools/bench_append.py) share:
synthetic archives to serve, the bytes a level should fetch, and moto's S3 server with its request
recorder. The HTTP server is :class:`rangeserver.RangeServer`."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np


def synthetic_ordering(n: int, rng: np.random.Generator) -> Any:
    """A *synthetic* ``Ordering`` of n points: a random permutation, radius sqrt(1/(pi k)),
    random earlier parents (a level's cost depends on the stored layout only)."""
    from lodbuilder.sampling.ordering import Ordering

    k = np.arange(n, dtype=np.float64)
    radius = np.sqrt(1.0 / (np.pi * np.maximum(k, 1.0)))
    radius[0] = np.inf
    parent = np.floor(k * rng.random(n)).astype(np.int64)
    parent[0] = -1
    order = rng.permutation(n).astype(np.int64)
    return Ordering(order, radius, parent, 0.0, 0.0, order[:1].copy(), n, {"engine": "synthetic"})


def synthetic_record(n: int, name: str, seed: int = 0) -> Any:
    """A ``ScanRecord`` of a *synthetic* wavy scan with an intensity attribute and a
    :func:`synthetic_ordering`: this builds a 200k-point archive in a second."""
    from lodbuilder.archive.writer import ScanRecord
    from lodbuilder.datasets import demo_scan

    scan = demo_scan(n, kind="wavy", seed=seed, name=name)
    rng = np.random.default_rng(seed)
    scan.attributes["intensity"] = rng.random(n).astype(np.float32)
    return ScanRecord(scan, synthetic_ordering(n, rng))


def write_served(root: Path, n_one: int, parts: list[int] | tuple[int, ...]) -> list[Path]:
    """Write ``root/one.h5`` (one scan "big" of ``n_one`` points, a single file) and
    ``root/many.h5`` (scans s0, s1... of ``parts`` points, one part file each); returns every
    file written (what an S3 bucket must hold)."""
    from lodbuilder.archive.writer import update_archive, write_record

    one, many = root / "one.h5", root / "many.h5"
    write_record(one, synthetic_record(n_one, "big", 1))
    for i, n in enumerate(parts):
        update_archive(many, [synthetic_record(n, f"s{i}", 10 + i)])
    return [one, many, *sorted((root / "many.h5.scans").iterdir())]


def level_bytes(path: Path, name: str, k: int) -> float:
    """Stored bytes of the first k rows of the datasets a level reads (chunk bytes prorated)."""
    import h5py

    total = 0.0
    with h5py.File(path, "r") as f:
        g = f["scans"][name]
        keys = ["points", "source_index", "radius"] + [f"attributes/{a}" for a in g["attributes"]]
        for key in keys:
            ds = g[key]
            rows = ds.chunks[0]
            for start in range(0, k, rows):
                info = ds.id.get_chunk_info_by_coord((start,) + (0,) * (ds.ndim - 1))
                total += info.size * min(rows, k - start) / rows
    return total


def page_size(path: Path) -> int:
    """The file-space page size of the HDF5 file at ``path``."""
    import h5py

    with h5py.File(path, "r") as f:
        return int(f.id.get_create_plist().get_file_space_page_size())


class MotoS3:
    """moto's S3 server on 127.0.0.1 holding ``files`` (keys relative to ``root``) in ``bucket``;
    ``start()`` then ``recorded()`` return the requests made in between. ``recording``: the file
    moto's recorder writes (by default ./moto_recording)."""

    def __init__(self, root: Path, files: list[Path], bucket: str, recording: Path) -> None:
        import boto3
        from moto.server import ThreadedMotoServer

        os.environ["MOTO_RECORDER_FILEPATH"] = str(recording)
        self.server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
        self.server.start()
        host, port = self.server.get_host_and_port()
        self.endpoint = f"http://{host}:{port}"
        client = boto3.client(
            "s3",
            endpoint_url=self.endpoint,
            aws_access_key_id="test",
            aws_secret_access_key="test",
            region_name="us-east-1",
        )
        client.create_bucket(Bucket=bucket)
        for p in files:
            client.upload_file(str(p), bucket, str(p.relative_to(root)))
        self.options = {"endpoint_url": self.endpoint, "key": "test", "secret": "test"}

    def start(self) -> None:
        import requests

        requests.post(self.endpoint + "/moto-api/recorder/reset-recording")
        requests.post(self.endpoint + "/moto-api/recorder/start-recording")

    def recorded(self) -> list[dict[str, Any]]:
        import requests

        requests.post(self.endpoint + "/moto-api/recorder/stop-recording")
        text = requests.get(self.endpoint + "/moto-api/recorder/download-recording").text
        return [json.loads(line) for line in text.splitlines() if line.strip()]

    def stop(self) -> None:
        self.server.stop()
