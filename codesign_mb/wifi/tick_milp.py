"""The exact per-tick optimum as a MILP (HiGHS through ``scipy.optimize.milp``): the reference.

The per-tick objective is the one of :mod:`codesign_mb.wifi.tick_dp` ([qp] at
``rho = 0``). This formulation shares nothing with the dynamic programme but the plan: it
works on RU positions and their 26-tone units, not on the plan's sub-channel structure::

    max  sum_i a_i t_i + b_i z_i
    s.t. t_i + z_i <= sum_r (N_SD(r) / S) y_ir       service of station i
         sum_r y_ir <= 1                             one RU per station
         sum_i sum_{r covers u} y_ir <= 1            every 26-tone unit u used at most once
         0 <= t_i <= T_i,  0 <= z_i <= Z_i,  y_ir in {0, 1}

([layout]: RUs that share no 26-tone unit share no tone in 802.11ax.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.optimize import Bounds, LinearConstraint, milp

from codesign_mb.wifi.phy import RuPlan

__all__ = ["TickMilpResult", "solve_tick_milp"]


@dataclass(frozen=True)
class TickMilpResult:
    """The exact per-tick optimum: its value, a layout attaining it, HiGHS's status."""

    value: float
    layout: NDArray[np.int64]
    status: str


def solve_tick_milp(
    plan: RuPlan,
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    t_max: NDArray[np.float64],
    z_max: NDArray[np.float64],
    *,
    time_limit_s: float = 60.0,
) -> TickMilpResult:
    """The best valid layout of ``plan`` for the per-tick objective (stations = rows).

    Raises ``RuntimeError`` when HiGHS does not prove optimality (status named).
    """
    m, n_ru = len(a), len(plan.units)
    if m == 0:
        return TickMilpResult(0.0, np.zeros(0, dtype=np.int64), "no station")
    full = float(plan.full_band_data_subcarriers)
    frac = np.array([u.data_subcarriers / full for u in plan.units])
    covers = np.array(
        [[(u.unit_mask >> k) & 1 for u in plan.units] for k in range(plan.n_units)], dtype=float
    )
    ny = m * n_ru  # y (row-major: station, RU), then t, then z
    eye = sp.identity(m, format="csr")
    serve = sp.hstack([sp.kron(eye, -frac[None, :]), eye, eye])
    one = sp.hstack([sp.kron(eye, np.ones((1, n_ru))), sp.csr_matrix((m, 2 * m))])
    units = sp.hstack([sp.kron(np.ones((1, m)), covers), sp.csr_matrix((plan.n_units, 2 * m))])
    constraints = [
        LinearConstraint(serve, -np.inf, 0.0),
        LinearConstraint(one, -np.inf, 1.0),
        LinearConstraint(units, -np.inf, 1.0),
    ]
    cost = np.concatenate([np.zeros(ny), -np.asarray(a, float), -np.asarray(b, float)])
    upper = np.concatenate([np.ones(ny), t_max, z_max])
    integrality = np.concatenate([np.ones(ny), np.zeros(2 * m)])
    res = milp(
        cost,
        constraints=constraints,
        bounds=Bounds(np.zeros(ny + 2 * m), upper),
        integrality=integrality,
        options={"time_limit": time_limit_s, "mip_rel_gap": 1e-9},
    )
    if res.status != 0 or res.x is None:
        raise RuntimeError(f"HiGHS did not solve the per-tick MILP: {res.message}")
    y = res.x[:ny].reshape(m, n_ru) > 0.5
    layout = np.where(y.any(axis=1), y.argmax(axis=1), -1).astype(np.int64)
    return TickMilpResult(float(-res.fun), layout, str(res.message))
