"""Generate scan-like surfaces (wavy sheet, sphere, torus, folded sheet with a gap) as point files.

    python tools/surfaces.py wavy -n 20000 --seed 1 --noise 0.0005 -o wavy.ply

The generators live in the package (lodbuilder.datasets) so that ``lodbuilder demo``
works from an installed package; this script is their command line. Import ``make_surface`` or
``demo_scan`` from here or from the package.
"""

from __future__ import annotations

import argparse
import json
import sys

from lodbuilder.datasets import SURFACES, demo_scan, make_surface

__all__ = ["SURFACES", "demo_scan", "make_surface", "main"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("kind", choices=sorted(SURFACES))
    p.add_argument("-n", "--points", type=int, default=20000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise", type=float, default=0.0, help="Gaussian noise along the normal (std)")
    p.add_argument("-o", "--output", required=True, help="output file (.ply, .npy, .csv, ...)")
    args = p.parse_args(argv)
    from lodbuilder.io import write_scan

    scan = demo_scan(args.points, kind=args.kind, seed=args.seed, noise=args.noise, name=args.kind)
    write_scan(args.output, scan)
    json.dump(
        {
            "output": args.output,
            "kind": args.kind,
            "points": len(scan),
            "seed": args.seed,
            "noise": args.noise,
        },
        sys.stdout,
    )
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
