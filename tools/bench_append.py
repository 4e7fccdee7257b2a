"""Benchmark adding one scan to archives of 1 and of many scans (issue 10: O(new data) growth).

    python tools/bench_append.py                         # archives of 1 and 100 scans of 20k points
    python tools/bench_append.py --scans 1 10 100 --points 20000 --new-points 200000

Prints one JSON document. Scans are *synthetic* (a generated wavy surface with a random
permutation as its ordering, like tools/bench_slice.py): the cost of adding a scan depends on the
bytes written, not on how its ordering was computed. Each repeat adds the new scan to a fresh
copy of the archive (hard links of the archive's files, made outside the timed region: parts are
never changed in place, so a linked copy is a true copy). ``bytes_written`` counts the files the
addition created (new inodes), measured from the file system.

Target (issue 10): adding one scan to an archive of 100 scans takes <= 1.3x the time of adding it
to an archive of 1.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from benchdoc import measured, publish, stamp  # noqa: E402
from remote_setup import synthetic_record  # noqa: E402


def files_of(path: Path) -> dict[Path, tuple[int, int]]:
    """(inode, size) of the archive file and of everything in its directory of parts."""
    out = {}
    for p in [path, *sorted(path.parent.glob(path.name + ".scans/*"))]:
        if p.is_file():
            st = p.stat()
            out[p] = (st.st_ino, st.st_size)
    return out


def linked_copy(src: Path, dst: Path) -> None:
    os.link(src, dst)
    parts = src.with_name(src.name + ".scans")
    if parts.is_dir():
        target = dst.with_name(dst.name + ".scans")
        target.mkdir()
        for p in parts.iterdir():
            os.link(p, target / p.name)


def remove(path: Path) -> None:
    path.unlink(missing_ok=True)
    shutil.rmtree(path.with_name(path.name + ".scans"), ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scans", type=int, nargs="+", default=[1, 100], help="archive sizes (scans)")
    p.add_argument("--points", type=int, default=20_000, help="points per scan already stored")
    p.add_argument("--new-points", type=int, default=20_000, help="points of the scan added")
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--workdir", help="where to write (default: a temporary directory)")
    p.add_argument("--markdown", help="update the 'append' section of this file")
    args = p.parse_args(argv)

    import lodbuilder
    from lodbuilder.archive.writer import update_archive

    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_append_"))
    work.mkdir(parents=True, exist_ok=True)
    result = stamp(
        "bench_append",
        argv,
        inputs=f"synthetic wavy scans: {args.points} points each stored, {args.new_points} "
        "points added (random-permutation orderings)",
        synthetic=True,
    )
    result.update(lodbuilder=str(Path(lodbuilder.__file__).parent), cases=[])
    new = synthetic_record(args.new_points, "added", 10**6)
    bases, builds = {}, {}
    times: dict[int, list[float]] = {s: [] for s in args.scans}
    written: dict[int, list[int]] = {s: [] for s in args.scans}
    try:
        for s in args.scans:
            base = work / f"base_{s}.h5"
            remove(base)
            t = time.perf_counter()
            update_archive(base, [synthetic_record(args.points, f"s{i:04d}", i) for i in range(s)])
            builds[s] = time.perf_counter() - t
            bases[s] = base
        for r in range(args.repeat):  # interleaved, so the machine's load hits every case alike
            for s in args.scans:
                path = work / f"copy_{s}_{r}.h5"
                remove(path)
                linked_copy(bases[s], path)
                inodes = {v[0] for v in files_of(path).values()}
                t = time.perf_counter()
                update_archive(path, [new])
                times[s].append(time.perf_counter() - t)
                after = files_of(path)
                written[s].append(sum(size for ino, size in after.values() if ino not in inodes))
                with lodbuilder.open_archive(path) as arc:
                    assert len(arc.scans) == s + 1
                remove(path)
        for s in args.scans:
            case = {
                "scans_before": s,
                "archive_bytes_before": sum(v[1] for v in files_of(bases[s]).values()),
                "build_s": round(builds[s], 3),
                "add_s_min": round(min(times[s]), 4),
                "add_s_median": round(statistics.median(times[s]), 4),
                "bytes_written_median": int(statistics.median(written[s])),
            }
            result["cases"].append(case)
            print(json.dumps(case), file=sys.stderr, flush=True)
    finally:
        for base in bases.values():
            remove(base)
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    cases = {c["scans_before"]: c for c in result["cases"]}
    lo, hi = min(cases), max(cases)
    result["targets"] = {
        f"add_time_ratio_{hi}_vs_{lo}_median": round(cases[hi]["add_s_median"] / cases[lo]["add_s_median"], 3),
        f"add_time_ratio_{hi}_vs_{lo}_min": round(cases[hi]["add_s_min"] / cases[lo]["add_s_min"], 3),
        f"bytes_written_ratio_{hi}_vs_{lo}": round(
            cases[hi]["bytes_written_median"] / max(1, cases[lo]["bytes_written_median"]), 3
        ),
        "add_time_ratio_target": 1.3,
    }
    publish(result, section="append", render=markdown, markdown=args.markdown)
    return 0


def markdown(result: dict) -> str:
    lines = [
        f"{measured(result)}. Inputs: {result['inputs']}. Each "
        "repeat adds the scan to a fresh copy of the archive (hard links of its files); the cases "
        "run interleaved.",
        "",
        "| scans before | archive bytes | add s (min / median) | bytes written |",
        "|---|---|---|---|",
    ]
    for c in result["cases"]:
        lines.append(
            f"| {c['scans_before']} | {c['archive_bytes_before'] / 1e6:.1f} MB | "
            f"{c['add_s_min']:.3f} / {c['add_s_median']:.3f} | {c['bytes_written_median'] / 1e6:.2f} MB |"
        )
    t = result["targets"]
    lines += ["", "Ratios (target <= 1.3 for the time): " + ", ".join(
        f"{k} {v}" for k, v in t.items() if k != "add_time_ratio_target") + "."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
