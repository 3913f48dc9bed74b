"""Benchmark of the offline allocation LP at scale: a 48-robot cell, 10 s and 60 s of traffic.

Each case records a trace on the ``paper`` cell (``codesign wifi trace``) and solves [lp] by
windows (:mod:`codesign_mb.wifi.offline_windows`) with two pool workers, in a fresh process of
its own so that its peak memory (the process's and its workers' largest resident set) is the
case's alone. Cases:

* ``codesign`` traffic, every robot asking for 10 % of its packets (the co-design's rate on
  ``realistic``): frames leave the cell idle now and then, the horizon splits;
* ``static`` traffic (``q = 1``, the issue's instance): frames in flight at every tick, one
  window, solved whole by the interior point; only the 10 s trace (the 60 s one needs about
  6x the memory of the 10 s one, beyond a laptop's).

Reported per case: trace recording, LP build and solve wall times (median over repeats, at
most 3), peak memory, variables, windows; and the ratio of the 60 s to the 10 s solve time of
the co-design traffic, measured in the same run (linear scaling: 6.0).
"""

from __future__ import annotations

import functools
import resource
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any

from codesign_mb.evaluation.pool import imap
from codesign_mb.wifi.cell import generate_trace
from codesign_mb.wifi.offline_windows import solve_windows
from codesign_mb.wifi.presets import CHANNEL_PRESETS

__all__ = ["bench_offline_lp"]

ROBOTS = 48
CASES = (("codesign", 0.1, 10), ("codesign", 0.1, 60), ("static", 1.0, 10))
"""(traffic, requested reliability, seconds of traffic)."""


def _case(reliability: float, seconds: int, seed: int, workers: int) -> dict[str, Any]:
    """Record and solve one trace; wall times and this process tree's peak memory."""
    config = CHANNEL_PRESETS["paper"]
    steps = round(seconds / (config.traffic.period_ticks(config.mac.tick_us) * 1e-3))
    start = time.perf_counter()
    trace = generate_trace(config, ROBOTS, steps=steps, reliability=reliability, seed=seed)
    recorded = time.perf_counter()
    result = solve_windows(trace, mapper=functools.partial(imap, workers=workers))
    solved = time.perf_counter()
    peak_kb = max(
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
        resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss,
    )
    table = result.windows
    return {
        "trace_s": recorded - start,
        "build_s": float(table["build_time_s"].sum()),
        "solve_wall_s": solved - recorded,
        "peak_memory_mb": peak_kb / 1024,
        "variables": result.n_variables,
        "largest_window_variables": int(table["variables"].max()),
        "windows": len(table),
        "frames": len(trace.frames),
        "optimum_frames": result.optimum,
        "status": result.status,
    }


def _isolated(reliability: float, seconds: int, seed: int, workers: int) -> dict[str, Any]:
    """:func:`_case` in a fresh process (its own peak memory)."""
    with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn")) as ex:
        return ex.submit(_case, reliability, seconds, seed, workers).result()


def bench_offline_lp(*, repeats: int, seed: int, workers: int = 2) -> dict[str, Any]:
    """The cases of the module docstring; medians over ``min(repeats, 3)`` runs."""
    n = max(1, min(repeats, 3))
    out: dict[str, Any] = {"robots": ROBOTS, "workers": workers, "runs": n}
    for traffic, q, seconds in CASES:
        runs = [_isolated(q, seconds, seed, workers) for _ in range(n)]
        name = f"{traffic}_{seconds}s"
        for key in ("trace_s", "build_s", "solve_wall_s", "peak_memory_mb"):
            out[f"{name}_{key}"] = statistics.median(r[key] for r in runs)
        for key in ("variables", "largest_window_variables", "windows", "frames"):
            out[f"{name}_{key}"] = runs[0][key]
        out[f"{name}_optimum_frames"] = runs[0]["optimum_frames"]
        out[f"{name}_status"] = runs[0]["status"]
    out["codesign_ratio_60s_to_10s"] = (
        out["codesign_60s_solve_wall_s"] / out["codesign_10s_solve_wall_s"]
    )
    return out
