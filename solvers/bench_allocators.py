"""Per-tick allocation time (median, p99) of the RU allocators at 6, 12, 24, 48 stations, as JSON.

Thin script over :func:`codesign_mb.bench.allocators.bench_allocators`
(= ``codesign bench allocators``).
"""

from __future__ import annotations

import argparse
import json

from codesign_mb.bench.allocators import bench_allocators


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(json.dumps(bench_allocators(repeats=args.repeats, seed=args.seed), indent=2))


if __name__ == "__main__":
    main()
