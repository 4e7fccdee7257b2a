"""What the archive safety checks cost per command, measured part by part in one process.

    python tools/bench_safety.py                  # a 1M-point archive, a 30-scan collection
    python tools/bench_safety.py --n 200000 --repeat 9

Prints one JSON document. The archives are *synthetic* (a generated wavy surface with a random
permutation as its ordering, radius = sqrt(1 / (pi k)); see ``bench_slice.synthetic_record``):
the checks' cost depends on what is read, not on how the ordering was computed.

Measured (minimum over ``--repeat`` runs, milliseconds), each against the same work without it:

* ``open``: ``open_archive`` + ``scan()``; of it, ``safety.check_file`` (the metadata walk that
  refuses links, external storage, virtual datasets, sizes the file cannot hold) and
  ``checks.check_scan_group`` (the scan's attributes, shapes and dtypes);
* ``heap guard``: opening the file and reading a 100k-point prefix through h5py's ``fileobj``
  driver and :class:`safety.GuardedFile` (every global heap walked before HDF5 parses it) against
  h5py's default driver on the path;
* ``level``: ``ScanView.level(size=k)`` for k = 1k, 100k and all points, and the share of it
  spent in ``checks.check_rows`` (finite points inside the bounds, radii, distinct positions);
* ``info``: ``scan_info`` (the whole radius array, checked);
* ``collection``: opening a 30-scan archive (index file + parts) and every scan.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))

from benchdoc import publish, stamp  # noqa: E402


def best(fn: Any, repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return round(min(ts) * 1e3, 3)


def build(work: Path, n: int) -> tuple[Path, str, Path]:
    sys.path.insert(0, str(HERE))
    from bench_slice import synthetic_record

    from lodbuilder.archive.writer import update_archive

    big = work / "big.h5"
    rec, _ = synthetic_record(n, 1, False)
    update_archive(big, [rec])
    coll = work / "coll.h5"
    recs = []
    for i in range(30):
        r, _ = synthetic_record(20000, 10 + i, False)
        r.scan.name = f"scan{i:02d}"
        recs.append(r)
    update_archive(coll, recs)
    return big, rec.scan.name, coll


def measure(big: Path, name: str, coll: Path, n: int, repeat: int) -> dict[str, Any]:
    import h5py

    import lodbuilder
    from lodbuilder.archive import checks, safety
    from lodbuilder.archive import layout as L
    from lodbuilder.cli.info import scan_info

    out: dict[str, Any] = {}

    def open_scan() -> None:
        with lodbuilder.open_archive(big) as a:
            a.scan(name)

    f = safety.open_h5(big)
    g = f[f"{L.G_SCANS}/{name}"]
    out["open"] = {
        "open_archive_and_scan": best(open_scan, repeat),
        "of_it_check_file": best(lambda: safety.check_file(f, big), repeat),
        "of_it_check_scan_group": best(lambda: checks.check_scan_group(g, big, name), repeat),
    }
    f.close()

    k = min(100_000, n)

    def prefix(fobj: Any) -> None:
        with h5py.File(fobj, "r") as h:
            s = h[f"{L.G_SCANS}/{name}"]
            for rel in (L.D_POINTS, L.D_RADIUS, L.D_SOURCE_INDEX):
                s[rel][:k]
            for key in s[L.G_ATTRIBUTES]:
                s[L.G_ATTRIBUTES][key][:k]

    def guarded() -> None:
        with open(big, "rb", buffering=0) as raw:
            prefix(safety.GuardedFile(raw, big))

    plain = best(lambda: prefix(big), repeat)
    through = best(guarded, repeat)
    out["heap_guard"] = {
        "open_and_read_100k_path_ms": plain,
        "open_and_read_100k_guarded_ms": through,
        "ratio": round(through / plain, 3),
    }

    levels: dict[str, Any] = {}
    with lodbuilder.open_archive(big) as a:
        v = a.scan(name)
        meta = v._meta
        for size in sorted({1000, k, n}):
            total = best(lambda s=size: v.level(size=s), repeat)
            lev = v.level(size=size)
            raw = v._g[L.D_POINTS][:size]
            rad = v._g[L.D_RADIUS][: size + 1]

            def check(lev=lev, raw=raw, rad=rad) -> None:
                checks.check_rows(meta, L.D_POINTS, raw, 0, v._raw_rows)
                checks.check_rows(meta, L.D_RADIUS, rad, 0, v._raw_rows)
                checks.check_rows(meta, L.D_SOURCE_INDEX, lev.source_index, 0, v._raw_rows)

            spent = best(check, repeat)
            levels[f"size_{size}"] = {
                "level_ms": total,
                "of_it_checks_ms": spent,
                "share": round(spent / total, 3),
            }

        def info() -> None:
            v._radius = None
            scan_info(v)

        levels["info_scan_ms"] = best(info, repeat)
        rad_all = v._g[L.D_RADIUS][:]
        levels["info_of_it_radius_checks_ms"] = best(
            lambda: checks.check_rows(meta, L.D_RADIUS, rad_all, 0, v._raw_rows), repeat
        )
    out["level"] = levels

    def open_all() -> None:
        with lodbuilder.open_archive(coll) as a:
            for s in a.scans:
                a.scan(s)

    out["collection_30_scans"] = {"open_and_every_scan_ms": best(open_all, repeat)}
    parts = sorted(coll.with_name(L.parts_dir_name(coll.name)).glob("*.h5"))
    walk = 0.0
    for p in parts:
        ff = h5py.File(p, "r")
        walk += best(lambda ff=ff, p=p: safety.check_file(ff, p), repeat)
        ff.close()
    idx = h5py.File(coll, "r")
    walk += best(lambda: safety.check_file(idx, coll), repeat)
    idx.close()
    out["collection_30_scans"]["of_it_check_file_ms"] = round(walk, 3)
    out["collection_30_scans"]["files"] = len(parts) + 1
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=1_000_000, help="points of the big archive")
    p.add_argument("--repeat", type=int, default=7, help="runs per measurement (minimum kept)")
    args = p.parse_args(argv)
    sys.path.insert(0, str(REPO))
    doc = stamp(
        "bench_safety",
        argv,
        inputs=f"synthetic: {args.n}-point wavy surface (7 attributes); 30 scans of 20,000 points",
        synthetic=True,
    )
    with tempfile.TemporaryDirectory(prefix="bench-safety-") as tmp:
        big, name, coll = build(Path(tmp), args.n)
        res = measure(big, name, coll, args.n, args.repeat)
    doc["ms_min"] = res
    publish(doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
