"""Where an ordering's CPU time goes, kernel by kernel (JSON on stdout).

py-spy and cProfile see a numba kernel as one opaque call (py-spy --native: bare addresses). This
program runs ``lodbuilder.fastfps`` on the points of a file under ``perf record``, with a perf map
(/tmp/perf-PID.map) of every compiled function of the engine: the symbols of the object code numba
loads from its cache, resolved in numba's JIT, helpers that LLVM did not inline included
(``_seed_sample``, ``march_round``, ...). It prints each symbol's share of the samples and the
engine's phase times. Needs Linux ``perf`` and ``nm`` (binutils). The shares are of every sample
of the process: start-up, reading and kernel loading included (with a cold numba cache, the
compile too: run it twice).

    python tools/profile_kernels.py ../shared/data/igea.ply
    python tools/profile_kernels.py stack.ply --top 20 --frequency 999
    python tools/profile_kernels.py stack.ply --build     # the whole ``lodbuilder build`` process
    python tools/profile_kernels.py tile.npz --repeat 5   # a tile as order_tile orders it, 5 times

An ``.npz`` input holds ``points`` and optionally ``seeds``, ``voxel_size``, ``band_radius``,
``timed_idx``, ``timed_keys`` and ``size`` (the arguments of one ``fastfps`` call of a tiled build's
``order_tile``: head points as seeds, the neighbours' halo points as timed seeds).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def _capture_objects(out: dict[str, bytes]) -> None:
    """Keep the object code of every library numba loads from its cache (name -> ELF bytes)."""
    from numba.core import codegen

    original = codegen.CPUCodeLibrary._unserialize.__func__  # type: ignore[attr-defined]

    def unserialize(cls: Any, codegen_: Any, state: Any) -> Any:
        name, kind, data = state
        if kind == "object":
            out[name] = data[0]
        return original(cls, codegen_, state)

    codegen.CPUCodeLibrary._unserialize = classmethod(unserialize)  # type: ignore[method-assign,assignment]


def _demangle(name: str) -> str:
    """``_ZN10lodbuilder8_kernels5march11march_roundB4v1...`` -> ``march.march_round``."""
    j = name.find("_ZN") + 3
    parts = []
    while j < len(name) and name[j].isdigit():
        k = j
        while name[k].isdigit():
            k += 1
        n = int(name[j:k])
        parts.append(name[k:k + n])
        j = k + n
    prefix = "(cfunc) " if name.startswith("cfunc.") else ""
    if parts[:1] == ["cpython"]:  # the wrapper Python calls
        prefix, parts = "(wrapper) ", parts[1:]
    if parts[:2] == ["lodbuilder", "_kernels"]:
        parts = parts[2:]
    return prefix + ".".join(parts)


def _write_map(objects: dict[str, bytes]) -> int:
    """Write /tmp/perf-PID.map for the functions of ``objects``; returns how many were mapped."""
    from numba.core.registry import cpu_target

    engine = cpu_target.target_context.codegen()._engine
    symbols: dict[int, tuple[str, int]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for lib, code in objects.items():
            path = Path(tmp) / f"{lib}.o"
            path.write_bytes(code)
            listing = subprocess.run(["nm", "-S", str(path)], capture_output=True, text=True, check=True).stdout
            for line in listing.splitlines():
                fields = line.split()
                if len(fields) != 4 or fields[2] not in "TtWw" or "_ZN" not in fields[3]:
                    continue
                address = engine.get_function_address(fields[3])
                if address:
                    symbols[address] = (_demangle(fields[3]), int(fields[1], 16))
    with open(f"/tmp/perf-{os.getpid()}.map", "w") as f:
        for address in sorted(symbols):
            name, size = symbols[address]
            f.write(f"{address:x} {size:x} {name}\n")
    return len(symbols)


def _input(path: str) -> tuple[Any, dict[str, Any]]:
    """The points of ``path`` and the keywords of the ``fastfps`` call (an ``.npz``: see above)."""
    if path.endswith(".npz"):
        import numpy as np

        z = np.load(path)
        kw: dict[str, Any] = {k: z[k] for k in ("seeds",) if k in z}
        kw.update({k: float(z[k]) for k in ("voxel_size", "band_radius") if k in z})
        kw.update({k: int(z[k]) for k in ("size",) if k in z})
        if "timed_idx" in z and z["timed_idx"].size:
            kw["timed_seeds"] = (z["timed_idx"], z["timed_keys"])
        return z["points"], kw
    from lodbuilder.io import read_scan

    return read_scan(path).points, {}


def child(path: str, repeat: int = 1) -> None:
    """In the profiled process: load the kernels, map them, order the points ``repeat`` times
    (stats of the last on stdout)."""
    objects: dict[str, bytes] = {}
    _capture_objects(objects)
    import lodbuilder
    from lodbuilder._kernels.warm import compile_group, ensure_compiled

    ensure_compiled()
    for group in ("band", "thin", "ordering"):
        compile_group(group)
    mapped = _write_map(objects)
    pts, kw = _input(path)
    c0 = time.process_time()
    for _ in range(repeat):
        o = lodbuilder.fastfps(pts, **kw)
    stats = {k: v for k, v in o.stats.items() if isinstance(v, (int, float, str))}
    print(json.dumps({"mapped_symbols": mapped, "cpu_s": time.process_time() - c0, "stats": stats}))


def build_child(path: str) -> None:
    """``--build``: in the profiled process, ``lodbuilder build`` of the file as the command runs it
    (start-up, imports, kernel loading, read, ordering, write); the perf map is written at the end
    (perf reads it when it reports)."""
    objects: dict[str, bytes] = {}
    c0 = time.process_time()
    _capture_objects(objects)
    from lodbuilder.cli.main import main as cli

    with tempfile.TemporaryDirectory() as tmp:
        sys.argv = ["lodbuilder", "build", path, "-o", str(Path(tmp) / "a.h5"), "--no-progress", "-q"]
        cli()
    mapped = _write_map(objects)
    print(json.dumps({"mapped_symbols": mapped, "cpu_s": time.process_time() - c0}))


def shares(data: Path, top: int) -> list[dict[str, Any]]:
    """The ``top`` symbols by share of the samples (perf report, self time)."""
    rep = subprocess.run(
        ["perf", "report", "-i", str(data), "--no-children", "--sort", "sym", "--stdio", "-t", "\t"],
        capture_output=True, text=True, check=True,
    ).stdout
    rows = []
    for line in rep.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        share, _, sym = line.strip().partition("\t")
        rows.append({"share_percent": float(share.strip().rstrip("%")), "symbol": sym.replace("[.] ", "").strip()})
    return rows[:top]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("points", help="a points file lodbuilder reads (PLY, LAS/LAZ, E57, ...)")
    ap.add_argument("--top", type=int, default=25, help="symbols listed")
    ap.add_argument("--frequency", type=int, default=499, help="perf samples per second")
    ap.add_argument("--build", action="store_true",
                    help="profile the whole `lodbuilder build` process of the file instead of the ordering")
    ap.add_argument("--repeat", type=int, default=1, help="orderings in the profiled process (not with --build)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        if args.build:
            build_child(args.points)
        else:
            child(args.points, args.repeat)
        return
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "perf.data"
        res = subprocess.run(
            ["perf", "record", "-F", str(args.frequency), "-o", str(data), "--",
             sys.executable, __file__, "--child", args.points, "--repeat", str(args.repeat),
             *(["--build"] if args.build else [])],
            capture_output=True, text=True,
        )
        if res.returncode:
            sys.exit(f"perf record failed: {res.stderr.strip()[-500:]}")
        run = json.loads(res.stdout.strip().splitlines()[-1])
        report = {
            "benchmark": "profile_kernels",
            "command": " ".join(["python", "tools/profile_kernels.py", *sys.argv[1:]]),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "load_avg": os.getloadavg(),
            **run,
            "symbols": shares(data, args.top),
        }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
