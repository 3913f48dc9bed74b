"""[lp] written in cvxpy, row by row as :mod:`codesign_mb.wifi.offline` states it: the readable
reference the sparse assembly on the hot path is checked against (same optimum), not a solver
path (a modelling layer costs seconds where the arrays cost milliseconds)."""

from __future__ import annotations

from collections import defaultdict
from typing import Any

from codesign_mb.wifi.sim import Trace

__all__ = ["reference_optimum"]


def reference_optimum(trace: Trace, *, solver: str = "HIGHS") -> float:
    """The optimum of [lp] for ``trace``, modelled in cvxpy and solved by ``solver``."""
    import cvxpy as cp

    cfg = trace.config
    mac, phy = cfg.mac, cfg.phy
    p = cfg.traffic.processing_ticks(mac.tick_us)
    n_ul = mac.max_ul_data_symbols(phy, with_dl=False)
    n_ul_dl = mac.max_ul_data_symbols(phy, with_dl=True)
    full = float(phy.plan.full_band_data_subcarriers)
    y = cp.Variable(trace.horizon_ticks, nonneg=True)
    constraints: list[Any] = [y <= 1]
    ul_load: dict[int, list[Any]] = defaultdict(list)  # tick -> UL subcarrier-symbol shares
    dl_load: dict[int, list[Any]] = defaultdict(list)
    delivered = []
    table = trace.frames[["station", "capture_tick", "deadline_tick", "ul_bits", "dl_bits"]]
    ok = (trace.frames["ul_ok"] != 0) & (trace.frames["dl_ok"] != 0)
    for station, capture, deadline, ul_bits, dl_bits in table[ok].to_numpy(dtype=int).tolist():
        dead = min(deadline, trace.horizon_ticks)
        ul_ticks = range(capture, dead - 1 - p)  # the camera frame's ticks
        dl_ticks = range(capture + 1 + p, dead)  # the state frame's ticks
        if len(ul_ticks) == 0 or len(dl_ticks) == 0:
            continue
        U = cp.Variable(len(ul_ticks))  # cumulative fractions sent
        V = cp.Variable(len(dl_ticks))
        constraints += [U >= 0, U <= 1, V >= 0, V <= 1, cp.diff(U) >= 0, cp.diff(V) >= 0]
        sent_u = cp.hstack([U[0], cp.diff(U)])
        sent_v = cp.hstack([V[0], cp.diff(V)])
        for j, k in enumerate(dl_ticks):
            constraints.append(V[j] <= U[min(k - 1 - p - capture, len(ul_ticks) - 1)])
            if n_ul_dl < n_ul:
                constraints.append(sent_v[j] <= y[k])  # a DL exchange in tick k
            bits = trace.dl_bpss[station, k] * mac.dl_data_symbols * full
            dl_load[k].append(sent_v[j] * (dl_bits / bits))
        for j, k in enumerate(ul_ticks):
            bits = trace.ul_bpss[station, k] * n_ul * full
            ul_load[k].append(sent_u[j] * (ul_bits / bits))
        delivered.append(V[len(dl_ticks) - 1])
    if not delivered:
        return 0.0
    share = (n_ul - n_ul_dl) / n_ul if n_ul_dl < n_ul else 0.0
    for k, terms in ul_load.items():
        exchange = share * y[k] if k in dl_load else 0
        constraints.append(cp.sum(cp.hstack(terms)) + exchange <= 1)
    constraints += [cp.sum(cp.hstack(terms)) <= 1 for terms in dl_load.values()]
    problem = cp.Problem(cp.Maximize(cp.sum(cp.hstack(delivered))), constraints)
    problem.solve(solver=solver)
    return float(problem.value)
