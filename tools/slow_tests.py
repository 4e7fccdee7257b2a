"""Write tests/slow_tests.txt, the tests the fast lane (``pytest -m "not slow"``) leaves out: every
test that took at least THRESHOLD seconds (setup + call + teardown) in a full run's durations.

    python -m pytest -q -p no:cacheprovider --durations=0 > run.log
    python tools/slow_tests.py run.log [--threshold 1.0] [--load-factor F]

``--load-factor`` divides the times first (a run on a loaded machine; 1 on a quiet one). The list
is sorted and committed; tests/conftest.py marks its entries ``slow`` at collection.
"""

from __future__ import annotations

import argparse
import collections
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINE = re.compile(r"\s*([\d.]+)s (call|setup|teardown)\s+(\S+)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path, help="output of pytest --durations=0")
    ap.add_argument("--threshold", type=float, default=1.0, help="seconds (default 1)")
    ap.add_argument("--load-factor", type=float, default=1.0, help="divide the times by this first")
    args = ap.parse_args(argv)
    seconds: dict[str, float] = collections.defaultdict(float)
    for line in args.log.read_text().splitlines():
        m = LINE.match(line)
        if m:
            seconds[m.group(3)] += float(m.group(1)) / args.load_factor
    slow = sorted(n for n, t in seconds.items() if t >= args.threshold)
    out = ROOT / "tests" / "slow_tests.txt"
    out.write_text("# written by tools/slow_tests.py: the tests pytest -m 'not slow' leaves out\n"
                   + "\n".join(slow) + "\n")
    fast = sum(t for t in seconds.values() if t < args.threshold)
    print(f"{len(slow)} slow tests of {len(seconds)} timed; the others took {fast:.0f} s in all")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
