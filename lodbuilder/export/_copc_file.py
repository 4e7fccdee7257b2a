"""The bytes of a COPC 1.0 file, written here with laspy (header, VLRs) and lazrs (one LAZ chunk
per octree node), so that every detail of the 1.0 specification is ours to keep
(https://copc.io, "Cloud Optimized Point Cloud Specification 1.0"):

* the LAS 1.4 header (point format 6, 7 or 8, global-encoding WKT bit set), then the ``copc``
  info VLR (record 1, 160 bytes) first, at offset 375, with the GPS-time range filled;
* the ``laszip encoded`` VLR of variable-size chunks, the extra-bytes VLR and the CRS as an OGC
  WKT VLR (LASF_Projection 2112: readers such as laspy's CopcReader look there);
* the points: one variable-size LAZ chunk per node, in the order given (breadth-first), then the
  LAZ chunk table;
* EVLRs: the hierarchy (``copc``, record 1000: one page, 32 bytes a node) and the caller's.

No legacy ``copc``/10000 extents VLR (the draft had one; 1.0 removed it).
"""

from __future__ import annotations

import io
import struct
from dataclasses import dataclass
from typing import Any, BinaryIO

import numpy as np

#: the LAS 1.4 header size: the COPC info VLR starts right after it
HEADER_SIZE = 375
_INFO = struct.Struct("<5d2Q2d11Q")  # 160 bytes
_ENTRY = struct.Struct("<4iQii")  # 32 bytes a hierarchy entry
_LAZ_USER, _LAZ_RECORD = "laszip encoded", 22204


@dataclass(frozen=True)
class Octree:
    """The cube of the octree (actual coordinates) and the point spacing at its root."""

    center: tuple[float, float, float]
    halfsize: float
    spacing: float


def info_bytes(octree: Octree, root_offset: int, root_size: int, gps: tuple[float, float]) -> bytes:
    """The 160 bytes of the COPC info VLR (reserved words 0)."""
    return _INFO.pack(
        *octree.center, octree.halfsize, octree.spacing, root_offset, root_size, gps[0], gps[1],
        *([0] * 11),
    )


def compress_nodes(records: np.ndarray, starts: np.ndarray, ends: np.ndarray,
                   point_format: int, n_extra_bytes: int) -> tuple[Any, bytes, np.ndarray]:
    """(laszip VLR, LAZ point data, (M,) compressed size of each node): one variable-size chunk
    per node ``records[starts[i]:ends[i]]``, compressed on every core by lazrs. The point data
    begins with the 8-byte chunk-table offset, relative to its own start (the caller adds the
    file offset)."""
    import lazrs

    vlr = lazrs.LazVlr.new_for_compression(int(point_format), int(n_extra_bytes), True)
    raw = records.view(np.uint8).reshape(records.shape[0], -1)
    chunks = [raw[s:e].tobytes() for s, e in zip(starts, ends, strict=True)]
    dest = io.BytesIO()
    compressor = lazrs.ParLasZipCompressor(dest, vlr)
    compressor.reserve_offset_to_chunk_table()
    compressor.compress_chunks(chunks)
    compressor.done()
    data = dest.getvalue()
    table = lazrs.read_chunk_table(io.BytesIO(data), vlr)
    sizes = np.array([b for _, b in table], dtype=np.int64)
    counts = np.array([c for c, _ in table], dtype=np.int64)
    if sizes.size != len(chunks) or not np.array_equal(counts, ends - starts):
        raise RuntimeError(f"lazrs wrote {sizes.size} chunks for {len(chunks)} nodes")
    return vlr, data, sizes


def write_copc_file(
    f: BinaryIO,
    header: Any,
    records: np.ndarray,
    keys: np.ndarray,
    starts: np.ndarray,
    ends: np.ndarray,
    octree: Octree,
    gps: tuple[float, float],
    wkt: str | None,
    evlrs: list[Any],
) -> None:
    """Write a COPC file to ``f`` (at its position 0): ``header`` is a laspy LAS 1.4 header
    (scales, offsets, bounds, point counts and extra dimensions already set), ``records`` the
    point records sorted by node, node i being ``records[starts[i]:ends[i]]`` with voxel key
    ``keys[i]`` = (depth, x, y, z), nodes breadth-first; ``evlrs`` laspy VLRs written after the
    hierarchy."""
    import laspy
    from laspy.vlrs.known import WktCoordinateSystemVlr
    from laspy.vlrs.vlrlist import VLRList

    n_extra = header.point_format.num_extra_bytes
    laz_vlr, points, sizes = compress_nodes(records, starts, ends, header.point_format.id, n_extra)
    extra = [v for v in header.vlrs if type(v).__name__ == "ExtraBytesVlr"]
    vlrs = [laspy.VLR("copc", 1, "copc info", info_bytes(octree, 0, 0, gps)),
            laspy.VLR(_LAZ_USER, _LAZ_RECORD, "lazrs variable size chunks", laz_vlr.record_data()),
            *extra]
    if wkt:
        vlrs.append(WktCoordinateSystemVlr(wkt))
    header.vlrs = VLRList(vlrs)
    for vlr in header.vlrs:  # the extra bytes' min and max, as laspy's own writer fills them
        if type(vlr).__name__ == "ExtraBytesVlr":
            vlr.partial_reset()
            vlr.grow(laspy.PackedPointRecord(records, header.point_format))
    header.global_encoding.wkt = True
    header.are_points_compressed = True
    with io.BytesIO() as tmp:
        header.write_to(tmp)
        head_len = len(tmp.getvalue())
    start = head_len  # offset to point data
    node_offsets = start + 8 + np.concatenate([[0], np.cumsum(sizes)[:-1]])
    hier_start = start + len(points)
    entries = b"".join(
        _ENTRY.pack(*map(int, keys[i]), int(node_offsets[i]), int(sizes[i]), int(ends[i] - starts[i]))
        for i in range(keys.shape[0])
    )
    evlr_header = 60
    header.vlrs[0] = laspy.VLR(
        "copc", 1, "copc info", info_bytes(octree, hier_start + evlr_header, len(entries), gps)
    )
    header.start_of_first_evlr = hier_start
    header.number_of_evlrs = 1 + len(evlrs)
    header.write_to(f, ensure_same_size=False)
    if f.tell() != start:
        raise RuntimeError("COPC header size changed while writing")
    (table_offset,) = struct.unpack("<q", points[:8])
    f.write(struct.pack("<q", table_offset + start))
    f.write(memoryview(points)[8:])
    VLRList([laspy.VLR("copc", 1000, "EPT hierarchy", entries), *evlrs]).write_to(f, as_extended=True)
