"""Conveyor env control steps per second (20 physics substeps + Pinocchio OSC each), as JSON.

Thin script over :func:`codesign_mb.bench.env.bench_env` (= ``codesign bench env``).
Usage: ``python solvers/bench_env.py [--repeats N] [--seed S]``
"""

from __future__ import annotations

import argparse
import json

from codesign_mb.bench.env import bench_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(json.dumps(bench_env(repeats=args.repeats, seed=args.seed), indent=2))


if __name__ == "__main__":
    main()
