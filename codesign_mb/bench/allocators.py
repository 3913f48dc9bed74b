"""Per-tick allocation time of the convex allocator (hot path and cvxpy path) and the greedy one.

The demands are taken from replays of staggered, overloaded static-QoS traces (so consecutive
ticks look like a real run and warm starts matter), at 6, 12, 24 and 48 stations on 40 MHz.
Times cover the whole ``allocate`` call (admission, QP data, solve, rounding), in
milliseconds, as wall-clock time and as the thread's CPU time (``cpu_*``: not counting the
time the process waits for a core, which is what a loaded, shared machine adds). The hot path
and the greedy allocator are timed on the same ticks, interleaved, so their ratio
(``hot_over_greedy``) is robust to the machine's load.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from codesign_mb.wifi import ConvexAllocator, ConvexAllocatorConfig, GreedyEdfAllocator, TickDemand
from codesign_mb.wifi.cell import generate_trace
from codesign_mb.wifi.channel import ChannelConfig
from codesign_mb.wifi.config import WifiConfig
from codesign_mb.wifi.sim import replay

__all__ = ["STATION_COUNTS", "bench_allocators", "recorded_demands"]

STATION_COUNTS = (6, 12, 24, 48)


class _Recorder:
    """An allocator that records the demands it sees and defers to another."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.plan = inner.plan
        self.demands: list[TickDemand] = []

    def allocate(self, demand: TickDemand) -> np.ndarray:
        self.demands.append(demand)
        return self.inner.allocate(demand)


def recorded_demands(n_stations: int, *, steps: int, seed: int) -> list[TickDemand]:
    """UL demands of a greedy replay of a static-QoS trace (staggered capture, MCS 3)."""

    config = WifiConfig(channel=ChannelConfig(fixed_mcs=3))
    trace = generate_trace(config, n_stations, steps=steps, seed=seed)
    ul = _Recorder(GreedyEdfAllocator(40))
    replay(trace, (ul, GreedyEdfAllocator(40)))
    return ul.demands


def _stats(times_s: list[float], cpu_s: list[float]) -> dict[str, float]:
    ms = np.asarray(times_s) * 1e3
    cpu = np.asarray(cpu_s) * 1e3
    return {
        "median_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "mean_ms": float(ms.mean()),
        "cpu_median_ms": float(np.median(cpu)),
        "cpu_p99_ms": float(np.percentile(cpu, 99)),
        "ticks": int(ms.size),
    }


def _time(alloc: Any, demands: list[TickDemand]) -> tuple[list[float], list[float]]:
    wall, cpu = [], []
    clock, cpu_clock = time.perf_counter, time.thread_time
    for d in demands:
        c0, w0 = cpu_clock(), clock()
        alloc.allocate(d)
        w1, c1 = clock(), cpu_clock()
        wall.append(w1 - w0)
        cpu.append(c1 - c0)
    return wall, cpu


def bench_allocators(*, repeats: int = 3, seed: int = 0) -> dict[str, Any]:
    """Per-tick allocation time, median and p99, for 6/12/24/48 stations (40 MHz).

    Parameters
    ----------
    repeats:
        Passes over the recorded demands (``steps = 2 * repeats`` control steps each).
    seed:
        Seed of the traces.

    Returns
    -------
    dict
        ``{"stations": {n: {"hot": {...}, "cvxpy": {...}, "greedy": {...}, "hot_over_greedy":
        {...}, "cvxpy_over_hot_median": r}}, "target": ..., "meets_target": bool,
        "meets_target_cpu": bool}`` with ``median_ms``, ``p99_ms``, ``mean_ms``,
        ``cpu_median_ms``, ``cpu_p99_ms`` and ``ticks`` per path.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    out: dict[str, Any] = {
        "bandwidth_mhz": 40,
        "target": {"stations": 24, "hot_median_ms": 0.3, "hot_p99_ms": 1.0},
        "stations": {},
    }
    for n in STATION_COUNTS:
        demands = recorded_demands(n, steps=2 * repeats, seed=seed)
        demands = [d for d in demands if np.any(d.backlog_bits > 0)]
        hot = ConvexAllocator(ConvexAllocatorConfig(bandwidth_mhz=40, n_stations=n))
        ref = ConvexAllocator(ConvexAllocatorConfig(bandwidth_mhz=40, n_stations=n, hot_path=False))
        greedy = GreedyEdfAllocator(40)
        for alloc in (hot, greedy):  # OSQP setups of every model size, placement memos
            for d in demands:
                alloc.allocate(d)
        sample = demands[: max(40, len(demands) // 4)]
        ref.allocate(sample[0])  # cvxpy compilation
        times: dict[str, tuple[list[float], list[float]]] = {
            name: ([], []) for name in ("hot", "greedy")
        }
        for d in demands:  # interleaved: both see the same load
            for name, alloc in (("hot", hot), ("greedy", greedy)):
                wall, cpu = _time(alloc, [d])
                times[name][0].extend(wall)
                times[name][1].extend(cpu)
        row: dict[str, Any] = {name: _stats(*times[name]) for name in ("hot", "greedy")}
        row["cvxpy"] = _stats(*_time(ref, sample))
        row["hot_over_greedy"] = {
            "median": row["hot"]["median_ms"] / row["greedy"]["median_ms"],
            "p99": row["hot"]["p99_ms"] / row["greedy"]["p99_ms"],
            "cpu_median": row["hot"]["cpu_median_ms"] / row["greedy"]["cpu_median_ms"],
        }
        row["cvxpy_over_hot_median"] = row["cvxpy"]["median_ms"] / row["hot"]["median_ms"]
        out["stations"][str(n)] = row
    hot24 = out["stations"]["24"]["hot"]
    out["meets_target"] = bool(hot24["median_ms"] <= 0.3 and hot24["p99_ms"] <= 1.0)
    out["meets_target_cpu"] = bool(hot24["cpu_median_ms"] <= 0.3 and hot24["cpu_p99_ms"] <= 1.0)
    return out
