"""The tables of our COPC EVLRs beside the points: the insertion radius by rank
(``rank_radius="exact"``) and the sub-levels of every depth (``rank_radius="level"``), with
their readers. See :mod:`lodbuilder.export.copc`."""

from __future__ import annotations

import os

import numpy as np

from ..errors import InputError

#: our EVLR
VLR_USER_ID = "lodbuilder"
VLR_RECORD_ID = 1
VLR_DESCRIPTION = "farthest-point levels per depth"
#: our EVLR of the insertion radius by rank (with rank_radius)
RADIUS_RECORD_ID = 2
RADIUS_DESCRIPTION = "insertion radius by rank"
#: our EVLR of the sub-levels of every depth (with rank_radius="level")
SUBLEVEL_RECORD_ID = 3
SUBLEVEL_DESCRIPTION = "sub-levels: prefix and rho"
#: at most this many sub-levels a depth (the extra byte ``sublevel`` is a uint8)
SUBLEVELS = 256
#: what ``rank_radius`` may be (None: neither)
RANK_RADIUS_MODES = ("level", "exact")
#: one row of the sub-level table (stored column after column)
SUBLEVEL_DTYPE = np.dtype([("depth", "u1"), ("sublevel", "u1"), ("prefix", "<u8"),
                           ("points", "<u8"), ("rho", "<f8")])
_COLUMNS = ("depth", "sublevel", "prefix", "points", "rho")


def check_rank_radius(mode: str | None) -> str | None:
    """``mode`` (None, "level" or "exact") or InputError naming the choices."""
    if mode is None or (isinstance(mode, str) and mode in RANK_RADIUS_MODES):
        return mode
    raise InputError(f"rank_radius must be 'level' (one byte a point: {SUBLEVELS} sub-levels a depth, "
                     f"each with its covering radius) or 'exact' (each point's rank and the radius "
                     f"by rank), got {mode!r}")


def sublevels(band: np.ndarray, depth: np.ndarray, bounds: np.ndarray,
              rho: float) -> tuple[np.ndarray, np.ndarray]:
    """(sublevel of each point, table): depth d's band, the positions [a, b) of the ordering,
    cut into S = min(SUBLEVELS, b - a) runs of equal count ending at ``a + (s + 1)(b - a) // S``;
    a point's sublevel is the run its position falls in (0 for a point moved up to keep the
    octree connected). The points of depths < D and those of depth D with sublevel <= s are
    then the prefix that ends at the run's end plus the points moved up into depths <= D, and
    ``bounds[end]`` (``rho`` for the whole level) covers the scan: the table's row (depth,
    sublevel, prefix, points, rho) says so, one row per run, in file order."""
    k = band.size
    sub = np.zeros(k, dtype=np.uint8)
    rows: list[tuple[int, int, int, int, float]] = []
    for d in range(int(depth.max()) + 1):
        a, b = int(np.count_nonzero(band < d)), int(np.count_nonzero(band <= d))
        m = b - a
        runs = max(1, min(SUBLEVELS, m))
        ends = a + (np.arange(1, runs + 1, dtype=np.int64) * m) // runs
        pos = np.arange(a, b)
        own = depth[a:b] == d
        sub[pos[own]] = np.searchsorted(ends, pos[own], side="right")
        above = int(np.count_nonzero(depth < d))  # (moved points of later bands included)
        at = np.cumsum(np.bincount(sub[depth == d], minlength=runs))
        for s, end in enumerate(ends.tolist()):
            rows.append((d, s, end, above + int(at[s]),
                         float(bounds[end]) if end < k else float(rho)))
    table = np.array(rows, dtype=SUBLEVEL_DTYPE)
    return sub, table


def sublevel_payload(table: np.ndarray) -> bytes:
    """Our EVLR record SUBLEVEL_RECORD_ID: zlib of the table's columns, one after the other
    (depth uint8, sublevel uint8, prefix uint64, points uint64, rho float64; little-endian)."""
    import zlib

    return zlib.compress(b"".join(np.ascontiguousarray(table[c]).tobytes()
                                  for c in _COLUMNS), 9)


def read_sublevels(path: str | os.PathLike) -> np.ndarray:
    """The sub-levels that ``write_copc(..., rank_radius="level")`` stored: a structured array
    with, per depth and sub-level (file order), ``prefix`` (the farthest-point prefix that
    ends there), ``points`` (what a reader keeps: the points of depths < depth and those of
    this depth with sublevel <= sublevel) and ``rho`` (their covering radius: the archive's
    radius at ``prefix``). Needs laspy; raises InputError when the file has none."""
    import zlib

    import laspy

    with laspy.open(str(path)) as reader:
        found = [v for v in reader.header.evlrs
                 if v.user_id == VLR_USER_ID and v.record_id == SUBLEVEL_RECORD_ID]
    if not found:
        raise InputError(f"{path} has no sub-level table; export it with --rank-radius level")
    raw = zlib.decompress(found[0].record_data)
    n = len(raw) // SUBLEVEL_DTYPE.itemsize
    table = np.empty(n, dtype=SUBLEVEL_DTYPE)
    at = 0
    for c in _COLUMNS:
        size = n * SUBLEVEL_DTYPE[c].itemsize
        table[c] = np.frombuffer(raw[at:at + size], dtype=SUBLEVEL_DTYPE[c])
        at += size
    return table


def radius_table(rank: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, bytes]:
    """(table, payload): the insertion radius by rank (ranks 0..max(rank); NaN for a rank not
    in the file), as float32 rounded up (an upper bound stays one), and the payload of our
    EVLR record RADIUS_RECORD_ID: zlib of the little-endian int32 differences of the table's
    float32 bit patterns (radii never increase along the ranks, so the differences are small:
    0.3-1.3 bytes a point; per-point float64 extra bytes cost 6.9, float32 3.2)."""
    import zlib

    r32 = radius.astype(np.float32)
    low = r32.astype(np.float64) < radius
    r32[low] = np.nextafter(r32[low], np.float32(np.inf))
    table = np.full(int(rank.max()) + 1, np.nan, dtype=np.float32)
    table[rank] = r32
    bits = table.view(np.uint32).astype(np.int64)
    diff = np.diff(bits, prepend=np.int64(0)).astype("<i4")
    return table, zlib.compress(diff.tobytes(), 6)  # (level 9: 10x the time for 6 % less)


def read_radius_table(path: str | os.PathLike) -> np.ndarray:
    """The insertion radius by rank that ``write_copc(..., rank_radius="exact")`` stored (float32,
    rounded up; NaN for ranks not in the file): ``read_radius_table(f)[las["rank"]]`` is each
    point's radius. Needs laspy; raises InputError when the file has no such table."""
    import zlib

    import laspy

    with laspy.open(str(path)) as reader:
        found = [v for v in reader.header.evlrs
                 if v.user_id == VLR_USER_ID and v.record_id == RADIUS_RECORD_ID]
    if not found:
        raise InputError(f"{path} has no radius table; export it with --rank-radius exact")
    diff = np.frombuffer(zlib.decompress(found[0].record_data), dtype="<i4")
    return np.cumsum(diff, dtype=np.int64).astype(np.uint32).view(np.float32)
