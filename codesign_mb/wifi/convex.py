"""The convex RU allocator: admission control, the QP relaxation [qp], rounding.

Per tick, :class:`ConvexAllocator` admits the head frames that earliest-deadline-first can
still finish in time ([admit], :mod:`codesign_mb.wifi.admission`) and whose must-serve
shares, each rounded up to an RU size, fit one layout (RU-size-aware admission: while they do
not, the frame of the largest work per value among those that must be served now is
rejected and the shares recomputed), solves the relaxation
[qp] over fractional RU assignments by size class for the admitted stations
(:mod:`codesign_mb.wifi.convex_qp`: built once, as cvxpy ``Parameter``s (DPP) and as an OSQP
workspace whose ``P`` and ``A`` stay fixed while only ``q, u`` change per tick, the hot path),
and rounds the fractional solution to a valid layout ([round]).

Rounding ([round])
-----------------------
Each admitted station may get an RU size in the support of its relaxed ``x_i``, the size
just below or just above its relaxed service ``(t_i + z_i) S``, or the smallest size
carrying its must-serve share ``T_i``; among those choices the layout that maximises the
per-tick objective ([qp]'s at ``rho = 0``, :mod:`codesign_mb.wifi.tick_dp`) is found
exactly by dynamic programming over the plan's structure. Spectrum left then goes towards
the whole backlog (:meth:`~codesign_mb.wifi.allocators.RuPacker.grow`), admitted stations
first, rejected ones after, each group in deadline order. On 100 seeded random ticks
(``tests/test_wifi_tick_optimum.py``) the rounded layout's gap to the exact per-tick optimum
(the MILP of :mod:`codesign_mb.wifi.tick_milp`) is 0 at the median and at p90.

Solver failures
---------------
After every solve the solver's status is checked. When the solution cannot be used (a failed
status, values that are not finite), the tick falls back to zero relaxed service: the rounding
still offers the admitted frames their must-serve RU sizes (which come from [admit],
not from the solver), then spreads the spectrum towards the backlog. The allocator counts
these ticks (:attr:`ConvexAllocator.fallbacks`, :attr:`ConvexAllocator.last_fallback_reason`);
the simulator reports them (:attr:`codesign_mb.wifi.engine.ChannelEngine.fallbacks`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.wifi.admission import tick_admission
from codesign_mb.wifi.allocators import RuPacker, TickDemand
from codesign_mb.wifi.convex_qp import CvxpyQp, OsqpQp, QpShape
from codesign_mb.wifi.phy import ru_plan
from codesign_mb.wifi.tick_dp import TickDp

__all__ = ["ConvexAllocator", "ConvexAllocatorConfig"]


@dataclass(frozen=True)
class ConvexAllocatorConfig:
    """Settings of :class:`ConvexAllocator`.

    Parameters
    ----------
    bandwidth_mhz:
        Channel width (20, 40, 80).
    n_stations:
        Most stations a demand may have (the cvxpy model's size; the hot path builds OSQP
        models sized to the admitted stations, in a few bucket sizes up to this).
    regularization:
        ``rho`` of [qp]: makes the optimum unique (hot path == cvxpy) and OSQP fast.
    surplus_weight:
        ``beta``: value of service ahead of need of the earliest-deadline admitted frame,
        relative to must-serve service (``a = 1``); in (0, 1).
    surplus_decay:
        ``gamma``: each later deadline's surplus value is this times the previous one's.
        ``beta = 0.05, gamma = 0.2`` were chosen on 24 traces of the ``dev`` seed set (most
        frames delivered in time by this and the tick-optimal allocator together, among beta
        in {0.5, 0.2, 0.1, 0.05} x gamma in {0.5, 0.2, 0.1}; ``solvers/
        select_tick_objective.py``); 0.5, 0.5 delivered 8 % fewer frames.
    admission:
        Admission control ([admit]). ``False``: every frame that can make its deadline
        alone is admitted.
    admission_capacity:
        ``c``: full bands per tick the admission test assumes (below 1 leaves a margin for
        RU packing losses and ticks shortened by a downlink exchange).
    eps:
        OSQP absolute and relative tolerance (the hot path; the relaxation only picks RU sizes,
        and 1 % of the band is a fifth of the smallest RU of 40 MHz).
    max_iter:
        OSQP iteration cap per tick.
    hot_path:
        ``True``: OSQP called directly (fast). ``False``: the cvxpy model (reference).
    cvxpy_solver:
        Solver of the cvxpy path (``"OSQP"``, ``"CLARABEL"``).
    """

    bandwidth_mhz: int = 40
    n_stations: int = 24
    regularization: float = 1e-2
    surplus_weight: float = 0.05
    surplus_decay: float = 0.2
    admission: bool = True
    admission_capacity: float = 0.95
    eps: float = 1e-2
    max_iter: int = 200
    hot_path: bool = True
    cvxpy_solver: str = "OSQP"

    def __post_init__(self) -> None:
        ru_plan(self.bandwidth_mhz)  # validates bandwidth_mhz
        if isinstance(self.n_stations, bool) or not isinstance(self.n_stations, int):
            raise ValueError(f"n_stations must be an integer, got {self.n_stations!r}")
        if self.n_stations < 1:
            raise ValueError(f"n_stations must be >= 1, got {self.n_stations}")
        for name in ("regularization", "eps"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        for name in ("surplus_weight", "surplus_decay", "admission_capacity"):
            value = getattr(self, name)
            top = 1.0 if name == "admission_capacity" else 1.0 - 1e-12
            if not (isinstance(value, int | float) and 0.0 < value <= top):
                raise ValueError(
                    f"{name} must be in (0, 1{']' if top == 1.0 else ')'}, got {value!r}"
                )
        if not isinstance(self.admission, bool):
            raise ValueError(f"admission must be true or false, got {self.admission!r}")
        if (
            isinstance(self.max_iter, bool)
            or not isinstance(self.max_iter, int)
            or (self.max_iter < 1)
        ):
            raise ValueError(f"max_iter must be an integer >= 1, got {self.max_iter!r}")
        if self.cvxpy_solver.upper() not in ("OSQP", "CLARABEL"):
            raise ValueError(f"cvxpy_solver must be OSQP or CLARABEL, got {self.cvxpy_solver!r}")


def _bucket_sizes(n: int) -> list[int]:
    """Model sizes the hot path builds (lazily): about 1.25x apart, up to ``n``."""
    sizes, b = [], 1
    while b < n:
        sizes.append(b)
        b = max(b + 1, round(b * 1.25))
    return [*sizes, n]


class _Tick:
    """Per-tick data of :class:`ConvexAllocator`: [admit] and the weights of [qp].

    ``order`` holds the admitted stations in deadline order; they are also the QP's station
    slots, in that order (``a``, ``b``, ``t_max``, ``z_max`` are aligned with it). ``must`` is
    each admitted station's must-serve share of the band (``T``), ``need_sc`` every station's
    backlog in data subcarriers.
    """

    __slots__ = ("a", "b", "m", "must", "need_sc", "order", "order_list", "rejected", "t_max",
                 "z_max")  # fmt: skip

    def __init__(self, alloc: _TickAllocator, demand: TickDemand) -> None:
        cfg = alloc.config
        backlog = demand.backlog_bits
        e = demand.bits_per_subcarrier
        m = backlog.shape[0]
        if m > alloc._n:
            raise ValueError(
                f"demand has {m} stations but the allocator was built for n_stations={alloc._n}"
            )
        self.m = m
        act, keep, must, need = tick_admission(
            backlog,
            demand.head_bits,
            demand.slack_ticks,
            e,
            demand.weights,
            admission=cfg.admission,
            capacity=cfg.admission_capacity,
            **alloc._admission_args,
        )
        need_sc = np.zeros(m)
        need_sc[act] = need  # whole backlog in data subcarriers
        self.need_sc = need_sc.tolist()
        self.order = order = act[keep]
        self.order_list = order.tolist()
        self.rejected: list[int] = act[~keep].tolist()
        j = len(self.order_list)
        self.t_max = t_max = must[keep]  # must-serve shares T (of the band): sum <= c, fit RUs
        self.must = t_max.tolist()
        self.a = alloc._ones[:j]
        self.b = alloc._surplus[:j]
        self.z_max = np.maximum(np.minimum(need[keep] / alloc._full_sd, 1.0) - t_max, 0.0)

    def full(self, n: int) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
        """``a, b, T, Z, active`` for all ``n`` stations of the full model (0 if not in it)."""
        out = np.zeros((5, n))
        out[0, self.order] = self.a
        out[1, self.order] = self.b
        out[2, self.order] = self.t_max
        out[3, self.order] = self.z_max
        out[4, self.order] = 1.0
        return out[0], out[1], out[2], out[3], out[4]


class _TickAllocator:
    """What the convex and the tick-optimal allocators share: admission ([admit]), the
    per-tick objective (:mod:`codesign_mb.wifi.tick_dp`) and the layout built from it.

    ``config`` needs ``bandwidth_mhz``, ``n_stations``, ``surplus_weight``,
    ``surplus_decay``, ``admission`` and ``admission_capacity``.
    """

    config: Any

    def _setup(self) -> None:
        cfg = self.config
        self.plan = ru_plan(cfg.bandwidth_mhz)
        self._packer = RuPacker(self.plan)
        self._dp = TickDp(self.plan, self._packer)
        self._n, self._k = cfg.n_stations, len(self.plan.sizes)
        self._full_sd = float(self.plan.full_band_data_subcarriers)
        self._ones = np.ones(self._n)
        self._surplus = cfg.surplus_weight * cfg.surplus_decay ** np.arange(self._n, dtype=float)
        self._last: tuple[TickDemand, _Tick] | None = None
        code = {26: 0, 52: 1, 106: 2, 242: 3, 484: 4}
        self._admission_args: dict[str, Any] = {
            "full_sd": self._full_sd,
            "size_sd_lo": self._packer.size_sd_lo,
            "size_code": np.array([code.get(t, 4) for t in self.plan.sizes], dtype=np.int64),
            "n_sub": self._dp.n_sub,
            "extra": self._dp.extra,
        }
        self._all_sizes = np.ones((self._n, self._k), dtype=bool)
        empty = np.zeros(0)  # compile (or load from numba's disk cache) before the first tick
        tick_admission(
            empty, empty, empty, empty, None, admission=True, capacity=1.0, **self._admission_args
        )

    def _tick(self, demand: TickDemand) -> _Tick:
        if self._last is not None and self._last[0] is demand:
            return self._last[1]
        tick = _Tick(self, demand)
        self._last = (demand, tick)
        return tick

    def admitted(self, demand: TickDemand) -> NDArray[np.int64]:
        """Stations whose head frame [admit] admits, in deadline order."""
        return self._tick(demand).order.copy()

    def tick_objective(
        self, demand: TickDemand
    ) -> tuple[NDArray[np.int64], NDArray, NDArray, NDArray, NDArray]:
        """The admitted stations and their ``a, b, T, Z`` (the per-tick objective's data)."""
        tick = self._tick(demand)
        return tick.order.copy(), tick.a.copy(), tick.b.copy(), tick.t_max.copy(), tick.z_max.copy()

    def _layout(self, tick: _Tick, allowed: NDArray[np.bool_] | None) -> NDArray[np.int64]:
        """The best layout of the admitted for the per-tick objective (sizes restricted to
        ``allowed``), then the spectrum left towards the whole backlog ([round])."""
        lay = [-1] * tick.m
        order = tick.order_list
        used = 0
        if order:
            if allowed is None:
                allowed = self._all_sizes[: len(order)]
            sizes, _ = self._dp.solve_objective(tick.a, tick.b, tick.t_max, tick.z_max, allowed)
            used = self._dp.place(order, sizes, lay)
        rest = order + tick.rejected  # admitted first, then the rejected, deadline order
        if rest:
            self._packer.grow(lay, used, tick.need_sc, rest)
        return np.asarray(lay, dtype=np.int64)


class ConvexAllocator(_TickAllocator):
    """Admission control ([admit]) and the QP relaxation [qp], rounded ([round]).

    The cvxpy model (:attr:`problem`, DPP) is built once for ``config.n_stations`` stations.
    The hot path solves the same problem restricted to the admitted stations (the others'
    variables are zero in the full model too, and the optimum is unique), with OSQP models of
    a few sizes (about 1.25x apart) built on first use, each warm-started from its previous
    solution; per tick only ``q`` and ``u`` change.

    Attributes
    ----------
    fallbacks:
        Ticks whose relaxed solution could not be used and were rounded from zero relaxed
        service instead (see the module docstring).
    last_fallback_reason:
        The solver status of the last fallback, ``None`` before any.
    """

    def __init__(self, config: ConvexAllocatorConfig | None = None) -> None:
        self.config = config or ConvexAllocatorConfig()
        self._setup()
        cfg, sizes = self.config, self.plan.sizes
        self._shape = QpShape(
            frac_sd=self._packer.size_sd / self._full_sd,
            counts=np.array([self.plan.count(t) for t in sizes], dtype=float),
            units=np.array([self.plan.of_size(t)[0].n_units for t in sizes], dtype=float),
            n_units=self.plan.n_units,
            regularization=cfg.regularization,
        )
        self._buckets = _bucket_sizes(self._n)
        self._bucket_of = [next(b for b in self._buckets if b >= j) for j in range(self._n + 1)]
        self._models: dict[int, OsqpQp] = {}
        for size in self._buckets:  # every solver model built up front
            self._models[size] = OsqpQp(size, self._shape, eps=cfg.eps, max_iter=cfg.max_iter)
        self._cvx: CvxpyQp | None = None if cfg.hot_path else CvxpyQp(self._n, self._shape)
        self.fallbacks = 0
        self.last_fallback_reason: str | None = None

    # -- per-tick data --------------------------------------------------------------------------
    def _qp_data(self, demand: TickDemand) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """``q, l, u`` of the full ``n``-station model (``v = [x, t, z]``) and ``active``."""
        n, k = self._n, self._k
        a, b, t_max, z_max, active = self._tick(demand).full(n)
        q = np.concatenate([np.zeros(n * k), -a, -b])
        u = np.concatenate(
            [np.zeros(n), np.ones(n), self._shape.counts, [float(self.plan.n_units)],
             np.repeat(active, k), t_max, z_max]
        )  # fmt: skip
        l = np.concatenate([np.full(2 * n + k + 1, -np.inf), np.zeros(n * k + 2 * n)])
        return q, l, u, active

    def _fall_back(self, reason: str) -> None:
        """Count a tick whose relaxed solution cannot be used (rounded from zero service)."""
        self.fallbacks += 1
        self.last_fallback_reason = reason

    # -- solvers --------------------------------------------------------------------------------
    def _solve_sized(self, tick: _Tick) -> tuple[NDArray, NDArray, NDArray] | None:
        """``x, t, z`` of the admitted stations (in ``tick.order``) from the hot path, or
        ``None`` (counted as a fallback) when OSQP's solution cannot be used."""
        j = tick.order.size
        size = self._bucket_of[j]
        model = self._models[size]
        sol = model.solve(tick.a, tick.b, tick.t_max, tick.z_max)
        if sol is None:
            self._fall_back(model.last_status)
            return None
        k = self._k
        return (
            sol[: size * k].reshape(size, k)[:j],
            sol[size * k : size * k + j],
            sol[size * k + size : size * k + size + j],
        )

    def solve_hot(self, demand: TickDemand) -> NDArray[np.float64]:
        """Relaxed solution ``v = [x, t, z]`` (full ``n``-station layout) by OSQP directly.

        All zeros (the fallback, counted in :attr:`fallbacks`) when OSQP's solution cannot be
        used.
        """
        tick = self._tick(demand)
        n, k = self._n, self._k
        v = np.zeros(n * k + 2 * n)
        solution = self._solve_sized(tick) if tick.order.size else None
        if solution is not None:
            x, t, z = solution
            v[: n * k].reshape(n, k)[tick.order] = x
            v[n * k + tick.order] = t
            v[n * k + n + tick.order] = z
        return v

    def _cvxpy_model(self) -> CvxpyQp:
        if self._cvx is None:
            self._cvx = CvxpyQp(self._n, self._shape)
        return self._cvx

    @property
    def problem(self) -> Any:
        """The cvxpy model of [qp] (built on first use)."""
        return self._cvxpy_model().problem

    def solve_cvxpy(self, demand: TickDemand) -> NDArray[np.float64]:
        """Relaxed solution ``v = [x, t, z]`` from the cvxpy model (reference path).

        All zeros (the fallback, counted in :attr:`fallbacks`) when the solver's solution
        cannot be used.
        """
        model = self._cvxpy_model()
        values = self._tick(demand).full(self._n)
        v = model.solve(values, solver=self.config.cvxpy_solver.upper(), eps=self.config.eps)
        if v is None:
            self._fall_back(model.last_status)
            return np.zeros(self._n * self._k + 2 * self._n)
        return v

    # -- rounding -------------------------------------------------------------------------------
    def round(self, v: NDArray[np.float64], demand: TickDemand) -> NDArray[np.int64]:
        """[round]: a valid layout from the relaxed solution ``v`` (full layout)."""
        tick = self._tick(demand)
        n, k = self._n, self._k
        order = tick.order
        served = v[n * k + order] + v[n * k + n + order]
        return self._round(tick, served, v[: n * k].reshape(n, k)[order])

    def _round(
        self, tick: _Tick, served: NDArray[np.float64], x: NDArray[np.float64] | None = None
    ) -> NDArray[np.int64]:
        """[round] from the relaxed solution of the admitted (``tick.order``): service
        ``t + z`` and RU-size shares ``x`` (rows: stations). Each station may get an RU size in
        the support of its ``x``, the size just below or just above its relaxed service, or
        the smallest one carrying its must-serve share ``T``; the best such layout for the
        per-tick objective is found exactly (:class:`~codesign_mb.wifi.tick_dp.TickDp`)."""
        allowed = self._dp.rounding_choices(served, x, tick.t_max)
        return self._layout(tick, allowed)

    def allocate(self, demand: TickDemand) -> NDArray[np.int64]:
        tick = self._tick(demand)
        if not self.config.hot_path:
            return self.round(self.solve_cvxpy(demand), demand)
        j = len(tick.order_list)
        if j == 1:
            # one station in [qp]: its optimum (without rho) is the backlog, up to the band
            served = tick.t_max + tick.z_max
        elif j:
            solution = self._solve_sized(tick)
            if solution is not None:
                return self._round(tick, solution[1] + solution[2], solution[0])
            served = np.zeros(j)
        else:
            served = np.zeros(0)
        return self._round(tick, served)
