"""RU allocators: one OFDMA layout per PPDU, called every schedule tick (1 ms).

Interface
---------
An :class:`Allocator` gets a :class:`TickDemand` (per station: queued bits, the head-of-line
frame's remaining bits and ticks to its deadline, and the bits one data subcarrier carries
over this PPDU at the station's MCS) and returns one RU index per station (``-1`` = none).
The layout must be valid: pairwise non-overlapping RUs ([layout]), one per station. A
station given RU ``r`` is served ``N_SD(r) * e_i`` bits ([serve]). An allocator that
solves an optimisation problem and may fall back when its solver fails also satisfies
:class:`ReportsFallbacks` (how many ticks fell back, and why the last one did).

Allocators
----------
:class:`GreedyEdfAllocator`
    The paper's two-stage heuristic (sec. 5): stations in deadline order, each given the
    smallest RU that finishes its head frame by its deadline if served every remaining tick
    ([greedy]); the largest free RU when none suffices; unused spectrum stays idle.
:class:`AdmissionGreedyAllocator`
    The improved greedy: admission control ([admit]), the paper's rule for the admitted
    frames, spectrum left over to the backlog in deadline order.
:class:`~codesign_mb.wifi.convex.ConvexAllocator`
    Admission control ([admit], RU-size-aware), then the per-tick QP relaxation
    [qp] (:mod:`codesign_mb.wifi.convex_qp`), rounded to a valid layout ([round]).
:class:`~codesign_mb.wifi.tick_optimal.TickOptimalAllocator`
    The same admission, then the exact per-tick optimum of the objective of [qp]
    (:mod:`codesign_mb.wifi.tick_dp`).

All place RUs with :class:`RuPacker` (best fit in the free spectrum, memoised).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from codesign_mb.wifi.admission import admit_lists
from codesign_mb.wifi.phy import RuPlan, ru_plan

if TYPE_CHECKING:
    from codesign_mb.wifi.config import WifiConfig

__all__ = [
    "AdmissionGreedyAllocator",
    "Allocator",
    "GreedyEdfAllocator",
    "ReportsFallbacks",
    "RuPacker",
    "TickDemand",
    "admission_greedy_allocator",
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
        Value of each station's head frame for admission control ([admit]); ``None``:
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


@runtime_checkable
class ReportsFallbacks(Protocol):
    """An allocator whose solver may fail: it then falls back, and counts it.

    Attributes
    ----------
    fallbacks:
        Ticks whose solver solution could not be used (failed status, non-finite values), so
        the layout came from the allocator's fallback instead.
    last_fallback_reason:
        Why the last fallback happened (solver and status), ``None`` before any.
    """

    fallbacks: int
    last_fallback_reason: str | None


def layout_is_valid(plan: RuPlan, layout: NDArray[np.int64]) -> bool:
    """[layout]: indices in range and pairwise non-overlapping RUs."""
    return plan.is_valid_layout(layout)


def served_bits(plan: RuPlan, layout: NDArray[np.int64], demand: TickDemand) -> NDArray:
    """[serve]: bits each station can send with its RU this tick (not capped by backlog)."""
    sd = np.array([u.data_subcarriers for u in plan.units] + [0])
    return sd[np.asarray(layout)] * demand.bits_per_subcarrier


# --------------------------------------------------------------------------- packing

_MEMO_LIMIT = 1 << 18
"""Entries of a packer's placement memo before it is cleared (bounds memory on 80 MHz)."""


class RuPacker:
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
        self.size_sd_lo = self.size_sd / (1.0 - 1e-9)  # smallest_size_for, for searchsorted
        self.size_sd_lo_list = self.size_sd_lo.tolist()
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
        k = np.searchsorted(self.size_sd_lo, subcarriers, side="left")
        return np.minimum(k, len(self.sizes) - 1).tolist()

    def seat(self, lay: list[int], used: int, need: list[float], order: list[int]) -> int:
        """Give each station of ``order`` without an RU the smallest one carrying ``need``."""
        full, mask, lo, last = self.full, self.mask, self.size_sd_lo_list, len(self.sizes) - 1
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

    def grow(self, lay: list[int], used: int, need: list[float], order: list[int]) -> int:
        """Give spectrum away towards ``need`` (data subcarriers), stations in ``order``: each
        station's RU is replaced by the largest free one (its own included) up to the smallest
        carrying its need, when larger; then stations without an RU are seated (:meth:`seat`).

        Unlike :meth:`fill`, an RU may move, so a neighbour does not block its growth.
        """
        sd, mask, full, lo = self.sd_list, self.mask, self.full, self.size_sd_lo_list
        last = len(lo) - 1
        for i in order:
            if used == full:
                return used
            r = lay[i]
            if r < 0 or sd[r] >= need[i]:
                continue
            without = used & ~mask[r]
            r2 = self.place_at_most(min(bisect.bisect_left(lo, need[i]), last), without)
            if sd[r2] > sd[r]:
                lay[i] = r2
                used = without | mask[r2]
        if used != full:
            used = self.seat(lay, used, need, order)
        return used


# --------------------------------------------------------------------------- greedy


@dataclass
class GreedyEdfAllocator:
    """The paper's QoS-aware greedy scheduler (sec. 5, step 2; [greedy]).

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
        self._packer = RuPacker(self.plan)

    def allocate(self, demand: TickDemand) -> NDArray[np.int64]:
        n = demand.n_stations
        layout = np.full(n, -1, dtype=np.int64)
        e = demand.bits_per_subcarrier
        active = np.flatnonzero((demand.backlog_bits > 0) & (e > 0))
        if active.size == 0:
            return layout
        slack = demand.slack_ticks[active]
        order = active[np.lexsort((active, slack))]
        need_sc = demand.head_bits[order] / (  # [greedy]
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


@dataclass
class AdmissionGreedyAllocator:
    """The improved greedy: the paper's rule for the admitted frames, the rest of the band to
    the backlog (deadline order).

    1. Admission ([admit], :func:`~codesign_mb.wifi.admission.admit_lists`): the largest
       set of head frames earliest-deadline-first finishes in time on a band serving
       ``admission_capacity`` full bands per tick (weighted by ``demand.weights``).
    2. The admitted, in deadline order, get the smallest free RU that finishes the head frame
       by its deadline if served every remaining tick ([greedy]), or the largest free one.
    3. Spectrum left over: RUs grow in place, and stations without one are seated, towards the
       whole backlog, admitted stations first, then the rejected, each in deadline order.

    Unlike :class:`GreedyEdfAllocator`, hopeless frames get no spectrum ahead of frames that
    can still make it (under overload the paper's greedy spends the band on them), and no
    spectrum stays idle while a station has backlog.
    """

    bandwidth_mhz: int = 40
    admission_capacity: float = 0.95
    plan: RuPlan = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.plan = ru_plan(self.bandwidth_mhz)
        if not 0.0 < self.admission_capacity <= 1.0:
            raise ValueError(
                f"admission_capacity must be in (0, 1], got {self.admission_capacity!r}"
            )
        self._packer = RuPacker(self.plan)
        self._full_sd = float(self.plan.full_band_data_subcarriers)

    def allocate(self, demand: TickDemand) -> NDArray[np.int64]:
        n = demand.n_stations
        e = demand.bits_per_subcarrier
        active = np.flatnonzero((demand.backlog_bits > 0) & (e > 0))
        if active.size == 0:
            return np.full(n, -1, dtype=np.int64)
        order = active[np.argsort(demand.slack_ticks[active], kind="stable")]
        slack = np.maximum(demand.slack_ticks[order], 1.0)
        head, e_o = demand.head_bits[order], e[order]
        work = head / (e_o * self._full_sd * self.admission_capacity)  # ticks of the band
        ratio = None
        if demand.weights is not None:
            ratio = (work / np.maximum(np.asarray(demand.weights, float)[order], 1e-12)).tolist()
        keep = admit_lists(work.tolist(), slack.tolist(), ratio)
        stations = order.tolist()
        admitted = [i for i, k in zip(stations, keep, strict=True) if k]
        rejected = [i for i, k in zip(stations, keep, strict=True) if not k]
        packer = self._packer
        need = (head / (slack * e_o)).tolist()  # [greedy], subcarriers per tick
        sizes = packer.sizes_for(np.asarray(need))
        lay, used, largest = [-1] * n, 0, len(packer.sizes) - 1
        for i, k, x, ok in zip(stations, sizes, need, keep, strict=True):
            if not ok:
                continue
            r = packer.place_at_least(k, used) if packer.size_sd_list[k] >= x * (1 - 1e-9) else -1
            if r < 0:
                r = packer.place_at_most(largest, used)
            if r < 0:
                break
            lay[i] = r
            used |= packer.mask[r]
        backlog = [0.0] * n
        for i, x in zip(stations, (demand.backlog_bits[order] / e_o).tolist(), strict=True):
            backlog[i] = x
        packer.grow(lay, used, backlog, admitted + rejected)
        return np.asarray(lay, dtype=np.int64)


def admission_greedy_allocator(config: WifiConfig, n_stations: int) -> AdmissionGreedyAllocator:
    """The improved greedy for the cell of ``config`` (registry kind ``greedy-admit``)."""
    return AdmissionGreedyAllocator(config.phy.bandwidth_mhz)
