"""MPC solve time on recorded conveyor problems; prints JSON (same as ``codesign bench mpc``).

Usage: ``python solvers/bench_mpc.py [--repeats N] [--seed S]``
"""

from __future__ import annotations

import argparse
import json

from codesign_mb.bench.mpc import bench_mpc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20, help="replays of every episode")
    parser.add_argument("--seed", type=int, default=0, help="seed of the recorded episodes")
    args = parser.parse_args()
    print(json.dumps(bench_mpc(repeats=args.repeats, seed=args.seed), indent=2))


if __name__ == "__main__":
    main()
