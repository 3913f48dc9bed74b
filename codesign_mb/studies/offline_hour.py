"""An hour of a 48-robot cell, offline: the bound, the online allocators and the price of airtime.

``solvers/offline_hour.sh`` records the hour (``codesign wifi trace ... --steps 90000``), solves
it on two workers, on Ray, and with ``--compare``, each under ``/usr/bin/time -v``; this module
turns what those commands wrote into the results file ``docs/results/offline_hour.json``
(:func:`hour_results`) and its table in ``solvers/README.md`` (:func:`render_hour`):

* per minute (:func:`per_minute`): the frames the LP may deliver, its optimum (the bound), what
  each online allocator replayed on the same trace delivers in time, and the price of airtime
  (the duals of the ticks' capacity rows: their mean per tick, the share of ticks priced, the
  largest);
* per run: wall time, the peak resident set of its largest process (``/usr/bin/time``) and of
  its whole process tree (summed, sampled every 0.5 s by :func:`sample_tree_rss`).
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import psutil

from codesign_mb.studies.offline_lp import COMPARED_KEYS

__all__ = [
    "RUNS",
    "hour_results",
    "per_minute",
    "read_time_log",
    "render_hour",
    "sample_tree_rss",
]

RUNS = ("record", "solve", "ray", "compare")
"""The steps of ``solvers/offline_hour.sh``, in order; each wrote ``STEP.json`` and
``STEP.time`` (the ``/usr/bin/time -v`` report) in the run folder."""

MINUTE_TICKS = 60_000
"""A minute of 1 ms ticks."""


def per_minute(record: Mapping[str, Any], *, bin_ticks: int = MINUTE_TICKS) -> pd.DataFrame:
    """Per ``bin_ticks`` ticks, from ``codesign solve --compare --json``'s ``per_window``.

    A window counts in the bin of its first tick (windows are about a second long on this
    cell); ``ul_price_mean`` is the UL price summed over the bin's ticks over their number
    (frames per whole-band tick of UL airtime), ``priced_share`` the share of ticks with a
    price.
    """
    w = pd.DataFrame(record["per_window"])
    w["minute"] = w["first_tick"] // bin_ticks
    w["ticks"] = w["end_tick"] - w["first_tick"]
    allocators = [key for key in COMPARED_KEYS.values() if key in w]
    sums = w.groupby("minute")[
        ["ticks", "frames", "optimum", *allocators, "ul_price_sum", "dl_price_sum", "priced_ticks"]
    ].sum()
    table = pd.DataFrame(
        {
            "minute": sums.index.to_numpy(dtype=np.int64),
            "windows": w.groupby("minute").size().to_numpy(),
            "frames": sums["frames"].to_numpy(),
            "optimum": sums["optimum"].to_numpy(),
        }
    )
    for name in allocators:
        table[name] = sums[name].to_numpy()
    table["ul_price_mean"] = (sums["ul_price_sum"] / sums["ticks"]).to_numpy()
    table["dl_price_mean"] = (sums["dl_price_sum"] / sums["ticks"]).to_numpy()
    table["priced_share"] = (sums["priced_ticks"] / sums["ticks"]).to_numpy()
    table["ul_price_max"] = w.groupby("minute")["ul_price_max"].max().to_numpy()
    return table


def read_time_log(path: str | Path) -> dict[str, float]:
    """Wall time (s) and the largest resident set (MB) of a ``/usr/bin/time -v`` report."""
    text = Path(path).read_text()
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)", text)
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", text)
    if wall is None or rss is None:
        raise ValueError(f"{str(path)!r} is not a /usr/bin/time -v report")
    seconds = 0.0
    for part in wall.group(1).split(":"):
        seconds = 60.0 * seconds + float(part)
    return {"wall_s": seconds, "max_rss_mb": int(rss.group(1)) / 1024}


def sample_tree_rss(root: int, out: str | Path, *, steps: str | Path, every_s: float = 0.5) -> None:
    """Append ``time,step,rss_mb,pss_mb`` to ``out`` every ``every_s`` while process ``root``
    lives: the memory of ``root`` and all its descendants, summed, as resident sets (shared
    pages counted in every process: an upper bound) and as proportional sets (shared pages
    split between their processes: what the tree holds). ``step`` is the first word of the
    last line of ``steps``. The sampler leaves itself out (it may be one of the tree)."""
    with Path(out).open("a") as fh:
        while psutil.pid_exists(root):
            rss, pss = _tree_memory_mb(root)
            lines = Path(steps).read_text().split("\n") if Path(steps).is_file() else []
            step = next((line.split()[0] for line in reversed(lines) if line.strip()), "?")
            fh.write(f"{time.time():.1f},{step},{rss:.1f},{pss:.1f}\n")
            fh.flush()
            time.sleep(every_s)


def _tree_memory_mb(root: int) -> tuple[float, float]:
    """RSS and PSS (MB) of ``root`` and its descendants, summed, this process left out; a
    process gone (or not readable) meanwhile counts 0."""
    try:
        parent = psutil.Process(root)
        tree = [parent, *parent.children(recursive=True)]
    except psutil.Error:
        return 0.0, 0.0
    rss = pss = 0
    for proc in tree:
        if proc.pid == os.getpid():
            continue
        try:
            memory = proc.memory_full_info()
        except psutil.Error:
            continue
        rss, pss = rss + memory.rss, pss + memory.pss
    return rss / 2**20, pss / 2**20


def _tree_peaks(folder: Path) -> dict[str, dict[str, float]]:
    """Per step, the peaks of ``treerss.csv``'s RSS and PSS sums, steps told apart by the
    times of ``steps.log``."""
    samples, log = folder / "treerss.csv", folder / "steps.log"
    if not samples.is_file() or not log.is_file():
        return {}
    ends = []  # "STEP rc=N ISO" lines: when each step ended
    for line in log.read_text().splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[1].startswith("rc="):
            ends.append((parts[0], pd.Timestamp(parts[2]).timestamp()))
    table = pd.read_csv(samples, names=["time", "label", "rss_mb", "pss_mb"])
    peaks: dict[str, dict[str, float]] = {}
    start = -np.inf
    for step, end in ends:
        inside = table[(table["time"] > start) & (table["time"] <= end)]
        peaks[step] = {
            f"tree_{kind}_peak_mb": float(inside[f"{kind}_mb"].max()) for kind in ("rss", "pss")
        }
        start = end
    return peaks


def hour_results(folder: str | Path) -> dict[str, Any]:
    """The results of ``solvers/offline_hour.sh``'s run in ``folder``: totals, runs, minutes."""
    folder = Path(folder)
    records = {step: json.loads((folder / f"{step}.json").read_text()) for step in RUNS}
    peaks = _tree_peaks(folder)
    runs = {
        step: {**read_time_log(folder / f"{step}.time"), **peaks.get(step, {})} for step in RUNS
    }
    compare, solve, ray = records["compare"], records["solve"], records["ray"]
    totals = {
        k: compare[k]
        for k in (
            "optimum_frames",
            "frames_admitted",
            "frames_deliverable",
            "windows",
            "variables",
            "constraints",
            "largest_window_variables",
            "solver",
            "status",
        )
    }
    for key in COMPARED_KEYS.values():
        for suffix in ("frames", "gap", "solver_fallbacks"):
            totals[f"{key}_{suffix}"] = compare[f"{key}_{suffix}"]
    return {
        "robots": records["record"]["robots"],
        "horizon_ticks": records["record"]["horizon_ticks"],
        "commands": (folder / "commands.txt").read_text().splitlines()
        if (folder / "commands.txt").is_file()
        else [],
        "totals": totals,
        "optima": {step: records[step]["optimum_frames"] for step in ("solve", "ray", "compare")},
        "ray_equals_local": ray["optimum_frames"] == solve["optimum_frames"]
        and ray["per_window"]["optimum"] == solve["per_window"]["optimum"],
        "runs": runs,
        "record_and_solve_s": runs["record"]["wall_s"] + runs["solve"]["wall_s"],
        "per_minute": per_minute(compare).to_dict("list"),
    }


def render_hour(results: Mapping[str, Any]) -> str:
    """The table of ``solvers/README.md`` for the hour (checked against the results by a test)."""
    runs, t = results["runs"], results["totals"]
    minutes = results["horizon_ticks"] / MINUTE_TICKS

    def tree(step: str) -> str:
        peak = runs[step].get("tree_pss_peak_mb")
        return "–" if peak is None or peak != peak else f"{peak:,.0f} MB"

    lines = [
        "| step | wall time | peak memory: largest process / process tree (PSS) | result |",
        "|---|---|---|---|",
        f"| record ({minutes:.0f} min of traffic, {results['robots']} robots) | "
        f"{runs['record']['wall_s']:,.0f} s | {runs['record']['max_rss_mb']:,.0f} MB / "
        f"{tree('record')} | {t['frames_admitted']:,} frames admitted |",
        f"| solve, 2 workers | {runs['solve']['wall_s']:,.0f} s | "
        f"{runs['solve']['max_rss_mb']:,.0f} MB / {tree('solve')} | optimum "
        f"{results['optima']['solve']:,.3f} of {t['frames_deliverable']:,} deliverable frames, "
        f"{t['windows']:,} windows, {t['variables']:,} variables |",
        f"| solve on Ray, 2 workers | {runs['ray']['wall_s']:,.0f} s | "
        f"{runs['ray']['max_rss_mb']:,.0f} MB / {tree('ray')} | optimum "
        f"{results['optima']['ray']:,.3f} ("
        + ("the same, bit for bit" if results["ray_equals_local"] else "DIFFERENT")
        + ") |",
        f"| `--compare`, windows from the journal | {runs['compare']['wall_s']:,.0f} s | "
        f"{runs['compare']['max_rss_mb']:,.0f} MB / {tree('compare')} | "
        + ", ".join(
            f"{name} {t[key + '_frames']:,} (gap {t[key + '_gap']:.1%})"
            for name, key in COMPARED_KEYS.items()
        )
        + " |",
    ]
    return "\n".join(lines)
