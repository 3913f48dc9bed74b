"""RU allocators: one OFDMA layout per PPDU, called every schedule tick (1 ms).

Interface
---------
An :class:`Allocator` gets a :class:`TickDemand` (per station: queued bits, the head-of-line
frame's remaining bits and ticks to its deadline, and the bits one data subcarrier carries
over this PPDU at the station's MCS) and returns one RU index per station (``-1`` = none).
The layout must be valid: pairwise non-overlapping RUs (``eq_layout``), one per station. A
station given RU ``r`` is served ``N_SD(r) * e_i`` bits (``eq_serve``).

Allocators
----------
:class:`GreedyEdfAllocator`
    The paper's two-stage heuristic (sec. 5): stations in deadline order, each given the
    smallest RU that finishes its head frame by its deadline if served every remaining tick
    (``eq_greedy``); the largest free RU when none suffices; unused spectrum stays idle.
:class:`ConvexAllocator`
    The per-tick QP relaxation ``eq_qp`` over fractional RU assignments by size class, built
    once (cvxpy ``Parameter``s, DPP) and solved on a hot path that calls OSQP directly with
    ``P`` and ``A`` fixed and only ``q, l, u`` updated per tick; the fractional solution is
    rounded to a valid layout (``eq_round``) and leftover spectrum is filled.

``eq_qp`` (per tick; variables scaled to fractions of the full band's ``S`` data subcarriers)::

    max  sum_i a_i t_i + b_i z_i - rho/2 (|x|^2 + |t|^2 + |z|^2)
    s.t. t_i + z_i <= sum_k (N_SD,k / S) x_ik      served subcarriers of station i
         sum_k x_ik <= 1                            one RU per station
         sum_i x_ik <= count_k                      RUs of size k in the channel
         sum_ik units_k x_ik <= n_units             26-tone units of the channel
         0 <= t_i <= T_i,  0 <= z_i <= Z_i,  0 <= x_ik <= active_i

``t_i`` is the part of station ``i``'s service that keeps its head frame on track (``T_i =
rate needed to finish by the deadline``), valued ``a_i = S e_i / H_i`` (fraction of the frame
per unit of band: cheap frames first, i.e. the most deadlines met) and 0 when even the full
band cannot finish it in time; ``z_i`` is service ahead of need, valued ``b_i = 0.05 a_i /
slack_i`` (earliest deadline first).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from codesign_mb.wifi.phy import RuPlan, ru_plan

__all__ = [
    "Allocator",
    "ConvexAllocator",
    "ConvexAllocatorConfig",
    "GreedyEdfAllocator",
    "TickDemand",
    "layout_is_valid",
    "served_bits",
]


@dataclass(frozen=True)
class TickDemand:
    """What an allocator sees at one tick (arrays of shape ``(n_stations,)``).

    Attributes
    ----------
    backlog_bits:
        Every bit queued at the station (0: nothing to send).
    head_bits:
        Remaining bits of the head-of-line frame.
    slack_ticks:
        Ticks left to serve the head frame, this one included (>= 1).
    bits_per_subcarrier:
        ``e_i``: bits one data subcarrier carries over this PPDU's data symbols at the
        station's MCS (``N_BPSCS * R * N_SS * N_sym``).
    """

    backlog_bits: NDArray[np.float64]
    head_bits: NDArray[np.float64]
    slack_ticks: NDArray[np.float64]
    bits_per_subcarrier: NDArray[np.float64]

    @property
    def n_stations(self) -> int:
        return int(np.shape(self.backlog_bits)[0])


@runtime_checkable
class Allocator(Protocol):
    """Turns a tick's demand into an OFDMA layout."""

    plan: RuPlan

    def allocate(self, demand: TickDemand) -> NDArray[np.int64]:
        """One RU index per station into ``plan.units`` (``-1`` = no RU); a valid layout."""
        ...


def layout_is_valid(plan: RuPlan, layout: NDArray[np.int64]) -> bool:
    """``eq_layout``: indices in range and pairwise non-overlapping RUs."""
    return plan.is_valid_layout(layout)


def served_bits(plan: RuPlan, layout: NDArray[np.int64], demand: TickDemand) -> NDArray:
    """``eq_serve``: bits each station can send with its RU this tick (not capped by backlog)."""
    sd = np.array([u.data_subcarriers for u in plan.units] + [0])
    return sd[np.asarray(layout)] * demand.bits_per_subcarrier


# --------------------------------------------------------------------------- packing


class _Packer:
    """Places RUs of a requested size into the free spectrum, best fit (buddy style)."""

    def __init__(self, plan: RuPlan) -> None:
        self.plan = plan
        self.by_size: dict[int, list[tuple[int, int, int]]] = {}
        for ru in plan.units:
            larger = [v for v in plan.units if v.tones > ru.tones and v.unit_mask & ru.unit_mask]
            parent = min(larger, key=lambda v: v.tones).unit_mask if larger else ru.unit_mask
            self.by_size.setdefault(ru.tones, []).append((ru.index, ru.unit_mask, parent))
        self.sd = np.array([u.data_subcarriers for u in plan.units])
        self.sd_list = [u.data_subcarriers for u in plan.units]
        self.mask = [u.unit_mask for u in plan.units]
        self.sizes = plan.sizes
        self.size_sd = np.array([self.plan.of_size(t)[0].data_subcarriers for t in self.sizes])
        self.size_sd_list = self.size_sd.tolist()
        # containing RUs of each RU, smallest first (for upgrades)
        self.parents: list[list[int]] = [
            [
                v.index
                for v in sorted(plan.units, key=lambda v: v.tones)
                if v.tones > ru.tones and (v.unit_mask & ru.unit_mask) == ru.unit_mask
            ]
            for ru in plan.units
        ]

    def place(self, size_idx: int, used: int) -> int:
        """Index of a free RU of size ``sizes[size_idx]`` (best fit), or -1."""
        best, best_score = -1, -1
        for index, mask, parent in self.by_size[self.sizes[size_idx]]:
            if mask & used:
                continue
            score = (parent & used).bit_count()
            if score > best_score:
                best, best_score = index, score
        return best

    def place_at_most(self, size_idx: int, used: int) -> int:
        """The largest free RU no larger than ``sizes[size_idx]``, or -1."""
        for k in range(size_idx, -1, -1):
            r = self.place(k, used)
            if r >= 0:
                return r
        return -1

    def smallest_size_for(self, subcarriers: float) -> int:
        """Index of the smallest RU size with at least ``subcarriers`` data subcarriers."""
        target = subcarriers * (1.0 - 1e-9)
        for k, sd in enumerate(self.size_sd_list):
            if sd >= target:
                return k
        return len(self.sizes) - 1

    def fill(
        self,
        layout: NDArray[np.int64],
        used: int,
        need_sc: NDArray[np.float64],
        order: list[int],
    ) -> int:
        """Give leftover spectrum away: upgrade RUs in place, then seat stations without one.

        ``need_sc`` is each station's backlog in data subcarriers; ``order`` the priority.
        """
        need = need_sc.tolist()
        lay = layout.tolist()
        sd, mask = self.sd_list, self.mask
        for i in order:
            r = lay[i]
            if r < 0 or sd[r] >= need[i]:
                continue
            for p in self.parents[r]:
                if mask[p] & used & ~mask[r]:
                    break  # the parents only grow: if this one is taken, so are the larger
                used = (used & ~mask[r]) | mask[p]
                lay[i] = r = p
                if sd[p] >= need[i]:
                    break
        for i in order:
            if lay[i] >= 0 or need[i] <= 0:
                continue
            r = self.place_at_most(self.smallest_size_for(need[i]), used)
            if r < 0:
                continue
            lay[i] = r
            used |= mask[r]
        layout[:] = lay
        return used


# --------------------------------------------------------------------------- greedy


@dataclass
class GreedyEdfAllocator:
    """The paper's QoS-aware greedy scheduler (sec. 5, step 2; ``eq_greedy``).

    Stations are taken in order of their head frame's deadline (ties: lower index); each gets
    the smallest free RU whose rate finishes the head frame by its deadline if it is served
    every remaining tick, ``N_SD(r) e_i slack_i >= H_i``; when no free RU is that large it gets
    the largest free one. Spectrum left over stays idle (minimum bandwidth per station).

    Parameters
    ----------
    bandwidth_mhz:
        Channel width (20, 40, 80).
    """

    bandwidth_mhz: int = 40
    plan: RuPlan = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.plan = ru_plan(self.bandwidth_mhz)
        self._packer = _Packer(self.plan)

    def allocate(self, demand: TickDemand) -> NDArray[np.int64]:
        n = demand.n_stations
        layout = np.full(n, -1, dtype=np.int64)
        active = np.flatnonzero(demand.backlog_bits > 0)
        order = active[np.lexsort((active, demand.slack_ticks[active]))]
        used = 0
        packer = self._packer
        for i in order:
            e = demand.bits_per_subcarrier[i]
            if e <= 0:
                continue
            need_sc = demand.head_bits[i] / (max(demand.slack_ticks[i], 1.0) * e)  # eq_greedy
            k = packer.smallest_size_for(need_sc)
            r = -1
            if packer.size_sd[k] >= need_sc * (1 - 1e-9):
                for kk in range(k, len(packer.sizes)):
                    r = packer.place(kk, used)
                    if r >= 0:
                        break
            if r < 0:
                r = packer.place_at_most(len(packer.sizes) - 1, used)
            if r < 0:
                break
            layout[i] = r
            used |= packer.mask[r]
        return layout


# --------------------------------------------------------------------------- convex


@dataclass(frozen=True)
class ConvexAllocatorConfig:
    """Settings of :class:`ConvexAllocator`.

    Parameters
    ----------
    bandwidth_mhz:
        Channel width (20, 40, 80).
    n_stations:
        Problem size the QP is built for (stations beyond it are an error).
    regularization:
        ``rho`` of ``eq_qp``: makes the optimum unique (hot path == cvxpy) and OSQP fast.
    surplus_weight:
        Value of service ahead of need relative to on-track service (``b_i / a_i`` scale).
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
    eps: float = 1e-2
    max_iter: int = 400
    hot_path: bool = True
    cvxpy_solver: str = "OSQP"

    def __post_init__(self) -> None:
        ru_plan(self.bandwidth_mhz)  # validates bandwidth_mhz
        if isinstance(self.n_stations, bool) or not isinstance(self.n_stations, int):
            raise ValueError(f"n_stations must be an integer, got {self.n_stations!r}")
        if self.n_stations < 1:
            raise ValueError(f"n_stations must be >= 1, got {self.n_stations}")
        for name in ("regularization", "surplus_weight", "eps"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        if (
            isinstance(self.max_iter, bool)
            or not isinstance(self.max_iter, int)
            or (self.max_iter < 1)
        ):
            raise ValueError(f"max_iter must be an integer >= 1, got {self.max_iter!r}")
        if self.cvxpy_solver.upper() not in ("OSQP", "CLARABEL"):
            raise ValueError(f"cvxpy_solver must be OSQP or CLARABEL, got {self.cvxpy_solver!r}")


class ConvexAllocator:
    """QP relaxation ``eq_qp`` rounded to a valid layout (``eq_round``).

    The model is built once for ``config.n_stations`` stations: a cvxpy problem with
    ``Parameter``s (:attr:`problem`, DPP) and the same problem as OSQP matrices (hot path).
    Per tick only the objective weights and the bounds change.

    Rounding (``eq_round``): stations in decreasing order of value per subcarrier; each gets
    the smallest RU size carrying its relaxed service, placed best fit, or the largest free
    smaller size; then leftover spectrum upgrades RUs in place and seats waiting stations.
    """

    def __init__(self, config: ConvexAllocatorConfig | None = None) -> None:
        self.config = config or ConvexAllocatorConfig()
        cfg = self.config
        self.plan = ru_plan(cfg.bandwidth_mhz)
        self._packer = _Packer(self.plan)
        n, sizes = cfg.n_stations, self.plan.sizes
        k = len(sizes)
        self._n, self._k = n, k
        self._full_sd = float(self.plan.full_band_data_subcarriers)
        self._frac_sd = np.array([self._packer.size_sd[j] / self._full_sd for j in range(k)])
        self._counts = np.array([self.plan.count(t) for t in sizes], dtype=float)
        self._units = np.array([self.plan.of_size(t)[0].n_units for t in sizes], dtype=float)
        self._build_matrices()
        self._osqp = None
        self._cvx = None
        self._last_demand: TickDemand | None = None
        self._last_vectors: tuple[NDArray, NDArray, NDArray, NDArray] | None = None
        self.last_solution: NDArray[np.float64] | None = None

    # -- model ----------------------------------------------------------------------------------
    def _build_matrices(self) -> None:
        """``eq_qp`` as ``min 1/2 v'Pv + q'v, l <= Av <= u`` with ``v = [x (n*k), t, z]``."""
        import scipy.sparse as sp

        n, k = self._n, self._k
        nv = n * k + 2 * n
        self._nv = nv
        ix = np.arange(n * k).reshape(n, k)
        it = n * k + np.arange(n)
        iz = n * k + n + np.arange(n)
        rows, cols, vals = [], [], []
        r = 0
        for i in range(n):  # t_i + z_i - sum_k sd_k x_ik <= 0
            rows += [r, r] + [r] * k
            cols += [it[i], iz[i], *ix[i]]
            vals += [1.0, 1.0, *(-self._frac_sd)]
            r += 1
        for i in range(n):  # sum_k x_ik <= 1
            rows += [r] * k
            cols += list(ix[i])
            vals += [1.0] * k
            r += 1
        for j in range(k):  # sum_i x_ij <= count_j
            rows += [r] * n
            cols += list(ix[:, j])
            vals += [1.0] * n
            r += 1
        rows += [r] * (n * k)  # sum units x <= n_units
        cols += list(ix.ravel())
        vals += list(np.tile(self._units, n))
        r += 1
        n_rows = r
        # variable bounds as identity rows (OSQP has no bounds)
        A = sp.vstack(
            [
                sp.csc_matrix((vals, (rows, cols)), shape=(n_rows, nv)),
                sp.identity(nv, format="csc"),
            ],
            format="csc",
        )
        self._A = A
        self._n_rows = n_rows
        self._P = sp.identity(nv, format="csc") * self.config.regularization
        self._u_fixed = np.concatenate(
            [np.zeros(n), np.ones(n), self._counts, [float(self.plan.n_units)]]
        )
        self._ix, self._it, self._iz = ix, it, iz

    def _vectors(self, demand: TickDemand) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Per-tick data: weights ``a, b`` and bounds ``T, Z, active`` (``eq_qp``)."""
        n = self._n
        m = demand.n_stations
        if m > n:
            raise ValueError(
                f"demand has {m} stations but the allocator was built for n_stations={n}"
            )
        e = np.zeros(n)
        e[:m] = demand.bits_per_subcarrier
        backlog = np.zeros(n)
        backlog[:m] = demand.backlog_bits
        head = np.zeros(n)
        head[:m] = demand.head_bits
        slack = np.ones(n)
        slack[:m] = np.maximum(demand.slack_ticks, 1.0)
        active = (backlog > 0) & (e > 0)
        cap = np.where(active, e * self._full_sd, 1.0)  # bits per tick with the full band
        need = np.where(active, head / slack / cap, 0.0)  # on-track share of the band
        a = np.where(need <= 1.0 + 1e-12, np.minimum(cap / np.maximum(head, 1.0), 50.0), 0.0)
        a *= active
        b = (self.config.surplus_weight / slack) * np.maximum(a, 1e-2) * active
        # The LP part is scale free; normalising keeps rho's relative weight and OSQP's
        # conditioning the same at every tick.
        top = max(float(a.max()), float(b.max()), 1e-12)
        a /= top
        b /= top
        total = np.where(active, backlog / cap, 0.0)
        t_max = np.minimum(need, 1.0)
        z_max = np.maximum(np.minimum(total, 1.0) - t_max, 0.0)
        return a, b, np.stack([t_max, z_max]), active.astype(float)

    def _qp_data(self, demand: TickDemand) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        a, b, tz, active = self._vectors(demand)
        self._last_demand, self._last_vectors = demand, (a, b, tz, active)
        n, k = self._n, self._k
        q = np.concatenate([np.zeros(n * k), -a, -b])
        upper_var = np.concatenate([np.repeat(active, k), tz[0], tz[1]])
        l = np.concatenate([np.full(self._n_rows, -np.inf), np.zeros(self._nv)])
        u = np.concatenate([self._u_fixed, upper_var])
        return q, l, u, active

    # -- solvers --------------------------------------------------------------------------------
    def solve_hot(self, demand: TickDemand) -> NDArray[np.float64]:
        """Relaxed solution ``v = [x, t, z]`` by OSQP called directly (matrices built once)."""
        q, l, u, _ = self._qp_data(demand)
        if self._osqp is None:
            import osqp

            solver = osqp.OSQP()
            solver.setup(
                self._P,
                q,
                self._A,
                l,
                u,
                verbose=False,
                eps_abs=self.config.eps,
                eps_rel=self.config.eps,
                max_iter=self.config.max_iter,
                polishing=False,
                warm_starting=True,
                adaptive_rho=True,
                adaptive_rho_interval=25,
                check_termination=5,
                rho=0.1,
            )
            self._osqp = solver
        else:
            self._osqp.update(q=q, u=u)
        result = self._osqp.solve(raise_error=False)
        x = np.asarray(result.x, dtype=float)
        if not np.all(np.isfinite(x)):
            x = np.zeros(self._nv)
        return x

    def _build_cvxpy(self) -> None:
        import cvxpy as cp

        n, k = self._n, self._k
        x = cp.Variable((n, k), name="x")
        t = cp.Variable(n, name="t")
        z = cp.Variable(n, name="z")
        a = cp.Parameter(n, nonneg=True, name="a")
        b = cp.Parameter(n, nonneg=True, name="b")
        t_max = cp.Parameter(n, nonneg=True, name="t_max")
        z_max = cp.Parameter(n, nonneg=True, name="z_max")
        active = cp.Parameter(n, nonneg=True, name="active")
        rho = self.config.regularization
        objective = cp.Maximize(
            a @ t + b @ z - rho / 2 * (cp.sum_squares(x) + cp.sum_squares(t) + cp.sum_squares(z))
        )
        constraints = [
            t + z <= x @ self._frac_sd,
            cp.sum(x, axis=1) <= 1,
            cp.sum(x, axis=0) <= self._counts,
            cp.sum(x @ self._units) <= self.plan.n_units,
            x >= 0,
            x <= cp.reshape(active, (n, 1), order="C") @ np.ones((1, k)),
            t >= 0,
            t <= t_max,
            z >= 0,
            z <= z_max,
        ]
        problem = cp.Problem(objective, constraints)
        if not problem.is_dpp():
            raise AssertionError("eq_qp must be DPP")
        self._cvx = (problem, x, t, z, a, b, t_max, z_max, active)

    @property
    def problem(self):
        """The cvxpy model of ``eq_qp`` (built on first use)."""
        if self._cvx is None:
            self._build_cvxpy()
        return self._cvx[0]

    def solve_cvxpy(self, demand: TickDemand) -> NDArray[np.float64]:
        """Relaxed solution ``v = [x, t, z]`` from the cvxpy model (reference path)."""
        if self._cvx is None:
            self._build_cvxpy()
        problem, x, t, z, a, b, t_max, z_max, active = self._cvx
        av, bv, tz, act = self._vectors(demand)
        self._last_demand, self._last_vectors = demand, (av, bv, tz, act)
        a.value, b.value, t_max.value, z_max.value, active.value = av, bv, tz[0], tz[1], act
        solver = self.config.cvxpy_solver.upper()
        kwargs = (
            {"eps_abs": self.config.eps, "eps_rel": self.config.eps} if solver == "OSQP" else {}
        )
        problem.solve(solver=solver, warm_start=True, **kwargs)
        if x.value is None:
            return np.zeros(self._nv)
        return np.concatenate([np.asarray(x.value).ravel(), t.value, z.value])

    # -- rounding -------------------------------------------------------------------------------
    def round(self, v: NDArray[np.float64], demand: TickDemand) -> NDArray[np.int64]:
        """``eq_round``: a valid layout from the relaxed solution ``v``."""
        n, k, m = self._n, self._k, demand.n_stations
        if self._last_demand is demand and self._last_vectors is not None:
            a, b, _, active = self._last_vectors
        else:
            a, b, _, active = self._vectors(demand)
        t = v[n * k : n * k + n][:m]
        z = v[n * k + n :][:m]
        served_l = (np.maximum(t + z, 0.0) * self._full_sd).tolist()
        value_l = (a[:m] * t + b[:m] * z).tolist()
        share_l = v[: n * k].reshape(n, k)[:m].sum(axis=1).tolist()
        active_l = active[:m].tolist()
        slack_l = demand.slack_ticks.tolist()
        chosen = [
            i for i in range(m) if active_l[i] > 0 and share_l[i] > 1e-3 and served_l[i] > 1e-3
        ]
        # decreasing value per subcarrier, then earliest deadline, then index
        chosen.sort(key=lambda i: (-value_l[i] / served_l[i], slack_l[i], i))
        layout = np.full(m, -1, dtype=np.int64)
        packer = self._packer
        used = 0
        for i in chosen:
            r = packer.place_at_most(packer.smallest_size_for(served_l[i] * (1.0 - 1e-3)), used)
            if r >= 0:
                layout[i] = r
                used |= packer.mask[r]
        # leftover spectrum, earliest deadline first
        need_sc = (demand.backlog_bits / np.maximum(demand.bits_per_subcarrier, 1e-12)) * (
            active[:m] > 0
        )
        fill_order = sorted(range(m), key=lambda i: (slack_l[i], i))
        packer.fill(layout, used, need_sc, fill_order)
        return layout

    def allocate(self, demand: TickDemand) -> NDArray[np.int64]:
        if not np.any(demand.backlog_bits > 0):
            return np.full(demand.n_stations, -1, dtype=np.int64)
        v = self.solve_hot(demand) if self.config.hot_path else self.solve_cvxpy(demand)
        self.last_solution = v
        return self.round(v, demand)
