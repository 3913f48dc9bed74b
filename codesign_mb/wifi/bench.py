"""Per-tick allocation time of the convex allocator (hot path and cvxpy path) and the greedy one.

The demands are taken from replays of staggered, overloaded static-QoS traces (so consecutive
ticks look like a real run and warm starts matter), at 6, 12, 24 and 48 stations on 40 MHz.
Times cover the whole ``allocate`` call (QP data, solve, rounding), in milliseconds.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from codesign_mb.wifi.allocators import (
    ConvexAllocator,
    ConvexAllocatorConfig,
    GreedyEdfAllocator,
    TickDemand,
)

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
    from codesign_mb.wifi.cell import generate_trace
    from codesign_mb.wifi.channel import ChannelConfig
    from codesign_mb.wifi.config import WifiConfig
    from codesign_mb.wifi.sim import replay

    config = WifiConfig(channel=ChannelConfig(fixed_mcs=3))
    trace = generate_trace(config, n_stations, steps=steps, seed=seed)
    ul = _Recorder(GreedyEdfAllocator(40))
    replay(trace, (ul, GreedyEdfAllocator(40)))
    return ul.demands


def _stats(times_s: list[float]) -> dict[str, float]:
    ms = np.asarray(times_s) * 1e3
    return {
        "median_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "mean_ms": float(ms.mean()),
        "ticks": int(ms.size),
    }


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
        ``{"stations": {n: {"hot": {...}, "cvxpy": {...}, "greedy": {...}}}, "target": ...}``
        with ``median_ms``, ``p99_ms``, ``mean_ms`` and ``ticks`` per path.
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
        row: dict[str, Any] = {}
        for name in ("hot", "cvxpy", "greedy"):
            if name == "greedy":
                alloc: Any = GreedyEdfAllocator(40)
            else:
                alloc = ConvexAllocator(
                    ConvexAllocatorConfig(bandwidth_mhz=40, n_stations=n, hot_path=name == "hot")
                )
            sample = demands if name != "cvxpy" else demands[: max(40, len(demands) // 4)]
            alloc.allocate(sample[0])  # setup / compile outside the timing
            times: list[float] = []
            for d in sample:
                start = time.perf_counter()
                alloc.allocate(d)
                times.append(time.perf_counter() - start)
            row[name] = _stats(times)
        out["stations"][str(n)] = row
    hot24 = out["stations"]["24"]["hot"]
    out["meets_target"] = bool(hot24["median_ms"] <= 0.3 and hot24["p99_ms"] <= 1.0)
    return out
