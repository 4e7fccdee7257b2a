"""The work directory of a tiled build, in one place: every file's name and record layout, the
markers of finished pieces, and the named moments at which tests stop a build.

Files (little-endian raw arrays unless said otherwise), by the phase that writes them::

    spill       points.f64          (N, 3) float64 coordinates in input order (poses applied)
                attr.<k>.bin        attribute k in input order (dtype and shape in spill.json)
                decimated.i8        input indices of the decimated copy (one point per grid cell)
    distribute  core.<t>.bin        the points of tile t: REC records (g, x, y, z), g the input index
                halo.<t>.bin        the REC records within the halo width of tile t owned by others
    coarse      head.bin            HEAD records: the coarse global level (the head)
    order       stream.<t>.bin      STREAM records: tile t's ordering (input index, key, position, margin)
                face.<t>.<p>.bin    FACE records: tile t's points near its shared faces after pass p
    merge       order.i8, key.f8    the merged order (input index at each position) and its keys
                rank.i8             the position of every input point (the inverse of order.i8)
    cover       cover.<t>.ev/.pt    EVENT / POINT records of tile t's covering pass
    radii       radius.f8, parent.i8  the stored radius and parent of each position
    buckets     bucket.<b>.bin      the external permutation's buckets (see write.py)

A finished phase or tile task leaves a marker ``<piece>.json`` (:func:`marker`) that lists the files
it wrote with their size and CRC-32 (:mod:`.sums`); a resumed build trusts a piece only when its
marker and files check out. Every file is written to a temporary and published
(:mod:`lodbuilder._atomic`).
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
#: a point of the head: input index, position, radius on the decimated copy, parent
HEAD = np.dtype([("g", "<i8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "<f8"), ("parent", "<i8")])
#: a tile's point near its shared faces, by input index, with its key
FACE = np.dtype([("g", "<i8"), ("key", "<f8")])
#: a covering event (the covering radius of the prefix of ``rank`` points rises to ``value``)
EVENT = np.dtype([("rank", "<i8"), ("value", "<f8")])
#: a point's rank, parent and spacing as the covering pass finds them
POINT = np.dtype([("rank", "<i8"), ("parent", "<i8"), ("space", "<f8")])

# ------------------------------------------------------------------------------------ names

POINTS = "points.f64"
DECIMATED = "decimated.i8"
HEAD_FILE = "head.bin"
ORDER = "order.i8"
KEY = "key.f8"
RANK = "rank.i8"
RADIUS = "radius.f8"
PARENT = "parent.i8"

#: the phases, in order; each leaves the marker ``<phase>.json`` when complete
PHASES = ("spill", "plan", "distribute", "coarse", "merge", "buckets", "radii")


def attr(i: int) -> str:
    return f"attr.{i}.bin"


def core(t: int) -> str:
    return f"core.{t}.bin"


def halo(t: int) -> str:
    return f"halo.{t}.bin"


def stream(t: int) -> str:
    return f"stream.{t}.bin"


def face(t: int, p: int) -> str:
    return f"face.{t}.{p}.bin"


def cover_events(t: int) -> str:
    return f"cover.{t}.ev"


def cover_points(t: int) -> str:
    return f"cover.{t}.pt"


def bucket(b: int) -> str:
    return f"bucket.{b}.bin"


def order_piece(t: int, p: int) -> str:
    """The piece name of tile ``t``'s ordering in pass ``p`` (its marker is :func:`marker` of it)."""
    return f"order.{t}.{p}"


def cover_piece(t: int) -> str:
    return f"cover.{t}"


def marker(piece: str) -> str:
    """The marker file of a finished phase or task."""
    return f"{piece}.json"


def writing(name: str) -> str:
    """The name a file has while a phase writes it (published onto ``name`` when complete)."""
    return f"{name}.tmp"


# ------------------------------------------------------------------------------------ moments

#: environment variable naming the moment at which a build kills itself (tests only)
FAULT_ENV = "LODBUILDER_TILED_FAULT"
#: the named moments: after each phase's marker, and after the first tile ordering's marker
MOMENTS = (*PHASES, "tile")


def moment(name: str) -> None:
    """A named moment of the build: when ``$LODBUILDER_TILED_FAULT`` names it, the process kills
    itself with SIGKILL (the kill tests' deterministic fault hook; a no-op otherwise)."""
    if os.environ.get(FAULT_ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)

