"""Fuzz the PLY, LAS/LAZ and archive readers with byte-level mutants; print the counts as JSON.

    python tools/fuzz.py                          # 5,000 mutants per reader, a random seed
    python tools/fuzz.py --mutants 300 --seed 7 --readers ply_ascii archive --keep /tmp/fuzz

Seeds: ``bun_zipper_res4.ply`` (ascii, and the same points and properties as binary PLY),
``simple.las`` (and the same points as LAZ), all from ``../shared/data``, and three archives
built from ``bun_zipper_res4.ply``, taken in turn: the archive as lodbuilder writes it, the same
with its text attributes as variable-length strings (as lodbuilder 0.1 wrote them: their bytes
live in an HDF5 global heap, which has no checksum), and a two-scan archive (an index file and two
part files, one of the three files mutated). Each mutant (1-3 mutations: bit flips, random or boundary bytes,
insertions, deletions, duplicated or truncated ranges, number tokens of the PLY header and body
replaced by extreme values; archive mutations biased towards HDF5 metadata blocks) runs in a
forked child with a time limit, so a hang or a signal is counted instead of stopping the run.
The children are forked from a fresh server process (``--serve``) that has imported the readers
but run none of them: a child forked from a process whose libraries have started thread pools
(lazrs decompresses LAZ on a rayon pool) would wait for threads that do not exist in it.

Outcomes per mutant:

* ``ok``: read without error (for archives: every level identical to the seed's);
* ``clean``: one of lodbuilder's documented errors (:class:`lodbuilder.errors.LodbuilderError`)
  with a one-line message (the histogram of error classes is printed);
* ``traceback``: any other exception (or a message on several lines);
* ``wrong``: for a scan reader, points that are not finite or attributes of the wrong length; for
  an archive, a level, point array or radius array that differs from the seed's without an error;
* ``hang``: still running after ``--timeout`` seconds and again after four times that;
* ``signal``: the child died of a signal (e.g. a segfault in a C library).

Targets (issue 13): >= 5,000 mutants per reader, 0 tracebacks, 0 hangs, 0 signals, 0 wrong.
"""

from __future__ import annotations

import argparse
import collections
import datetime as _dt
import functools
import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
READERS = ("ply_ascii", "ply_binary", "las", "laz", "archive")
SUFFIX = {"ply_ascii": ".ply", "ply_binary": ".ply", "las": ".las", "laz": ".laz", "archive": ".h5"}
HDF5_BLOCKS = (
    b"OHDR",
    b"OCHK",
    b"FRHP",
    b"FHDB",
    b"FHIB",
    b"BTHD",
    b"BTIN",
    b"BTLF",
    b"GCOL",
    b"FAHD",
    b"FADB",
    b"EAHD",
    b"EAIB",
    b"EADB",
    b"\x89HDF",
)
INTERESTING = [
    b"\x00",
    b"\xff",
    b"\x7f",
    b"\x80",
    b"\x00" * 4,
    b"\xff" * 4,
    b"\xff" * 8,
    b"\x7f\xff\xff\xff",
    b"\x00\x00\x00\x80",
    b"\x01\x00\x00\x00\x00\x00\x00\x00",
    b"\x00\x00\x00\x00\x00\x00\xf0\x7f",
    b"\x00\x00\xc0\x7f",
]  # inf, NaN (f8, f4)
NUMBERS = [
    b"0",
    b"-1",
    b"1",
    b"4294967295",
    b"18446744073709551616",
    b"1000000000000",
    b"-2147483649",
    b"1e308",
    b"-1e308",
    b"nan",
    b"inf",
    b"-0",
    b"1e-320",
    b"0x10",
    b"x",
]


# ---------------------------------------------------------------------------------------------
# seeds


def variable_length_strings(path: Path) -> Path:
    """Store every text attribute of the archive at ``path`` as a variable-length string."""
    import h5py
    import numpy as np

    def convert(obj: Any) -> None:
        for key, value in list(obj.attrs.items()):
            if isinstance(value, bytes | np.bytes_):
                del obj.attrs[key]
                obj.attrs[key] = bytes(value).decode("utf-8")  # h5py: str -> variable length

    with h5py.File(path, "r+") as f:
        convert(f)
        f.visititems(lambda _name, obj: convert(obj))
    return path


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def make_seeds(work: Path) -> dict[str, Any]:
    """The seed file of every reader, as bytes; for ``archive``, a list of archives, each a dict
    of relative file name -> bytes whose first entry is the file to open."""
    import laspy

    import lodbuilder
    from lodbuilder.io import read_scan, write_points

    seeds: dict[str, bytes] = {}
    ply = DATA / "bun_zipper_res4.ply"
    seeds["ply_ascii"] = ply.read_bytes()
    scan = read_scan(ply)
    binary = work / "seed_binary.ply"
    write_points(binary, scan.points, scan.attributes)
    seeds["ply_binary"] = binary.read_bytes()
    las = DATA / "simple.las"
    seeds["las"] = las.read_bytes()
    laz = work / "seed.laz"
    laspy.read(str(las)).write(str(laz))
    seeds["laz"] = laz.read_bytes()
    archives = []
    for variant in ("current", "variable-length strings", "two scans"):
        d = work / variant.replace(" ", "_")
        d.mkdir()
        lodbuilder.build_archive(ply, d / "seed.h5", name="bunny")
        if variant == "variable-length strings":
            variable_length_strings(d / "seed.h5")
        if variant == "two scans":
            lodbuilder.build_archive(ply, d / "seed.h5", name="second")
        files = _files(d)
        archives.append({"seed.h5": files.pop("seed.h5"), **files})
    seeds["archive"] = archives
    return seeds


# ---------------------------------------------------------------------------------------------
# mutations


def _number_tokens(data: bytes, limit: int) -> list[tuple[int, int]]:
    out, i, n = [], 0, min(len(data), limit)
    while i < n:
        c = data[i]
        if 48 <= c <= 57 or c in (45, 46):
            j = i
            while j < n and (48 <= data[j] <= 57 or data[j] in (45, 46, 101, 69, 43)):
                j += 1
            out.append((i, j))
            i = j
        else:
            i += 1
    return out


def mutate_archive(seed: dict[str, bytes], rng: random.Random) -> dict[str, bytes]:
    """One file of the archive (the index or main file half the time) mutated."""
    names = list(seed)
    name = names[0] if len(names) == 1 or rng.random() < 0.5 else rng.choice(names[1:])
    return {**seed, name: mutate(seed[name], "archive", rng)}


def mutate(seed: bytes, reader: str, rng: random.Random) -> bytes:
    """1-3 random mutations of ``seed``."""
    data = bytearray(seed)
    blocks = []
    if reader == "archive":
        for sig in HDF5_BLOCKS:
            at = seed.find(sig)
            while at >= 0:
                blocks.append(at)
                at = seed.find(sig, at + 1)
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        if not data:
            break
        if blocks and rng.random() < 0.6:  # inside an HDF5 metadata block
            pos = min(len(data) - 1, rng.choice(blocks) + rng.randrange(0, 512))
        elif reader.startswith("ply") and rng.random() < 0.5:  # header and first rows
            pos = rng.randrange(min(len(data), 2048))
        else:
            pos = rng.randrange(len(data))
        op = rng.choice(
            ("flip", "byte", "interesting", "insert", "delete", "duplicate", "truncate", "number")
        )
        if op == "flip":
            data[pos] ^= 1 << rng.randrange(8)
        elif op == "byte":
            data[pos] = rng.randrange(256)
        elif op == "interesting":
            v = rng.choice(INTERESTING)
            data[pos : pos + len(v)] = v
        elif op == "insert":
            data[pos:pos] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        elif op == "delete":
            del data[pos : pos + rng.randint(1, 64)]
        elif op == "duplicate":
            n = rng.randint(1, 256)
            src = rng.randrange(len(data))
            data[pos:pos] = data[src : src + n]
        elif op == "truncate":
            del data[pos:]
        else:
            tokens = _number_tokens(bytes(data), 4096 if reader != "archive" else 0)
            if tokens:
                a, b = rng.choice(tokens)
                data[a:b] = rng.choice(NUMBERS)
            else:
                data[pos] ^= 0x10
    return bytes(data)


# ---------------------------------------------------------------------------------------------
# what a mutant is run through (in the child)


def _one_line_ok(exc: BaseException) -> bool:
    return "\n" not in str(exc) and "\r" not in str(exc)


def target_scan(path: Path) -> str:
    import numpy as np

    from lodbuilder.io import read_scans

    for scan in read_scans(path):
        n = scan.points.shape[0]
        if scan.points.shape != (n, 3) or not np.isfinite(scan.points).all():
            return "wrong: points not (N, 3) finite"
        for key, arr in scan.attributes.items():
            if np.shape(arr)[:1] != (n,):
                return f"wrong: attribute {key!r} has {np.shape(arr)} for {n} points"
    return "ok"


def archive_digest(path: Path) -> str:
    """A digest of what the slice, info and view paths read from the archive at ``path``."""
    import numpy as np

    from lodbuilder.archive.reader import open_archive
    from lodbuilder.cli.info import scan_info
    from lodbuilder.viewer.source import load_view_data

    h = hashlib.sha256()

    def put(*arrays: Any) -> None:
        for a in arrays:
            h.update(np.ascontiguousarray(np.asarray(a)).tobytes())

    with open_archive(path) as arc:
        for name in arc.scans:
            v = arc.scan(name)
            info = scan_info(v)
            put(
                [info["n_points"], info["n_ordered"], info["n_seeds"]],
                [lv["size"] for lv in info["levels"]],
            )
            for query in (
                {"size": 1},
                {"size": 10},
                {"size": v.n_ordered},
                {"fraction": 0.5},
                {"rho": 0.02},
                {"rho": 0.005},
            ):
                lev = v.level(**query)
                put(lev.points, lev.source_index, lev.radius, [lev.rho, lev.size])
                for key in sorted(lev.attributes):
                    put(lev.attributes[key])
            lev = v.refine_box(np.r_[v.bounds[0], (v.bounds[0] + v.bounds[1]) / 2], 0.005, 0.02)
            put(lev.points, lev.rank, [lev.rho])
            lev = v.refine_viewpoint(v.bounds[0], 0.005, 0.5)
            put(lev.points, lev.rank, [lev.rho])
            put(v.representatives(10))
        data = load_view_data(arc)
        put(data.points, data.radius, data.parent)
    return h.hexdigest()


def target_archive(path: Path, reference: str) -> str:
    from lodbuilder.archive.validate import validate_archive

    validate_archive(path)  # faults are fine; an exception other than ours is not
    return "ok" if archive_digest(path) == reference else "wrong: a level differs from the seed's"


def run_child(fn: Callable[[], str], timeout: float, quiet: bool = True) -> str:
    """Run ``fn`` in a forked child (stderr silenced when ``quiet``); its outcome as a string."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child
        os.close(r)
        import faulthandler

        faulthandler.disable()  # a signal is counted by the parent, not reported by the child
        if quiet:  # libraries' warnings and log lines
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
        try:
            out = fn()
        except BaseException as exc:
            from lodbuilder.errors import LodbuilderError

            if isinstance(exc, LodbuilderError) and _one_line_ok(exc):
                out = f"clean: {type(exc).__name__}"
            elif isinstance(exc, LodbuilderError):
                out = f"traceback: multi-line {type(exc).__name__}: {str(exc)[:200]!r}"
            else:
                tb = traceback.extract_tb(exc.__traceback__)[-1]
                where = f"{Path(tb.filename).name}:{tb.lineno}"
                out = f"traceback: {type(exc).__name__} at {where}: {' '.join(str(exc).split())[:200]}"
        try:
            os.write(w, out.encode()[:4000])
        finally:
            os._exit(0)
    os.close(w)
    deadline = time.monotonic() + timeout
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            os.close(r)
            return "hang"
        time.sleep(0.002)
    chunks = []
    while True:
        b = os.read(r, 4096)
        if not b:
            break
        chunks.append(b)
    os.close(r)
    if os.WIFSIGNALED(status):
        return f"signal: {signal.Signals(os.WTERMSIG(status)).name}"
    return b"".join(chunks).decode() or "traceback: the child exited without a result"


# ---------------------------------------------------------------------------------------------
# the campaign


def fuzz(
    readers: list[str],
    mutants: int,
    seed: int,
    timeout: float = 20.0,
    keep: Path | None = None,
    work: Path | None = None,
    seeds: dict[str, bytes] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Run the campaign; the per-reader counts (see the module docstring)."""
    own = work is None
    work = Path(tempfile.mkdtemp(prefix="lodbuilder-fuzz-")) if work is None else work
    server = Server()
    try:
        seeds = seeds or make_seeds(work)
        references = []
        if "archive" in readers:
            for j, files in enumerate(seeds["archive"]):
                ref_path = _write_files(work / f"reference{j}", files)
                ref = server.run("digest", ref_path, "", timeout * 4)
                if len(ref) != 64:
                    raise RuntimeError(f"seed archive {j} does not read: {ref}")
                references.append(ref)
        rng = random.Random(seed)
        result: dict[str, Any] = {}
        for reader in readers:
            counts: collections.Counter[str] = collections.Counter()
            kinds: collections.Counter[str] = collections.Counter()
            failures: list[dict[str, Any]] = []
            t0 = time.perf_counter()
            for i in range(mutants):
                if reader == "archive":
                    j = i % len(seeds["archive"])
                    path = _write_files(work / "mutant", mutate_archive(seeds["archive"][j], rng))
                    job, ref = "archive", references[j]
                else:
                    path = work / f"mutant{SUFFIX[reader]}"
                    path.write_bytes(mutate(seeds[reader], reader, rng))
                    job, ref = "scan", ""
                out = server.run(job, path, ref, timeout)
                if out == "hang":  # make sure: a slow machine is not a hang
                    out = server.run(job, path, ref, timeout * 4)
                    if out != "hang":
                        counts["slow"] += 1
                kind = out.split(":", 1)[0]
                counts[kind] += 1
                if kind == "clean":
                    kinds[out.split(": ", 1)[1]] += 1
                elif kind != "ok":
                    entry = {"mutant": i, "outcome": out}
                    if keep is not None:
                        keep.mkdir(parents=True, exist_ok=True)
                        dst = keep / f"{reader}-{seed}-{i}{SUFFIX[reader]}"
                        if reader == "archive":
                            shutil.copytree(path.parent, dst)
                        else:
                            shutil.copyfile(path, dst)
                        entry["file"] = str(dst)
                    failures.append(entry)
                if progress and (i + 1) % 500 == 0:
                    print(f"{reader}: {i + 1}/{mutants} {dict(counts)}", file=sys.stderr)
            result[reader] = {
                "mutants": mutants,
                **{
                    k: counts.get(k, 0)
                    for k in ("ok", "clean", "traceback", "wrong", "hang", "signal", "slow")
                },
                "errors": dict(kinds.most_common()),
                "failures": failures[:50],
                "seconds": round(time.perf_counter() - t0, 1),
            }
        return result
    finally:
        server.close()
        if own:
            shutil.rmtree(work, ignore_errors=True)


JOBS: dict[str, Callable[[Path, str], str]] = {
    "scan": lambda path, ref: target_scan(path),
    "archive": target_archive,
    "digest": lambda path, ref: archive_digest(path),
}


class Server:
    """A fresh process that runs each job in a child forked from itself (see the docstring)."""

    def __init__(self) -> None:
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
        }
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--serve"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )

    def run(self, job: str, path: Path, reference: str, timeout: float) -> str:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps([job, str(path), reference, timeout]) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the fuzz server died")
        return str(json.loads(line))

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        self.proc.wait(timeout=60)


def serve() -> int:
    """The server's loop: one JSON job per line on stdin, one JSON outcome per line on stdout."""
    import laspy  # noqa: F401  - imported once here, so that every child starts warm
    import lazrs  # noqa: F401
    import plyfile  # noqa: F401

    import lodbuilder.archive.validate  # noqa: F401
    import lodbuilder.cli.info  # noqa: F401
    import lodbuilder.io.las  # noqa: F401
    import lodbuilder.io.ply  # noqa: F401
    import lodbuilder.viewer.source  # noqa: F401

    for line in sys.stdin:
        job, path, reference, timeout = json.loads(line)
        out = run_child(functools.partial(JOBS[job], Path(path), reference), float(timeout))
        sys.stdout.write(json.dumps(out) + "\n")
        sys.stdout.flush()
    return 0


def _write_files(root: Path, files: dict[str, bytes]) -> Path:
    """Write an archive's files under a fresh ``root``; the path of its first (main) file."""
    shutil.rmtree(root, ignore_errors=True)
    for name, data in files.items():
        p = root / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    return root / next(iter(files))


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO
        )
        return out.stdout.strip()
    except OSError:
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mutants", type=int, default=5000, help="mutants per reader (default 5000)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: a new one)")
    p.add_argument("--readers", nargs="+", choices=READERS, default=list(READERS))
    p.add_argument("--timeout", type=float, default=20.0, help="seconds per mutant before a hang")
    p.add_argument("--keep", type=Path, help="copy every failing mutant into this directory")
    p.add_argument("--progress", action="store_true", help="counts on stderr every 500 mutants")
    p.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.serve:
        return serve()
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(2**32)
    import h5py

    t0 = time.perf_counter()
    res = fuzz(args.readers, args.mutants, seed, args.timeout, args.keep, progress=args.progress)
    doc = {
        "benchmark": "fuzz",
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "git_commit": _commit(),
        "command": " ".join(
            [Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]
        ),
        "seed": seed,
        "loadavg": list(os.getloadavg()),
        "h5py": h5py.version.version,
        "hdf5": h5py.version.hdf5_version,
        "seconds": round(time.perf_counter() - t0, 1),
        "readers": res,
        "totals": {
            k: sum(r[k] for r in res.values())
            for k in ("mutants", "ok", "clean", "traceback", "wrong", "hang", "signal")
        },
    }
    print(json.dumps(doc, indent=2))
    bad = (
        doc["totals"]["traceback"]
        + doc["totals"]["wrong"]
        + doc["totals"]["hang"]
        + doc["totals"]["signal"]
    )
    return 1 if bad else 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    sys.exit(main())
