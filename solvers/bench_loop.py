"""The full closed loop (MPC + predictor + Bernoulli link + records) against bare physics, as JSON.

Thin script over :func:`codesign_mb.bench.loop.bench_loop` (= ``codesign bench loop``).
Usage: ``python solvers/bench_loop.py [--repeats N] [--seed S]``
"""

from __future__ import annotations

import argparse
import json

from codesign_mb.bench.loop import bench_loop


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(json.dumps(bench_loop(repeats=args.repeats, seed=args.seed), indent=2))


if __name__ == "__main__":
    main()
