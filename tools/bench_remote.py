"""Benchmark reading levels of archives over HTTP and S3 (servers on 127.0.0.1).

    python tools/bench_remote.py                    # a 1M-point archive, levels of 10k points
    python tools/bench_remote.py --n 1000000 --latency 0.02 --markdown docs/benchmarks.md

Prints one JSON document. Archives are *synthetic* (a generated wavy surface, a random
permutation as its ordering, like tools/bench_slice.py): a level's cost depends on the stored
layout only. Served by a local HTTP server that honours Range requests (tests/rangeserver.py,
with ``--latency`` seconds slept before each answer as a stand-in for a network) and by moto's S3
server; requests and bytes are counted by the servers (moto's request recorder).

For each case: open the archive and read the level (``open_archive(url).scan(name).level(size=k)``)
-> GET and HEAD requests, bytes fetched, the level's own stored bytes and the file's page size.
Also measured: the same read through fsspec's default file object (``fs.open(url)`` handed to
h5py, its default read-ahead cache), and the CLI ``lodbuilder slice URL --size k -o OUT`` against
the same command on the local file.

Targets (issue 12): opening an archive and reading a 10k-point level of one scan takes <= 4 GET
requests and fetches <= 2x the level's bytes plus one page; ``lodbuilder slice https://.../a.h5
--size 10000`` within 2x the local time plus request latency.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
sys.path.insert(0, str(HERE))

from benchdoc import load_run, measured, publish, stamp, write_section  # noqa: E402
from remote_setup import MotoS3, level_bytes, page_size, write_served  # noqa: E402


def _range_bytes(rng: str | None) -> int:
    if not rng:
        return 0
    a, b = rng[6:].split("-")
    return int(b) - int(a) + 1


def read_level(url: str, name: str, k: int, options: dict | None = None) -> tuple[float, int]:
    import lodbuilder

    t = time.perf_counter()
    with lodbuilder.open_archive(url, storage_options=options) as arc:
        lev = arc.scan(name).level(size=k)
    return time.perf_counter() - t, lev.size


def read_level_fsspec_default(url: str, name: str, k: int, options: dict | None = None) -> float:
    """The same level through fsspec's default file object (its read-ahead cache) and h5py."""
    import fsspec
    import h5py

    t = time.perf_counter()
    with fsspec.open(url, "rb", **(options or {})) as fobj, h5py.File(fobj, "r") as f:
        g = f["scans"][name]
        for key in ["points", "source_index", "radius"] + [f"attributes/{a}" for a in g["attributes"]]:
            g[key][:k]
    return time.perf_counter() - t


def cli_slice(src: str, name: str, k: int, out: Path, env: dict | None = None) -> float:
    exe = shutil.which("lodbuilder")
    cmd = [exe] if exe else [sys.executable, "-m", "lodbuilder.cli.main"]
    t = time.perf_counter()
    r = subprocess.run(cmd + ["slice", src, "--scan", name, "--size", str(k), "-o", str(out)],
                       capture_output=True, text=True, env=env)
    dt = time.perf_counter() - t
    if r.returncode != 0:
        raise RuntimeError(r.stderr)
    return dt


def markdown(result: dict) -> str:
    lines = [
        f"{measured(result)}. Servers on 127.0.0.1 (a Range-honouring HTTP server with "
        f"{result['latency_s'] * 1e3:.0f} ms added per request, moto's S3 server). Archives are "
        f"synthetic ({result['inputs']}). Fetched bytes: as "
        "sent by the HTTP server; for S3 the sum of the requested ranges (moto records requests, "
        "not answers). The level's bytes: the stored chunk bytes of its rows.",
        "",
        "| archive | server | level | GET | HEAD | fetched | level's bytes | page | fetched / (2 x level + page) | s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in result["cases"]:
        lines.append(
            f"| {c['archive']} | {c['server']} | {c['level']:,} | {c['get']} | {c['head']} | "
            f"{c['fetched_bytes'] / 1e6:.2f} MB | {c['level_bytes'] / 1e6:.2f} MB | "
            f"{c['page_bytes'] // 1024} KiB | {c['budget_ratio']:.2f} | {c['seconds']:.3f} |"
        )
    d = result.get("fsspec_default")
    if d:
        lines += ["", f"The same level through fsspec's default file object: {d['get']} GET(s), "
                  f"{d['fetched_bytes'] / 1e6:.1f} MB fetched of a {d['file_bytes'] / 1e6:.1f} MB file, "
                  f"{d['seconds']:.2f} s."]
    c = result.get("cli")
    if c:
        lines += ["", f"`lodbuilder slice URL --size {c['level']}` over HTTP: {c['remote_s']:.2f} s, on "
                  f"the local file {c['local_s']:.2f} s (ratio {c['ratio']:.2f}; target <= 2x + "
                  f"latency: {c['target_s']:.2f} s)."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1_000_000, help="points of the single-file archive")
    p.add_argument("--parts", type=int, nargs="+", default=[300_000, 50_000],
                   help="points of the scans of an archive with parts")
    p.add_argument("--level", type=int, default=10_000)
    p.add_argument("--latency", type=float, default=0.0, help="seconds added to every HTTP answer")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--no-s3", action="store_true")
    p.add_argument("--markdown", help="update the 'remote' section of this file")
    p.add_argument("--from-json", help="re-render a saved JSON result into --markdown, no new run")
    args = p.parse_args(argv)
    if args.from_json:
        saved = load_run(args.from_json)
        if args.markdown:
            write_section(Path(args.markdown), "remote", markdown(saved))
        print(json.dumps(saved.get("targets", {}), indent=2))
        return 0

    from rangeserver import RangeServer

    work = Path(tempfile.mkdtemp(prefix="bench_remote_"))
    result = stamp(
        "bench_remote",
        argv,
        inputs=f"synthetic wavy scans, {args.n:,} points in one file; "
        f"{', '.join(f'{n:,}' for n in args.parts)} points in an archive with parts",
        synthetic=True,
    )
    result.update(latency_s=args.latency, cases=[])
    moto = None
    try:
        files = write_served(work, args.n, args.parts)
        one, many = files[:2]
        import lodbuilder

        with lodbuilder.open_archive(many) as arc:
            parts = {r.name: work / "many.h5.scans" / r.part for r in arc.rows}
        targets = [("one.h5", "big", one)] + [("many.h5", n, parts[n]) for n in sorted(parts)]
        if not args.no_s3:
            moto = MotoS3(work, files, "lodbuilder-bench", work / "moto_recording")
        with RangeServer(work, delay=args.latency) as srv:
            for rel, name, part in targets:
                lb = level_bytes(part, name, args.level)
                page = page_size(part)
                runs = []
                for _ in range(args.repeat):
                    srv.reset()
                    dt, size = read_level(srv.url(rel), name, args.level)
                    runs.append((dt, srv.count("GET"), srv.count("HEAD"), srv.sent()))
                dt = min(r[0] for r in runs)
                get, head, sent = runs[-1][1:]
                result["cases"].append({
                    "archive": f"{rel} ({name})", "server": "HTTP", "level": args.level,
                    "get": get, "head": head, "fetched_bytes": sent, "level_bytes": int(lb),
                    "page_bytes": page, "budget_ratio": round(sent / (2 * lb + page), 3),
                    "seconds": round(dt, 4),
                })
                print(json.dumps(result["cases"][-1]), file=sys.stderr, flush=True)
                if moto is not None:
                    times = []
                    for _ in range(args.repeat):
                        moto.start()
                        dt, size = read_level(f"s3://lodbuilder-bench/{rel}", name, args.level,
                                              moto.options)
                        log = moto.recorded()
                        times.append(dt)
                    gets = [r for r in log if r["method"] == "GET"]
                    fetched = sum(_range_bytes((r.get("headers") or {}).get("Range")) for r in gets)
                    result["cases"].append({
                        "archive": f"{rel} ({name})", "server": "S3 (moto)", "level": args.level,
                        "get": len(gets), "head": sum(r["method"] == "HEAD" for r in log),
                        "fetched_bytes": fetched, "level_bytes": int(lb), "page_bytes": page,
                        "budget_ratio": round(fetched / (2 * lb + page), 3),
                        "seconds": round(min(times), 4),
                    })
                    print(json.dumps(result["cases"][-1]), file=sys.stderr, flush=True)
            # fsspec's default file object (read-ahead) for comparison
            srv.reset()
            dt = read_level_fsspec_default(srv.url("one.h5"), "big", args.level)
            result["fsspec_default"] = {
                "server": "HTTP", "get": srv.count("GET"), "head": srv.count("HEAD"),
                "fetched_bytes": srv.sent(), "file_bytes": one.stat().st_size, "seconds": round(dt, 3),
            }
            print(json.dumps(result["fsspec_default"]), file=sys.stderr, flush=True)
            # the command line, remote against local
            local, remote = [], []
            for _ in range(args.repeat):
                local.append(cli_slice(str(one), "big", args.level, work / "l.npy"))
                srv.reset()
                remote.append(cli_slice(srv.url("one.h5"), "big", args.level, work / "r.npy"))
                n_requests = len(srv.log)
            assert np.array_equal(np.load(work / "l.npy"), np.load(work / "r.npy"))
            lo, re_ = statistics.median(local), statistics.median(remote)
            result["cli"] = {
                "level": args.level, "local_s": round(lo, 3), "remote_s": round(re_, 3),
                "ratio": round(re_ / lo, 3), "requests": n_requests,
                "target_s": round(2 * lo + n_requests * args.latency, 3),
            }
            print(json.dumps(result["cli"]), file=sys.stderr, flush=True)
    finally:
        if moto is not None:
            moto.stop()
        shutil.rmtree(work, ignore_errors=True)
    result["targets"] = {
        "max_get_requests": max(c["get"] for c in result["cases"]),
        "max_get_target": 4,
        "max_fetched_over_budget": max(c["budget_ratio"] for c in result["cases"]),
        "budget_target": 1.0,
        "cli_remote_s": result["cli"]["remote_s"],
        "cli_target_s": result["cli"]["target_s"],
    }
    publish(result, section="remote", render=markdown, markdown=args.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
