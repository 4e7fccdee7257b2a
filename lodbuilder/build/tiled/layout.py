"""The work directory of a tiled build, in one place: every file's name and record layout, the
markers of finished pieces, and the named moments at which tests stop a build.

Files (little-endian raw arrays unless said otherwise; *zipped*: compressed with zstandard, read
whole or from the start only, see :class:`.workdir.Zipped`), by the phase that writes them::

    inputs      (a marker only)     the read blocks: input, row range, first input index of each
    read        raw.<b>.xyz         block b's (m, 3) float64 coordinates in input order (poses applied; zipped;
                                    the attributes are not copied: the write reads the inputs again)
                sample.<b>.f64      block b's points whose input index is a multiple of the sample step
    spill       sample.npy          the sample of the whole scan (for the plan's spacing), in input order
    plan        decimated.bin       the decimated copy (one point per grid cell): REC records
    distribute  core.<t>.<b>.bin    the points of tile t from block b: REC records (g, x, y, z), g the input index (zipped)
                halo.<t>.<b>.bin    block b's REC records within the halo width of tile t owned by others (zipped)
    coarse      head.bin            HEAD records: the coarse global level (the head)
    order       stream.<t>.keys     KEYS records: tile t's ordering (input index, key; zipped in frames of
                                    rows within one key bin each, see workdir.put_stream)
                seam.<t>.bin        STREAM records (input index, key, position, margin): the rows of tile
                                    t's ordering nearer a shared face than their key
                face.<t>.<p>.bin    FACE records: tile t's points near its shared faces after pass p
                bandp.<t>.i4        the band piece of each of tile t's core points (int32, core order; zipped):
                                    its ordering's band on the scan's grid (see pieces.py; not with seam rounds)
    merge       links.<j>.bin       LINK records: the seam points that group j of tiles found may meet another
                                    tile's (see merge.py: the only ones the seam repair merges)
                deferred.bin        DEFER records: the seam points the repair deferred, in merged order (seams)
                dropped.bin         DEFER records: the same points with the keys their tiles gave them, by
                                    descending key (the rows each band of the merge leaves out: a slice)
                merged.<j>.i8       piece j of the merged order (input indices; zipped in frames of rows,
                                    see workdir.put_framed): the head, then band j's
    ranks       rankp.<k>.bin       band k of the merged order as (input index, position) pairs by read block
                                    (PAIR records; removed when the phase is complete)
                rank.<b>.i8         the position of every input point of read block b (see ranks.py)
    cover       cover.<t>.ev/.pt    EVENT / POINT records of tile t's covering pass (banded: zipped in
                                    frames of the radii's bands of ranks, see workdir.put_banded)
    radii       radloc.<b>.f8       band b's radii, non-increasing within the band (round 1; zipped)
                space.<b>.f8        band b's running minimum of the spacing (round 1; zipped)
                parent.<b>.i8       the stored parent of each position of band b (framed, as merged.<j>)
                radius.<b>.f8       the stored radius of each position of band b (round 2; framed)
    buckets     bucket.<k0>_<k1>.<b>.bin  buckets k0 .. k1 of the external permutation from read block b,
                                    one zstd frame per bucket's piece (see write.py; at most
                                    BUCKET_FILES per block; after the radii and the pieces, once the
                                    covering files and the tiles' points are deleted)
    write       chunks.<k>.bin      band k's rows as finished HDF5 chunks, one after another (see bands.py)

A finished phase or tile task leaves a marker ``<piece>.json`` (:func:`marker`) that lists the files
it wrote with their size and CRC-32 (:mod:`.sums`); a resumed build trusts a piece only when its
marker and files check out. Every file is written to a temporary and renamed into place, not
flushed to the device: the checksums stand in (:mod:`lodbuilder._atomic`, work files).

A large file is deleted once every piece that reads it is done (:data:`PRUNE_AFTER`: when the
marker of the last one is written; a read block's coordinates once the tiles' pieces are written,
a bucket file once the bands of the write it holds are, a read block's ranks once its permutation
is), so that the work
directory holds only what later phases still read. Its producer's marker still lists it: a missing
file checks out while every piece that reads it (:func:`consumers`) checks out, so a resume that
finds one of those damaged or gone does its producer again too (the same bytes).
"""

from __future__ import annotations

import os
import signal

import numpy as np

# ------------------------------------------------------------------------------------ records

#: a point of a tile or of its halo: input index and coordinates
REC = np.dtype([("g", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
#: one row of a tile's ordering stream: input index, key (insertion radius), position, margin
STREAM = np.dtype([("g", "<f8"), ("key", "<f8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("m", "<f8")])
#: a row of a tile's stream as the merge's bands read it (stream.<t>.keys): input index and key
KEYS = np.dtype([("g", "<i8"), ("key", "<f8")])
#: a point of the head: input index, position, radius on the decimated copy, parent
HEAD = np.dtype([("g", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "<f8"), ("parent", "<i8")])
#: a tile's point near its shared faces, by input index, with its key
FACE = np.dtype([("g", "<i8"), ("key", "<f8")])
#: a covering event (the covering radius of the prefix of ``rank`` points rises to ``value``)
EVENT = np.dtype([("rank", "<i8"), ("value", "<f8")])
#: a point's rank, parent and spacing as the covering pass finds them
POINT = np.dtype([("rank", "<i8"), ("parent", "<i8"), ("space", "<f8")])

#: the bins of :func:`key_bins` and :func:`hist_bins` for an infinite key and for a key of zero
BIN_INF, BIN_ZERO = 1 << 40, -(1 << 40)


def key_bins(key: np.ndarray) -> np.ndarray:
    """The bin of each key (>= 0): eight bins per octave, a larger key never in a smaller bin.
    Exact (binary exponent and the mantissa's top three bits), so every process bins a key alike:
    a tile's stream is framed within these bins (:func:`.workdir.put_stream`)."""
    return _bins(key, 3)


def hist_bins(key: np.ndarray) -> np.ndarray:
    """:func:`key_bins` split in eight (64 bins per octave; ``hist_bins(k) // 8 == key_bins(k)`` for
    a finite key above zero): a tile's histogram of its stream's keys in these bins tells which
    rows of the stream each band of the merge reads (:mod:`.merge`), and a band takes whole bins,
    so the finest key bin of a survey (2.0M rows, 9 % of the 21.56M-point survey's) is no longer
    one band of its own."""
    return _bins(key, 6)


def key_hist(key: np.ndarray) -> list[list[int]]:
    """The keys' histogram in :func:`hist_bins`: ``[bins (ascending), counts]`` (as markers hold it)."""
    bins, counts = np.unique(hist_bins(key), return_counts=True)
    return [bins.tolist(), counts.tolist()]


def hist_ceiling(b: int) -> float:
    """A key above every key of :func:`hist_bins`'s bin ``b`` (0 for the bin of zero keys, inf for
    the infinite ones')."""
    if b == BIN_ZERO:
        return 0.0
    if b == BIN_INF:
        return float("inf")
    return float(np.ldexp(0.5 + ((b & 63) + 1) / 128, b >> 6))


def _bins(key: np.ndarray, bits: int) -> np.ndarray:
    """2^bits bins per octave: the binary exponent and the mantissa's top ``bits`` bits (exact)."""
    k = np.asarray(key, np.float64)
    if k.size and not (k >= 0).all():
        raise RuntimeError("a merge key is negative or NaN")
    inf = np.isinf(k)
    m, e = np.frexp(np.where(inf, 1.0, k))  # k = m * 2**e, m in [0.5, 1)
    b = (e.astype(np.int64) << bits) + np.floor((m - 0.5) * (2 << bits)).astype(np.int64)
    b[inf] = BIN_INF
    b[k == 0] = BIN_ZERO
    return b


# ------------------------------------------------------------------------------------ names

DECIMATED = "decimated.bin"
SAMPLE = "sample.npy"
HEAD_FILE = "head.bin"
#: the merge's deferred seam points, in merged order: input index, acceptance key
DEFERRED = "deferred.bin"
DEFER = np.dtype([("g", "<i8"), ("key", "<f8")])
#: the deferred seam points by their keys in their tiles (descending): input index, that key
DROPPED = "dropped.bin"
#: a seam point the seam repair merges: its tile, its row in the tile's seam file, and that row
LINK = np.dtype([("t", "<i8"), ("row", "<i8"), *STREAM.descr])

#: the phases, in order; each leaves the marker ``<phase>.json`` when complete
PHASES = ("inputs", "spill", "plan", "distribute", "coarse", "order", "merge", "ranks", "radii", "buckets")


def attr_record(fields: dict[str, tuple[str, tuple[int, ...]]]) -> np.dtype:
    """The record of a raw block's attribute file: field ``a<i>`` holds attribute i of ``fields``."""
    return np.dtype([(f"a{i}", dt, tuple(shape)) if shape else (f"a{i}", dt)
                     for i, (dt, shape) in enumerate(fields.values())])


def raw_xyz(b: int) -> str:
    return f"raw.{b}.xyz"


def raw_attr(b: int) -> str:
    return f"raw.{b}.attr"


def sample(b: int) -> str:
    return f"sample.{b}.f64"


def core(t: int, b: int) -> str:
    return f"core.{t}.{b}.bin"


def halo(t: int, b: int) -> str:
    return f"halo.{t}.{b}.bin"


def read_piece(b: int) -> str:
    """The piece name of reading block ``b`` (a read task)."""
    return f"read.{b}"


def split_piece(b: int) -> str:
    """The piece name of cutting block ``b`` into the tiles' pieces (a distribute task)."""
    return f"split.{b}"


def stream(t: int) -> str:
    return f"stream.{t}.keys"


def seam(t: int) -> str:
    """Tile ``t``'s seam points (stream rows nearer a shared face than their key), in stream order."""
    return f"seam.{t}.bin"


def band_labels(t: int) -> str:
    """Tile ``t``'s core points' pieces of its ordering's band (see :mod:`.pieces`)."""
    return f"bandp.{t}.i4"


def merged(j: int) -> str:
    """Piece ``j`` of the merged order (input indices; piece 0 the head, then one per key band)."""
    return f"merged.{j}.i8"


def merged_piece(j: int) -> str:
    """The piece name of band ``j`` of the merge (a task; ``seams``: the seam points' merge)."""
    return f"merged.{j}"


SEAMS_PIECE = "seams"


def links(j: int) -> str:
    """Group ``j`` of tiles' seam points that may meet another tile's (see :func:`.merge.seam_links`)."""
    return f"links.{j}.bin"


def links_piece(j: int) -> str:
    """The piece name of group ``j``'s seam links (a task)."""
    return f"links.{j}"


def face(t: int, p: int) -> str:
    return f"face.{t}.{p}.bin"


def cover_events(t: int) -> str:
    return f"cover.{t}.ev"


def cover_points(t: int) -> str:
    return f"cover.{t}.pt"


def bucket(k0: int, k1: int, b: int) -> str:
    """The pieces of destination buckets ``k0 .. k1`` (a run of consecutive ones) from raw block
    ``b``: one zstd frame per piece (see write.py)."""
    return f"bucket.{k0}_{k1}.{b}.bin"


def bucket_range(name: str) -> range:
    """The destination buckets whose pieces the bucket file ``name`` holds."""
    k0, k1 = name.split(".")[1].split("_")
    return range(int(k0), int(k1))


def bucket_piece(b: int) -> str:
    """The piece name of splitting raw block ``b`` into the buckets (a task)."""
    return f"permute.{b}"


def rank_pairs(k: int) -> str:
    """Band ``k`` of the merged order as (input index, position) pairs sorted by read block."""
    return f"rankp.{k}.bin"


def rank_pairs_piece(k: int) -> str:
    return f"rankp.{k}"


def rank_file(b: int) -> str:
    """The position of every input point of read block ``b``, in input order."""
    return f"rank.{b}.i8"


def rank_piece(b: int) -> str:
    return f"rank.{b}"


def chunks(k: int) -> str:
    """Band ``k`` of the write: its rows' filtered HDF5 chunks (see :mod:`.bands`)."""
    return f"chunks.{k}.bin"


def chunks_piece(k: int) -> str:
    """The piece name of band ``k`` of the write (a task)."""
    return f"chunks.{k}"


def order_piece(t: int, p: int) -> str:
    """The piece name of tile ``t``'s ordering in pass ``p`` (its marker is :func:`marker` of it)."""
    return f"order.{t}.{p}"


def radius_local(b: int) -> str:
    return f"radloc.{b}.f8"


def space(b: int) -> str:
    return f"space.{b}.f8"


def parent(b: int) -> str:
    return f"parent.{b}.i8"


def radius(b: int) -> str:
    return f"radius.{b}.f8"


def band_piece(b: int) -> str:
    """The piece name of round 1 of band ``b`` of the radii (a task)."""
    return f"band.{b}"


def cover_piece(t: int) -> str:
    return f"cover.{t}"


def task_log(pid: int | str) -> str:
    """A worker's log of the tasks it ran (one JSON line each: see :mod:`.timing`)."""
    return f"tasks.{pid}.jsonl"


def marker(piece: str) -> str:
    """The marker file of a finished phase or task."""
    return f"{piece}.json"


def writing(name: str) -> str:
    """The name a file has while a phase writes it (published onto ``name`` when complete)."""
    return f"{name}.tmp"


# ------------------------------------------------------------------------------------ pruning

#: the files deleted when a phase's marker is written (name prefixes; markers are never deleted):
#: (those of the prefix whose consumers include the phase): after the spill, the read blocks'
#: samples (summed into sample.npy); after the plan, sample.npy; after every
#: tile's ordering (the ``order`` marker: every ordering's marker, stream and seam points), the
#: face files; after the merge, the tiles' streams, seam points and links and the deferred (and dropped) points; after the
#: split into tiles (the last phase to read them), the read blocks' coordinates; after the pieces
#: (the last phase to read a tile's points), the tiles' core and halo;
#: after the radii, the covering passes' files and the radii's first round
PRUNE_AFTER = {"spill": ("sample.",), "plan": ("sample.",), "order": ("face.",), "merge": ("stream.", "seam.", "links.", "deferred.", "dropped."),
               "distribute": ("raw.",), "pieces": ("core.", "halo."), "radii": ("cover.", "radloc.", "space.")}


#: a consumer that stands for the covering pass of every tile of the plan (see :func:`consumers`)
EVERY_COVER = "cover.*"


def consumers(name: str) -> list[str] | None:
    """The pieces that read the work file ``name`` once its producer is done (``order.<t>.*``: every
    ordering of tile t; none: no piece reads it), None for a file that is never deleted before the
    build ends: while they are all done the file is not needed."""
    parts = name.split(".")
    kind, ext = parts[0], parts[-1]
    if name in (DEFERRED, DROPPED) or (kind in ("seam", "links") and ext == "bin"):
        return ["merge"]
    if kind == "raw" and ext == "xyz":
        return ["plan", "distribute"]
    if kind == "stream" and ext == "keys":
        return ["merge"]
    if kind == "face" and ext == "bin":
        return ["order"]
    if kind == "sample" and ext == "f64":  # (the spill's marker does not list them)
        return ["spill"]
    if name == SAMPLE:
        return ["plan"]
    if kind in ("core", "halo") and ext == "bin":
        return ["pieces", f"cover.{parts[1]}", f"order.{parts[1]}.*"]
    if (kind == "cover" and ext in ("ev", "pt")) or kind in ("radloc", "space"):
        return ["radii"]
    if kind == "bucket" and ext == "bin":
        return [chunks_piece(k) for k in bucket_range(name)]
    if kind == "rank" and ext == "i8":  # (read by every tile's covering pass and by its block's permutation)
        return [EVERY_COVER, bucket_piece(int(parts[1]))]
    return None


# ------------------------------------------------------------------------------------ moments

#: environment variable naming the moment at which a build kills itself (tests only)
FAULT_ENV = "LODBUILDER_TILED_FAULT"
#: the named moments: after each phase's marker, after the first tile ordering's marker, after the
#: first group's seam links and the seam repair's, and after the first read, split, merged (band of the merge), rank (a read block's
#: ranks), permute, band (of the radii) and chunks (band of the write) task's markers
MOMENTS = (*PHASES, "tile", "links", SEAMS_PIECE, "read", "split", "merged", "rank", "permute", "band", "chunks")


def moment(name: str) -> None:
    """A named moment of the build: when ``$LODBUILDER_TILED_FAULT`` names it, the process kills
    itself with SIGKILL (the kill tests' deterministic fault hook; a no-op otherwise)."""
    if os.environ.get(FAULT_ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)

