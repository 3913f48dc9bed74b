"""Choose the surplus weights (``beta``, ``gamma``) of the per-tick objective on ``dev`` traces.

Frames delivered in time by the tick-optimal and the convex allocators on 24 static-QoS traces
(8 cells: at capacity, overloaded, synchronised capture, latency 2, fading with q = 0.5; 3
seeds of the ``dev`` set each), for every ``beta`` x ``gamma`` of the grid, as JSON; the
paper's greedy and the improved greedy for reference. The defaults of
:class:`~codesign_mb.wifi.convex.ConvexAllocatorConfig` come from this run.

    python solvers/select_tick_objective.py > runs/select_tick_objective.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import math

from codesign_mb.core.seeds import episode_seeds, seed_set
from codesign_mb.wifi import (
    ChannelConfig,
    ConvexAllocator,
    ConvexAllocatorConfig,
    TrafficConfig,
    WifiConfig,
    generate_trace,
    replay,
)
from codesign_mb.wifi.tick_optimal import TickOptimalAllocator, TickOptimalConfig

CELL = WifiConfig(channel=ChannelConfig(fixed_mcs=1, q0=0.9, rician_k_db=math.inf))
SYNC = WifiConfig(channel=CELL.channel, traffic=TrafficConfig(capture="synchronised"))
FADE = WifiConfig(channel=ChannelConfig(distance_range_m=(5.0, 40.0)))
CELLS = [  # (cell, robots, reliability, latency steps)
    (CELL, 7, 1.0, 1),
    (CELL, 12, 1.0, 1),
    (CELL, 16, 1.0, 1),
    (SYNC, 8, 1.0, 1),
    (SYNC, 12, 1.0, 1),
    (CELL, 10, 1.0, 2),
    (FADE, 16, 0.5, 1),
    (FADE, 24, 0.5, 1),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=3, help="dev seeds per cell")
    parser.add_argument("--beta", type=float, nargs="+", default=[0.5, 0.2, 0.1, 0.05])
    parser.add_argument("--gamma", type=float, nargs="+", default=[0.5, 0.2, 0.1])
    args = parser.parse_args()
    seeds = episode_seeds(seed_set("dev"), args.seeds)
    traces = [
        generate_trace(c, r, steps=5, reliability=q, latency_steps=tau, seed=s)
        for (c, r, q, tau) in CELLS
        for s in seeds
    ]
    out = {k: sum(replay(t, k).delivered for t in traces) for k in ("greedy", "greedy-admit")}
    rows = []
    for beta, gamma in itertools.product(args.beta, args.gamma):
        row = {"beta": beta, "gamma": gamma, "tick_optimal": 0, "convex": 0}
        for t in traces:
            n = t.n_stations
            opt = TickOptimalConfig(n_stations=n, surplus_weight=beta, surplus_decay=gamma)
            cvx = ConvexAllocatorConfig(n_stations=n, surplus_weight=beta, surplus_decay=gamma)
            pair = (TickOptimalAllocator(opt), TickOptimalAllocator(opt))
            row["tick_optimal"] += replay(t, pair).delivered
            row["convex"] += replay(t, (ConvexAllocator(cvx), ConvexAllocator(cvx))).delivered
        rows.append(row)
    print(json.dumps({"traces": len(traces), **out, "grid": rows}, indent=2))


if __name__ == "__main__":
    main()
