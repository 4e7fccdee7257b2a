"""What the archive safety checks cost per command: this tree against the code before them.

    python tools/bench_safety.py                     # 1M-point archive and a 30-scan collection
    python tools/bench_safety.py --n 200000 --repeat 5 --before 50d94bc

Prints one JSON document. The archives are *synthetic* (a generated wavy surface with a random
permutation as its ordering, radius = sqrt(1 / (pi k)); see ``bench_slice.synthetic_record``):
the checks' cost depends on what is read, not on how the ordering was computed. Each measurement
runs in a fresh process importing either this tree or the tree of ``--before`` (a git ref,
default: where this branch left main), alternating, and reports the minimum over ``--repeat``
runs and the after / before ratio.

Measured: opening an archive and one scan (metadata walk, scan header checks, guarded file
object); levels by size (1k, 100k, all points) and by rho (about 100k points); ``info``'s
``scan_info`` (reads the whole radius array); a full ``validate``; ``lodbuilder slice`` wall time.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

MEASURE = r"""
import json, sys, time
import lodbuilder
from lodbuilder.cli.info import scan_info
from lodbuilder.archive.validate import validate_archive

path, name, coll, sizes = sys.argv[1], sys.argv[2], sys.argv[3], [int(s) for s in sys.argv[4].split(",")]
out = {}

def best(fn, repeat=5):
    ts = []
    for _ in range(repeat):
        t = time.perf_counter(); fn(); ts.append(time.perf_counter() - t)
    return min(ts) * 1e3

def open_scan(p, n):
    with lodbuilder.open_archive(p) as a:
        a.scan(n)

out["open_archive_and_scan_ms"] = best(lambda: open_scan(path, name))
out["open_collection_30_scans_ms"] = best(lambda: [a.scans for a in [lodbuilder.open_archive(coll)] if not a.close()])
with lodbuilder.open_archive(path) as a:
    v = a.scan(name)
    for k in sizes:
        out[f"level_size_{k}_ms"] = best(lambda: v.level(size=k))
    rho = float(v.radius[100000])
    def by_rho():
        v._rindex = None
        v.level(rho=rho)
    out["level_rho_100k_ms"] = best(by_rho)
    def info():
        v._radius = None
        scan_info(v)
    out["info_scan_ms"] = best(info)
out["validate_ms"] = best(lambda: validate_archive(path), 2)
print(json.dumps(out))
"""


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], capture_output=True, text=True, cwd=REPO).stdout.strip()


def _tree_at(ref: str, dest: Path) -> Path:
    """The lodbuilder package of ``ref`` extracted under ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "archive", ref, "lodbuilder"], capture_output=True, cwd=REPO, check=True)
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
    return dest


def _build(work: Path, n: int) -> tuple[Path, str, Path]:
    sys.path.insert(0, str(HERE))
    sys.path.insert(0, str(REPO))
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


def _run(tree: Path, args: list[str]) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    res = subprocess.run([sys.executable, "-c", MEASURE, *args], capture_output=True, text=True, env=env)
    if res.returncode:
        raise RuntimeError(res.stderr)
    return json.loads(res.stdout)


def _cli(tree: Path, big: Path, name: str, out: Path, repeat: int) -> float:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    ts = []
    for _ in range(repeat):
        out.unlink(missing_ok=True)
        t = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "lodbuilder.cli.main", "slice", str(big), "--scan", name,
             "--size", "100000", "-o", str(out)],
            env=env, check=True, capture_output=True,
        )
        ts.append(time.perf_counter() - t)
    return min(ts) * 1e3


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=1_000_000, help="points of the big archive")
    p.add_argument("--repeat", type=int, default=3, help="alternating process pairs per tree")
    p.add_argument("--before", default=None, help="git ref of the code before (default: merge-base with main)")
    args = p.parse_args(argv)
    before_ref = args.before or _git("merge-base", "HEAD", "main")
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench-safety-") as tmp:
        work = Path(tmp)
        big, name, coll = _build(work, args.n)
        before_tree = _tree_at(before_ref, work / "before")
        sizes = [1000, 100000, args.n]
        margs = [str(big), name, str(coll), ",".join(map(str, sizes))]
        runs: dict[str, list[dict]] = {"before": [], "after": []}
        for _ in range(args.repeat):  # alternate, so that load changes hit both alike
            runs["before"].append(_run(before_tree, margs))
            runs["after"].append(_run(REPO, margs))
        res = {k: {m: round(min(r[m] for r in v), 2) for m in v[0]} for k, v in runs.items()}
        res["before"]["cli_slice_100k_ms"] = round(_cli(before_tree, big, name, work / "o.npy", args.repeat), 1)
        res["after"]["cli_slice_100k_ms"] = round(_cli(REPO, big, name, work / "o.npy", args.repeat), 1)
    ratio = {m: round(res["after"][m] / res["before"][m], 3) for m in res["after"] if res["before"].get(m)}
    doc = {
        "benchmark": "bench_safety",
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "git_commit": _git("rev-parse", "--short", "HEAD"),
        "before": before_ref[:12],
        "command": " ".join(["tools/bench_safety.py", *(argv if argv is not None else sys.argv[1:])]),
        "loadavg": [round(x, 2) for x in load0],
        "loadavg_end": [round(x, 2) for x in os.getloadavg()],
        "inputs": f"synthetic: {args.n}-point wavy surface (7 attributes), and 30 scans of 20,000 points",
        "ms_min": res,
        "after_over_before": ratio,
    }
    print(json.dumps(doc, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
