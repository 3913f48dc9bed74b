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
    Admission control (``eq_admit``), then the per-tick QP relaxation ``eq_qp`` over
    fractional RU assignments by size class, built once (cvxpy ``Parameter``s, DPP) and solved
    on a hot path that calls OSQP directly with ``P`` and ``A`` fixed and only ``q, u`` updated
    per tick; the fractional solution is rounded to a valid layout (``eq_round``).

Admission (``eq_admit``)
------------------------
The channel is one machine that serves ``c`` full bands per tick (``c`` =
:attr:`ConvexAllocatorConfig.admission_capacity`); station ``i``'s head frame needs ``p_i =
H_i / (S e_i)`` ticks of the full band (``S`` data subcarriers of the widest RU) and is due in
``s_i`` ticks. The admitted set is the largest set that earliest-deadline-first finishes in
time (Moore-Hodgson: take the frames in deadline order and, whenever the running total of
``p / c`` passes a deadline, reject the frame of the largest ``p_i / w_i``, ``w_i`` the frame's
value, 1 by default). Rejected frames get no share of the relaxation, only the spectrum left
at the end of the rounding: under overload the band goes to the frames that can still make it
instead of being spread over all of them (EDF's domino effect).

For the admitted frames in deadline order, the as-late-as-possible schedule starts frame ``j``
at ``L_j = min_{k >= j} (s_k - P_k) + P_{j-1}`` (``P`` the running sum of ``p / c``); the part
of ``[L_j, L_j + p_j / c]`` inside the current tick is what frame ``j`` *must* get now for all
admitted frames to stay feasible: ``T_j = c |[L_j, L_j + p_j/c] & [0, 1]|``, and ``sum T <=
c``.

``eq_qp`` (per tick; variables scaled to fractions of the full band's ``S`` data subcarriers;
only the admitted stations are variables)::

    max  sum_i a_i t_i + b_i z_i - rho/2 (|x|^2 + |t|^2 + |z|^2)
    s.t. t_i + z_i <= sum_k (N_SD,k / S) x_ik      served subcarriers of station i
         sum_k x_ik <= 1                            one RU per station
         sum_i x_ik <= count_k                      RUs of size k in the channel
         sum_ik units_k x_ik <= n_units             26-tone units of the channel
         0 <= t_i <= T_i,  0 <= z_i <= Z_i,  0 <= x_ik <= active_i

``t_i`` is the service frame ``i`` must get now (value ``a_i = 1``), ``z_i`` service ahead of
need up to the station's backlog ``Z_i`` (value ``b_i = beta gamma^rank_i``, ``rank`` the
frame's place in deadline order among the admitted: earliest deadline first; ``beta`` =
:attr:`~ConvexAllocatorConfig.surplus_weight`, ``gamma`` =
:attr:`~ConvexAllocatorConfig.surplus_decay`).

Rounding (``eq_round``)
-----------------------
Admitted stations in deadline order get the smallest RU carrying their must-serve share
``T_i`` (best fit; the largest free smaller one if none), then RUs grow in place (or stations
are seated) towards the relaxed service ``(t_i + z_i) S``, then towards the whole backlog,
admitted stations first, rejected ones after, each group in deadline order.
"""

from __future__ import annotations

import bisect
import heapq
import math
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from codesign_mb.wifi.phy import RuPlan, ru_plan

__all__ = [
    "Allocator",
    "ConvexAllocator",
    "ConvexAllocatorConfig",
    "GreedyEdfAllocator",
    "TickDemand",
    "admit_edf",
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
    weights:
        Value of each station's head frame for admission control (``eq_admit``); ``None``:
        every frame is worth 1 (maximise the number of frames in time).
    """

    backlog_bits: NDArray[np.float64]
    head_bits: NDArray[np.float64]
    slack_ticks: NDArray[np.float64]
    bits_per_subcarrier: NDArray[np.float64]
    weights: NDArray[np.float64] | None = None

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

_MEMO_LIMIT = 1 << 18
"""Entries of a packer's placement memo before it is cleared (bounds memory on 80 MHz)."""


class _Packer:
    """Places RUs of a requested size into the free spectrum, best fit (buddy style).

    A placement depends only on the requested size and the occupied 26-tone units, so it is
    memoised: after a few ticks almost every placement is one dictionary lookup.
    """

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
        self._size_sd_lo = self.size_sd / (1.0 - 1e-9)  # smallest_size_for, for searchsorted
        self._size_sd_lo_list = self._size_sd_lo.tolist()
        self.full = (1 << plan.n_units) - 1
        # containing RUs of each RU, smallest first (for upgrades)
        self.parents: list[list[int]] = [
            [
                v.index
                for v in sorted(plan.units, key=lambda v: v.tones)
                if v.tones > ru.tones and (v.unit_mask & ru.unit_mask) == ru.unit_mask
            ]
            for ru in plan.units
        ]
        self._exact: dict[int, int] = {}
        self._at_most: dict[int, int] = {}
        self._at_least: dict[int, int] = {}

    def _place_search(self, size_idx: int, used: int) -> int:
        best, best_score = -1, -1
        for index, mask, parent in self.by_size[self.sizes[size_idx]]:
            if mask & used:
                continue
            score = (parent & used).bit_count()
            if score > best_score:
                best, best_score = index, score
        return best

    def place(self, size_idx: int, used: int) -> int:
        """Index of a free RU of size ``sizes[size_idx]`` (best fit), or -1."""
        key = (used << 4) | size_idx
        r = self._exact.get(key)
        if r is None:
            if len(self._exact) > _MEMO_LIMIT:
                self._exact.clear()
            r = self._exact[key] = self._place_search(size_idx, used)
        return r

    def place_at_most(self, size_idx: int, used: int) -> int:
        """The largest free RU no larger than ``sizes[size_idx]``, or -1."""
        key = (used << 4) | size_idx
        r = self._at_most.get(key)
        if r is None:
            if len(self._at_most) > _MEMO_LIMIT:
                self._at_most.clear()
            r = -1
            for k in range(size_idx, -1, -1):
                r = self.place(k, used)
                if r >= 0:
                    break
            self._at_most[key] = r
        return r

    def place_at_least(self, size_idx: int, used: int) -> int:
        """The smallest free RU no smaller than ``sizes[size_idx]``, or -1."""
        key = (used << 4) | size_idx
        r = self._at_least.get(key)
        if r is None:
            if len(self._at_least) > _MEMO_LIMIT:
                self._at_least.clear()
            r = -1
            for k in range(size_idx, len(self.sizes)):
                r = self.place(k, used)
                if r >= 0:
                    break
            self._at_least[key] = r
        return r

    def smallest_size_for(self, subcarriers: float) -> int:
        """Index of the smallest RU size with at least ``subcarriers`` data subcarriers."""
        target = subcarriers * (1.0 - 1e-9)
        for k, sd in enumerate(self.size_sd_list):
            if sd >= target:
                return k
        return len(self.sizes) - 1

    def sizes_for(self, subcarriers: NDArray[np.float64]) -> list[int]:
        """:meth:`smallest_size_for` of every entry (vectorised)."""
        k = np.searchsorted(self._size_sd_lo, subcarriers, side="left")
        return np.minimum(k, len(self.sizes) - 1).tolist()

    def seat(self, lay: list[int], used: int, need: list[float], order: list[int]) -> int:
        """Give each station of ``order`` without an RU the smallest one carrying ``need``."""
        full, mask, lo, last = self.full, self.mask, self._size_sd_lo_list, len(self.sizes) - 1
        for i in order:
            if used == full:
                break
            if lay[i] >= 0 or need[i] <= 0:
                continue
            r = self.place_at_most(min(bisect.bisect_left(lo, need[i]), last), used)
            if r >= 0:
                lay[i] = r
                used |= mask[r]
        return used

    def fill(self, lay: list[int], used: int, need: list[float], order: list[int]) -> int:
        """Give spectrum away towards ``need``: upgrade RUs in place, then seat stations.

        ``need`` is each station's demand in data subcarriers; ``order`` the priority.
        """
        sd, mask, full = self.sd_list, self.mask, self.full
        if used != full:
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
        if used != full:
            used = self.seat(lay, used, need, order)
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
        e = demand.bits_per_subcarrier
        active = np.flatnonzero((demand.backlog_bits > 0) & (e > 0))
        if active.size == 0:
            return layout
        slack = demand.slack_ticks[active]
        order = active[np.lexsort((active, slack))]
        need_sc = demand.head_bits[order] / (  # eq_greedy
            np.maximum(demand.slack_ticks[order], 1.0) * e[order]
        )
        packer = self._packer
        ks = packer.sizes_for(need_sc)
        fits = (packer.size_sd[ks] >= need_sc * (1 - 1e-9)).tolist()
        largest = len(packer.sizes) - 1
        used, full, mask = 0, packer.full, packer.mask
        lay = layout.tolist()
        for i, k, ok in zip(order.tolist(), ks, fits, strict=True):
            r = packer.place_at_least(k, used) if ok else -1
            if r < 0:
                r = packer.place_at_most(largest, used)
            if r < 0:
                break
            lay[i] = r
            used |= mask[r]
            if used == full:
                break
        layout[:] = lay
        return layout


# --------------------------------------------------------------------------- admission


def admit_edf(
    work_ticks: NDArray[np.float64] | list[float],
    slack_ticks: NDArray[np.float64] | list[float],
    weights: NDArray[np.float64] | list[float] | None = None,
) -> NDArray[np.bool_]:
    """``eq_admit``: which jobs of a single machine to keep so that EDF meets every deadline.

    Jobs are given in deadline order (``slack_ticks`` non-decreasing). With unit weights this
    is Moore-Hodgson's algorithm (the most jobs in time); with weights, the job rejected when
    a deadline is passed is the one of the largest ``work / weight``. A job that cannot make
    its deadline alone is never admitted.

    Examples
    --------
    >>> admit_edf(np.array([2.0, 2.0, 1.0]), np.array([2.0, 3.0, 4.0])).tolist()
    [True, False, True]
    """
    work = np.asarray(work_ticks, dtype=float)
    ratio = None if weights is None else (work / np.maximum(weights, 1e-12)).tolist()
    return np.array(_admit(work.tolist(), np.asarray(slack_ticks, float).tolist(), ratio))


def _admit(work: list[float], slack: list[float], ratio: list[float] | None) -> list[bool]:
    """:func:`admit_edf` on lists (the hot path's form)."""
    ratio = work if ratio is None else ratio
    admitted = [True] * len(work)
    heap: list[tuple[float, int]] = []
    total = 0.0
    for j, (pj, sj) in enumerate(zip(work, slack, strict=True)):
        sj += 1e-9
        if pj > sj:  # cannot make it even alone
            admitted[j] = False
            continue
        total += pj
        heapq.heappush(heap, (-ratio[j], -j))  # largest ratio first, then the latest deadline
        if total > sj:
            _, neg = heapq.heappop(heap)
            admitted[-neg] = False
            total -= work[-neg]
    return admitted


def must_serve(
    work_ticks: NDArray[np.float64] | list[float], slack_ticks: NDArray[np.float64] | list[float]
) -> NDArray[np.float64]:
    """Part of the current tick each job of a feasible EDF set needs (as-late-as-possible).

    ``work_ticks`` and ``slack_ticks`` in deadline order; returns the fraction of the machine
    (of one tick) each job must get now, summing to at most 1 (``eq_admit``).

    Examples
    --------
    >>> must_serve([0.5, 1.5], [1.0, 2.0]).tolist()  # two ticks of work in two ticks
    [0.5, 0.5]
    >>> must_serve([0.5, 1.0], [1.0, 2.0]).tolist()  # the second can wait
    [0.5, 0.0]
    """
    work = np.asarray(work_ticks, dtype=float).tolist()
    return np.array(_must(work, np.asarray(slack_ticks, dtype=float).tolist()))


def _must(work: list[float], slack: list[float]) -> list[float]:
    """:func:`must_serve` on lists: ``L_j = min_{k >= j}(s_k - P_k) + P_j - p_j``."""
    cum, total = [], 0.0
    for pj in work:
        total += pj
        cum.append(total)
    must = [0.0] * len(work)
    latest = math.inf
    for j in range(len(work) - 1, -1, -1):
        pj, cj = work[j], cum[j]
        latest = min(latest, slack[j] - cj)
        start = latest + cj - pj
        if start < 1.0:
            start = max(start, 0.0)
            must[j] = min(start + pj, 1.0) - start
    return must


# --------------------------------------------------------------------------- convex


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
        ``rho`` of ``eq_qp``: makes the optimum unique (hot path == cvxpy) and OSQP fast.
    surplus_weight:
        ``beta``: value of service ahead of need of the earliest-deadline admitted frame,
        relative to must-serve service (``a = 1``); in (0, 1).
    surplus_decay:
        ``gamma``: each later deadline's surplus value is this times the previous one's.
    admission:
        Admission control (``eq_admit``). ``False``: every frame that can make its deadline
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
    surplus_weight: float = 0.5
    surplus_decay: float = 0.5
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


def _qp_matrices(m: int, frac_sd: NDArray, units: NDArray) -> tuple[Any, Any, int]:
    """``eq_qp`` for ``m`` stations as OSQP's ``A`` (constraints, then variable bounds)."""
    import scipy.sparse as sp

    k = frac_sd.size
    nv = m * k + 2 * m
    ix = np.arange(m * k).reshape(m, k)
    it = m * k + np.arange(m)
    iz = m * k + m + np.arange(m)
    r_serve = np.arange(m)  # t_i + z_i - sum_k sd_k x_ik <= 0
    r_one = m + np.arange(m)  # sum_k x_ik <= 1
    r_count = 2 * m + np.arange(k)  # sum_i x_ik <= count_k
    r_units = 2 * m + k  # sum units x <= n_units
    rows = np.concatenate(
        [r_serve, r_serve, np.repeat(r_serve, k), np.repeat(r_one, k), np.tile(r_count, m),
         np.full(m * k, r_units)]
    )  # fmt: skip
    cols = np.concatenate([it, iz, ix.ravel(), ix.ravel(), ix.ravel(), ix.ravel()])
    vals = np.concatenate(
        [np.ones(2 * m), np.tile(-frac_sd, m), np.ones(2 * m * k), np.tile(units, m)]
    )
    n_rows = 2 * m + k + 1
    A = sp.vstack(
        [sp.csc_matrix((vals, (rows, cols)), shape=(n_rows, nv)), sp.identity(nv, format="csc")],
        format="csc",
    )
    return A, sp.identity(nv, format="csc"), n_rows


_OSQP_SETTINGS: dict[str, Any] = {
    "verbose": False,
    "polishing": False,
    "warm_starting": True,
    "adaptive_rho": True,
    "adaptive_rho_interval": 25,
    "check_termination": 5,
    "rho": 0.1,
}
"""OSQP settings of the hot path (tolerances and the iteration cap come from the config)."""


class _OsqpModel:
    """An OSQP workspace of ``eq_qp`` for ``m`` station slots (matrices fixed, vectors per tick).

    The solver is driven through its extension object when the installed ``osqp`` exposes it
    (``OSQP._solver``): the Python wrapper's ``update``/``solve`` add ~50 us of bookkeeping
    per tick (derivative caches, an info namespace) that the hot path does not need.
    """

    def __init__(self, m: int, owner: ConvexAllocator) -> None:
        import osqp

        cfg = owner.config
        k = owner._k
        self.m, self.k = m, k
        A, P, n_rows = _qp_matrices(m, owner._frac_sd, owner._units)
        nv = m * k + 2 * m
        self.nv, self.n_rows = nv, n_rows
        self.q = np.zeros(nv)
        self.u = np.concatenate(
            [np.zeros(m), np.ones(m), owner._counts, [float(owner.plan.n_units)], np.zeros(nv)]
        )
        lower = np.concatenate([np.full(n_rows, -np.inf), np.zeros(nv)])
        solver = osqp.OSQP()
        solver.setup(
            P * cfg.regularization,
            self.q,
            A,
            lower,
            self.u,
            **{**_OSQP_SETTINGS, "eps_abs": cfg.eps, "eps_rel": cfg.eps, "max_iter": cfg.max_iter},
        )
        self.solver = solver
        raw = getattr(solver, "_solver", None)
        self._raw = raw if raw is not None and hasattr(raw, "update_data_vec") else None
        # views of the per-tick parts of q and u
        self._qa = self.q[m * k : m * k + m]
        self._qb = self.q[m * k + m :]
        base = n_rows
        self._ux = self.u[base : base + m * k].reshape(m, k)
        self._ut = self.u[base + m * k : base + m * k + m]
        self._uz = self.u[base + m * k + m :]
        self._j = 0  # slots holding a station in q and u

    def solve(self, a: NDArray, b: NDArray, t_max: NDArray, z_max: NDArray) -> NDArray[np.float64]:
        """Solution ``[x (m*k), t, z]``; the first ``len(a)`` slots are the stations."""
        j = a.size
        self._qa[:j] = -a
        self._qb[:j] = -b
        self._ux[:j] = 1.0
        self._ut[:j] = t_max
        self._uz[:j] = z_max
        if j < self._j:  # slots used last time and not now: no station, all zero
            for part in (self._qa, self._qb, self._ux, self._ut, self._uz):
                part[j : self._j] = 0.0
        self._j = j
        if self._raw is not None:
            self._raw.update_data_vec(q=self.q, l=None, u=self.u)
            self._raw.solve()
            x = np.asarray(self._raw.solution.x, dtype=float)
        else:  # pragma: no cover - other osqp builds
            self.solver.update(q=self.q, u=self.u)
            x = np.asarray(self.solver.solve(raise_error=False).x, dtype=float)
        if x.shape != (self.nv,) or not math.isfinite(float(x.sum())):
            return np.zeros(self.nv)
        return x


class _Tick:
    """Per-tick data of :class:`ConvexAllocator`: ``eq_admit`` and the weights of ``eq_qp``.

    ``order`` holds the admitted stations in deadline order; they are also the QP's station
    slots, in that order (``a``, ``b``, ``t_max``, ``z_max`` are aligned with it). ``must`` is
    each admitted station's must-serve share of the band (``T``), ``need_sc`` every station's
    backlog in data subcarriers.
    """

    __slots__ = ("a", "b", "m", "must", "need_sc", "order", "order_list", "rejected", "t_max",
                 "z_max")  # fmt: skip

    def __init__(self, alloc: ConvexAllocator, demand: TickDemand) -> None:
        cfg = alloc.config
        backlog = demand.backlog_bits
        e = demand.bits_per_subcarrier
        m = backlog.shape[0]
        if m > alloc._n:
            raise ValueError(
                f"demand has {m} stations but the allocator was built for n_stations={alloc._n}"
            )
        self.m = m
        act = np.flatnonzero((backlog > 0) & (e > 0))
        slack_all = demand.slack_ticks[act]
        act = act[np.argsort(slack_all, kind="stable")]  # deadline order, ties by index
        e_act = e[act]
        full, c = alloc._full_sd, cfg.admission_capacity
        stations = act.tolist()
        need = (backlog[act] / e_act).tolist()  # whole backlog in data subcarriers
        work = (demand.head_bits[act] / (e_act * (full * c))).tolist()  # ticks at c bands/tick
        slack = np.maximum(demand.slack_ticks[act], 1.0).tolist()
        if cfg.admission:
            ratio = None
            if demand.weights is not None:
                w = np.maximum(np.asarray(demand.weights, dtype=float)[act], 1e-12)
                ratio = (np.asarray(work) / w).tolist()
            keep = _admit(work, slack, ratio)
        else:
            keep = [w <= s + 1e-9 for w, s in zip(work, slack, strict=True)]
        self.need_sc = need_sc = [0.0] * m
        for i, x in zip(stations, need, strict=True):
            need_sc[i] = x
        if all(keep):
            order, self.rejected = stations, []
        else:
            order = [i for i, k in zip(stations, keep, strict=True) if k]
            self.rejected = [i for i, k in zip(stations, keep, strict=True) if not k]
            work = [x for x, k in zip(work, keep, strict=True) if k]
            slack = [x for x, k in zip(slack, keep, strict=True) if k]
            need = [x for x, k in zip(need, keep, strict=True) if k]
        self.order_list = order
        self.order = np.array(order, dtype=np.int64)
        j = len(order)
        self.must = must = [c * x for x in _must(work, slack)]  # fraction of the band, sum <= c
        self.a = alloc._ones[:j]
        self.b = alloc._surplus[:j]
        self.t_max = np.array(must)
        self.z_max = np.array(
            [max(min(x / full, 1.0) - y, 0.0) for x, y in zip(need, must, strict=True)]
        )

    def full(self, n: int) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
        """``a, b, T, Z, active`` for all ``n`` stations of the full model (0 if not in it)."""
        out = np.zeros((5, n))
        out[0, self.order] = self.a
        out[1, self.order] = self.b
        out[2, self.order] = self.t_max
        out[3, self.order] = self.z_max
        out[4, self.order] = 1.0
        return out[0], out[1], out[2], out[3], out[4]


class ConvexAllocator:
    """Admission control (``eq_admit``) and the QP relaxation ``eq_qp``, rounded (``eq_round``).

    The cvxpy model (:attr:`problem`, DPP) is built once for ``config.n_stations`` stations.
    The hot path solves the same problem restricted to the admitted stations (the others'
    variables are zero in the full model too, and the optimum is unique), with OSQP models of
    a few sizes (about 1.25x apart) built on first use, each warm-started from its previous
    solution; per tick only ``q`` and ``u`` change.
    """

    def __init__(self, config: ConvexAllocatorConfig | None = None) -> None:
        self.config = config or ConvexAllocatorConfig()
        cfg = self.config
        self.plan = ru_plan(cfg.bandwidth_mhz)
        self._packer = _Packer(self.plan)
        sizes = self.plan.sizes
        self._n, self._k = cfg.n_stations, len(sizes)
        self._full_sd = float(self.plan.full_band_data_subcarriers)
        self._frac_sd = self._packer.size_sd / self._full_sd
        self._counts = np.array([self.plan.count(t) for t in sizes], dtype=float)
        self._units = np.array([self.plan.of_size(t)[0].n_units for t in sizes], dtype=float)
        self._ones = np.ones(self._n)
        self._surplus = cfg.surplus_weight * cfg.surplus_decay ** np.arange(self._n, dtype=float)
        self._buckets = _bucket_sizes(self._n)
        self._bucket_of = [next(b for b in self._buckets if b >= j) for j in range(self._n + 1)]
        self._models: dict[int, _OsqpModel] = {}
        self._cvx: tuple[Any, ...] | None = None
        self._last: tuple[TickDemand, _Tick] | None = None

    # -- per-tick data --------------------------------------------------------------------------
    def _tick(self, demand: TickDemand) -> _Tick:
        if self._last is not None and self._last[0] is demand:
            return self._last[1]
        tick = _Tick(self, demand)
        self._last = (demand, tick)
        return tick

    def admitted(self, demand: TickDemand) -> NDArray[np.int64]:
        """Stations whose head frame ``eq_admit`` admits, in deadline order."""
        return self._tick(demand).order.copy()

    def _qp_data(self, demand: TickDemand) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """``q, l, u`` of the full ``n``-station model (``v = [x, t, z]``) and ``active``."""
        n, k = self._n, self._k
        a, b, t_max, z_max, active = self._tick(demand).full(n)
        q = np.concatenate([np.zeros(n * k), -a, -b])
        u = np.concatenate(
            [np.zeros(n), np.ones(n), self._counts, [float(self.plan.n_units)],
             np.repeat(active, k), t_max, z_max]
        )  # fmt: skip
        l = np.concatenate([np.full(2 * n + k + 1, -np.inf), np.zeros(n * k + 2 * n)])
        return q, l, u, active

    # -- solvers --------------------------------------------------------------------------------
    def _solve_sized(self, tick: _Tick) -> tuple[NDArray, NDArray, NDArray]:
        """``x, t, z`` of the admitted stations (in ``tick.order``) from the hot path."""
        j = tick.order.size
        size = self._bucket_of[j]
        model = self._models.get(size)
        if model is None:
            model = self._models[size] = _OsqpModel(size, self)
        sol = model.solve(tick.a, tick.b, tick.t_max, tick.z_max)
        k = self._k
        return (
            sol[: size * k].reshape(size, k)[:j],
            sol[size * k : size * k + j],
            sol[size * k + size : size * k + size + j],
        )

    def solve_hot(self, demand: TickDemand) -> NDArray[np.float64]:
        """Relaxed solution ``v = [x, t, z]`` (full ``n``-station layout) by OSQP directly."""
        tick = self._tick(demand)
        n, k = self._n, self._k
        v = np.zeros(n * k + 2 * n)
        if tick.order.size:
            x, t, z = self._solve_sized(tick)
            v[: n * k].reshape(n, k)[tick.order] = x
            v[n * k + tick.order] = t
            v[n * k + n + tick.order] = z
        return v

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
    def problem(self) -> Any:
        """The cvxpy model of ``eq_qp`` (built on first use)."""
        if self._cvx is None:
            self._build_cvxpy()
        assert self._cvx is not None
        return self._cvx[0]

    def solve_cvxpy(self, demand: TickDemand) -> NDArray[np.float64]:
        """Relaxed solution ``v = [x, t, z]`` from the cvxpy model (reference path)."""
        if self._cvx is None:
            self._build_cvxpy()
        assert self._cvx is not None
        problem, x, t, z, a, b, t_max, z_max, active = self._cvx
        values = self._tick(demand).full(self._n)
        for param, value in zip((a, b, t_max, z_max, active), values, strict=True):
            param.value = value
        solver = self.config.cvxpy_solver.upper()
        kwargs = (
            {"eps_abs": self.config.eps, "eps_rel": self.config.eps} if solver == "OSQP" else {}
        )
        problem.solve(solver=solver, warm_start=True, **kwargs)
        if x.value is None:
            return np.zeros(self._n * self._k + 2 * self._n)
        return np.concatenate([np.asarray(x.value).ravel(), t.value, z.value])

    # -- rounding -------------------------------------------------------------------------------
    def round(self, v: NDArray[np.float64], demand: TickDemand) -> NDArray[np.int64]:
        """``eq_round``: a valid layout from the relaxed solution ``v`` (full layout)."""
        tick = self._tick(demand)
        n, k = self._n, self._k
        order = tick.order
        served = v[n * k + order] + v[n * k + n + order]
        return self._round(tick, served)

    def _round(self, tick: _Tick, served: NDArray[np.float64]) -> NDArray[np.int64]:
        """``eq_round`` from the relaxed service ``t + z`` of the admitted (``tick.order``)."""
        packer = self._packer
        lay = [-1] * tick.m
        order = tick.order_list
        used = 0
        if order:
            # 1. must-serve shares, deadline order (the relaxation's bound T, free of solver noise)
            full, mask, lo = self._full_sd, packer.mask, packer._size_sd_lo_list
            last = len(lo) - 1
            for i, share in zip(order, tick.must, strict=True):
                if share <= 0.0:
                    continue
                r = packer.place_at_most(min(bisect.bisect_left(lo, share * full), last), used)
                if r >= 0:
                    lay[i] = r
                    used |= mask[r]
            # 2. towards the relaxed service t + z
            target = [0.0] * tick.m
            for i, x in zip(order, served.tolist(), strict=True):
                if x > 1e-3:
                    target[i] = x * full
            used = packer.fill(lay, used, target, order)
        # 3. towards the whole backlog: admitted first, then the rejected
        rest = order + tick.rejected
        if rest:
            packer.fill(lay, used, tick.need_sc, rest)
        return np.asarray(lay, dtype=np.int64)

    def allocate(self, demand: TickDemand) -> NDArray[np.int64]:
        tick = self._tick(demand)
        if not self.config.hot_path:
            return self.round(self.solve_cvxpy(demand), demand)
        if len(tick.order_list) == 1:
            # one station in eq_qp: its optimum (without rho) is the backlog, up to the band
            served = tick.t_max + tick.z_max
        elif tick.order_list:
            _, t, z = self._solve_sized(tick)
            served = t + z
        else:
            served = np.zeros(0)
        return self._round(tick, served)
