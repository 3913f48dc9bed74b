"""The hour of ``offline_hour.sh``: sample a process tree's memory, or write the results file.

    python solvers/offline_hour.py sample PID OUT.csv STEPS.log     # while PID lives
    python solvers/offline_hour.py summarize DIR --out docs/results/offline_hour.json

``summarize`` reads what ``offline_hour.sh`` wrote in DIR
(:func:`codesign_mb.studies.offline_hour.hour_results`) and prints the table of
``solvers/README.md`` (:func:`~codesign_mb.studies.offline_hour.render_hour`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from codesign_mb.core.results import atomic_write
from codesign_mb.studies.offline_hour import hour_results, render_hour, sample_tree_rss


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sample = sub.add_parser("sample", help="sample the summed RSS of a process tree")
    sample.add_argument("pid", type=int)
    sample.add_argument("out", type=Path)
    sample.add_argument("steps", type=Path)
    summarize = sub.add_parser("summarize", help="write the results file of a run folder")
    summarize.add_argument("folder", type=Path)
    summarize.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if args.command == "sample":
        sample_tree_rss(args.pid, args.out, steps=args.steps)
        return
    results = hour_results(args.folder)
    with atomic_write(args.out, "w") as fh:
        json.dump(results, fh, indent=1)
        fh.write("\n")
    print(render_hour(results))


if __name__ == "__main__":
    main()
