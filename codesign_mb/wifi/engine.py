"""The slot-level WiFi 6 simulator: queues served by RU allocations every 1 ms tick.

One tick ``k`` (:class:`~codesign_mb.wifi.mac.MacTiming`): expired frames leave the queues
([deadline]; a camera frame expires ``1 + processing`` ticks before its deadline, the
least its state frame needs, and allocators see that earlier deadline for it); every
``bsrp_interval_ticks`` the AP polls (BSRP) the stations whose queue it believes empty, and
it sees a camera frame only once a BSR reported it (a poll, or the BSR a station sends with
its data); if state frames are ready, the allocator lays out one DL MU PPDU for all of them,
as long as their longest A-MPDU needs, and each scheduled station is served ``N_SD(r) *
e_dl`` bits ([serve]); then, if reported camera frames are queued, it lays out the UL
TB PPDU with every data symbol left in the tick ([air_ul]): the allocator sizes RUs with
the symbols left if every reported station were triggered, and the PPDU then gets the symbols
left by the Trigger frame and multi-STA BlockAck of the stations it scheduled (their User Info
and per-station fields are what grow with the users). Every served PSDU loses its SERVICE
and tail bits. A camera frame served in full
at tick ``k`` queues its state frame at tick ``k + 1 + processing``; a state frame served in
full at tick ``k`` is at the robot at time ``k + 1`` (ticks). A frame whose channel fate (drawn
from the hop's delivery probability, [per]) is "lost" is sent but never delivered.

:class:`ChannelEngine` is the mutable state of one cell (queues, clock, statistics, and the
allocators' solver fallbacks, :class:`FallbackCount`); :mod:`codesign_mb.wifi.sim` replays
recorded traces through it and :mod:`codesign_mb.wifi.cell` drives it from robots.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from codesign_mb.wifi.allocators import Allocator, ReportsFallbacks, TickDemand
from codesign_mb.wifi.config import WifiConfig

__all__ = ["ChannelEngine", "FallbackCount", "Frame"]


class Frame:
    """One robot frame pair (camera UL, then state DL) moving through the cell."""

    __slots__ = (
        "capture_tick",
        "deadline_tick",
        "delivered_tick",
        "dl_bits",
        "dl_left",
        "dl_ok",
        "dl_ready_tick",
        "fate",
        "station",
        "step",
        "ul_bits",
        "ul_left",
        "ul_ok",
        "value",
    )

    def __init__(
        self,
        station: int,
        step: int,
        capture_tick: int,
        deadline_tick: int,
        ul_bits: int,
        dl_bits: int,
        ul_ok: bool = True,
        dl_ok: bool = True,
        value: Any = None,
    ) -> None:
        self.station = station
        self.step = step
        self.capture_tick = capture_tick
        self.deadline_tick = deadline_tick
        self.ul_bits = ul_bits
        self.dl_bits = dl_bits
        self.ul_left = float(ul_bits)
        self.dl_left = float(dl_bits)
        self.ul_ok = ul_ok
        self.dl_ok = dl_ok
        self.dl_ready_tick = -1
        self.delivered_tick = -1
        self.fate = "queued"  # -> "delivered" | "late" | "lost"
        self.value = value


@dataclass
class _Stats:
    n: int
    frames: NDArray = field(init=False)
    delivered: NDArray = field(init=False)
    late: NDArray = field(init=False)
    lost: NDArray = field(init=False)
    latency_sum_ms: NDArray = field(init=False)
    ul_ru_us: NDArray = field(init=False)
    dl_ru_us: NDArray = field(init=False)

    def __post_init__(self) -> None:
        for name in ("frames", "delivered", "late", "lost"):
            setattr(self, name, np.zeros(self.n, dtype=np.int64))
        for name in ("latency_sum_ms", "ul_ru_us", "dl_ru_us"):
            setattr(self, name, np.zeros(self.n))


@dataclass(frozen=True)
class FallbackCount:
    """Ticks whose allocator could not use its solver's solution and fell back, UL and DL.

    Attributes
    ----------
    ul, dl:
        Fallback ticks of the UL and of the DL allocator since the engine started (0 for an
        allocator without a solver).
    ul_reason, dl_reason:
        The last fallback's reason (solver and status) of each, ``None`` if none.
    """

    ul: int = 0
    dl: int = 0
    ul_reason: str | None = None
    dl_reason: str | None = None

    @property
    def total(self) -> int:
        """Fallback ticks of both directions."""
        return self.ul + self.dl


def _fallbacks_of(allocator: Allocator) -> tuple[int, str | None]:
    """How often ``allocator`` fell back so far, and why last (0, None: it cannot fall back)."""
    if isinstance(allocator, ReportsFallbacks):
        return allocator.fallbacks, allocator.last_fallback_reason
    return 0, None


class ChannelEngine:
    """Mutable state of one cell: queues, clock, statistics (the spec is a :class:`WifiConfig`).

    Parameters
    ----------
    config:
        The cell.
    n_stations:
        Number of robots (stations).
    ul_allocator, dl_allocator:
        Allocators of the UL and the DL PPDUs (two instances: each keeps its own warm start).
    """

    def __init__(
        self,
        config: WifiConfig,
        n_stations: int,
        ul_allocator: Allocator,
        dl_allocator: Allocator,
    ) -> None:
        self.config = config
        self.n = n_stations
        self.ul_allocator = ul_allocator
        self.dl_allocator = dl_allocator
        plan = config.phy.plan
        self.plan = plan
        self._sd = np.array([u.data_subcarriers for u in plan.units] + [0], dtype=float)
        self._full_sd = float(plan.full_band_data_subcarriers)
        self._max_users = plan.count(26)
        self.symbol_us = config.phy.symbol_us
        self.tick_us = config.mac.tick_us
        self.processing_ticks = config.traffic.processing_ticks(self.tick_us)
        # A camera frame must be through by D - 1 - processing: its state frame needs a tick.
        self.dl_reserve_ticks = 1 + self.processing_ticks
        self.tick = 0
        self.ul_q: list[deque[Frame]] = [deque() for _ in range(n_stations)]
        self.dl_q: list[deque[Frame]] = [deque() for _ in range(n_stations)]
        self.delivered: list[list[Frame]] = [[] for _ in range(n_stations)]
        self.stats = _Stats(n_stations)
        self.busy_us = 0.0
        self._airtime_cache: dict[tuple[int, float, bool], int] = {}
        self._txop_ticks_left = 0  # later ticks the current TXOP still covers
        self.ul_symbol_us = config.phy.ul_symbol_us
        # last tick whose queue each station reported to the AP (BSR); -1: never
        self._reported = np.full(n_stations, -1, dtype=np.int64)
        self.layouts: list[tuple[int, str, NDArray[np.int64]]] | None = None
        # allocators may be reused across engines: count their fallbacks from here on
        self._fallbacks_before = (_fallbacks_of(ul_allocator)[0], _fallbacks_of(dl_allocator)[0])

    # ------------------------------------------------------------------ frames
    def add(self, frame: Frame) -> None:
        """Queue an admitted frame; its capture must not be in the past."""
        if frame.capture_tick < self.tick:
            raise ValueError(
                f"frame captured at tick {frame.capture_tick} but the channel is at {self.tick}"
            )
        self.ul_q[frame.station].append(frame)
        self.stats.frames[frame.station] += 1
        if self.config.mac.scheduled_uplink:  # the AP admitted it: known from its capture
            i = frame.station
            self._reported[i] = max(int(self._reported[i]), frame.capture_tick)

    def drop_station(self, station: int) -> None:
        """Forget every queued frame of a station (its robot left the cell)."""
        self.ul_q[station].clear()
        self.dl_q[station].clear()

    def _finish(self, frame: Frame, fate: str, tick: int) -> None:
        frame.fate = fate
        i = frame.station
        if fate == "delivered":
            frame.delivered_tick = tick
            self.stats.delivered[i] += 1
            self.stats.latency_sum_ms[i] += (tick - frame.capture_tick) * self.tick_us / 1000.0
            self.delivered[i].append(frame)
        elif fate == "late":
            self.stats.late[i] += 1
        else:
            self.stats.lost[i] += 1

    # ------------------------------------------------------------------ demand
    def _demand(
        self, queues: list[deque[Frame]], ul: bool, k: int, e_sc: NDArray
    ) -> TickDemand | None:
        n = self.n
        backlog = np.zeros(n)
        head = np.zeros(n)
        slack = np.ones(n)
        any_ = False
        for i in range(n):
            q = queues[i]
            if not q:
                continue
            total = 0.0
            first = None
            for f in q:
                if not ul and f.dl_ready_tick > k:
                    continue
                if ul and f.capture_tick > self._reported[i]:
                    break  # the AP learns of a camera frame from a BSR only
                if first is None:
                    first = f
                total += f.ul_left if ul else f.dl_left
            if first is None:
                continue
            any_ = True
            backlog[i] = total
            head[i] = first.ul_left if ul else first.dl_left
            slack[i] = first.deadline_tick - (self.dl_reserve_ticks if ul else 0) - k
        if not any_:
            return None
        return TickDemand(backlog, head, slack, e_sc)

    def _serve(
        self, queues: list[deque[Frame]], ul: bool, k: int, layout: NDArray, e_sc: NDArray
    ) -> None:
        mac = self.config.mac
        bits = self._sd[layout] * e_sc
        # An A-MPDU that ends inside an MPDU carries it as a dynamic fragment (26.3): one more
        # MAC header, FCS and delimiter.
        fragment_bits = 8 * (mac.mac_header_bytes + mac.fcs_bytes + mac.delimiter_bytes)
        for i in np.flatnonzero(layout >= 0).tolist():
            budget = bits[i] - mac.service_tail_bits  # per PSDU (27.3.12)
            q = queues[i]
            queued = sum(f.ul_left if ul else f.dl_left for f in q)
            if budget < queued:
                budget -= fragment_bits
            done: list[Frame] = []
            for f in q:
                if budget <= 0:
                    break
                if not ul and f.dl_ready_tick > k:
                    continue
                left = f.ul_left if ul else f.dl_left
                used = min(left, budget)
                budget -= used
                left -= used
                if ul:
                    f.ul_left = left
                else:
                    f.dl_left = left
                if left <= 1e-9:
                    done.append(f)
            for f in done:
                q.remove(f)
                if ul:
                    if f.ul_ok:
                        f.dl_ready_tick = k + 1 + self.processing_ticks
                        self.dl_q[i].append(f)
                    else:
                        self._finish(f, "lost", k + 1)
                elif f.dl_ok:
                    self._finish(f, "delivered", k + 1)
                else:
                    self._finish(f, "lost", k + 1)

    # ------------------------------------------------------------------ one tick
    def run_tick(self, ul_bpss: NDArray, dl_bpss: NDArray) -> None:
        """Advance one tick with the stations' bits per subcarrier-symbol for UL and DL.

        The tick opens a TXOP with the channel access, or continues the previous tick's with a
        SIFS when that tick's UL TB PPDU ran to its end and the TXOP limit covers this tick
        (:attr:`~codesign_mb.wifi.mac.MacTiming.txop_ticks`); a beacon or an idle tick ends it.
        """
        k = self.tick
        mac = self.config.mac
        beacon = mac.beacon_us if mac.beacon_due(k) else 0.0
        if not any(self.ul_q) and not any(self.dl_q):  # an idle tick
            self.busy_us += beacon
            self._txop_ticks_left = 0
            self.tick = k + 1
            return
        for queues, reserve in ((self.ul_q, self.dl_reserve_ticks), (self.dl_q, 0)):
            for q in queues:
                if q and any(f.deadline_tick - reserve <= k for f in q):
                    for f in [f for f in q if f.deadline_tick - reserve <= k]:
                        q.remove(f)
                        self._finish(f, "late", k)
        continues = self._txop_ticks_left > 0 and not beacon
        busy = beacon + self._poll(k, ul_bpss)
        dl_ready = [i for i, q in enumerate(self.dl_q) if any(f.dl_ready_tick <= k for f in q)]
        if dl_ready:
            busy += self._downlink(k, dl_ready, dl_bpss)
        ul_us = self._uplink(k, ul_bpss, busy, continues)  # the beacon's airtime included
        busy += ul_us
        if busy > beacon:
            busy += mac.access_us(continues)
        # a UL TB PPDU fills the tick: the next tick may continue this TXOP (10.23.2.8)
        if ul_us > 0:
            self._txop_ticks_left = self._txop_ticks_left - 1 if continues else mac.txop_ticks - 1
        else:
            self._txop_ticks_left = 0
        self.busy_us += busy
        self.tick = k + 1

    def _downlink(self, k: int, ready: list[int], dl_bpss: NDArray) -> float:
        """One DL MU PPDU with every ready state frame the layout fits, in full: airtime in us.

        The allocator lays out RUs for a PPDU sized as if the ready stations shared the band
        equally, every frame due now (an MPDU is not split over PPDUs); the PPDU then lasts as
        long as its longest A-MPDU on its RU needs (at most ``dl_data_symbols``).
        """
        mac = self.config.mac
        n_sym, _ = self._dl_symbols(ready, dl_bpss, self._equal_ru_sd(len(ready)))
        demand = self._demand(self.dl_q, False, k, dl_bpss * n_sym)
        if demand is None:
            return 0.0
        demand = TickDemand(
            demand.backlog_bits,
            demand.head_bits,
            np.ones_like(demand.slack_ticks),
            demand.bits_per_subcarrier,
            demand.weights,
        )
        layout = self.dl_allocator.allocate(demand)
        self._record(k, "dl", layout)
        users = np.flatnonzero(layout >= 0).tolist()
        if not users:
            return 0.0
        sd = int(min(self._sd[layout[i]] for i in users))
        n_sym, ack_sym = self._dl_symbols(users, dl_bpss, sd, self._sd[layout])
        e_dl = dl_bpss * n_sym
        self._serve(self.dl_q, False, k, layout, e_dl)
        data_us = n_sym * self.symbol_us
        self.stats.dl_ru_us += np.where(
            layout >= 0, self._sd[layout] / self._full_sd * data_us, 0.0
        )
        return mac.dl_exchange_us(len(users), n_sym, ack_sym, self.config.phy)

    def _uplink(self, k: int, ul_bpss: NDArray, busy_us: float, continues: bool) -> float:
        """The trigger-based UL exchange of tick ``k`` after ``busy_us`` of other exchanges.

        ``continues``: the tick continues a TXOP (a SIFS instead of the channel access).
        """
        n_ul = sum(1 for i in range(self.n) if self._known(i))
        if not n_ul:
            return 0.0
        # The allocator sizes RUs with the PPDU length it would get if every station with a
        # reported queue were triggered (a lower bound); the Trigger frame and the multi-STA
        # BlockAck then address the stations it scheduled, so the PPDU gets the symbols left.
        n_sym = self._ul_symbols(min(n_ul, self._max_users), busy_us, continues)
        if n_sym <= 0:
            return 0.0
        demand = self._demand(self.ul_q, True, k, ul_bpss * n_sym)
        if demand is None:
            return 0.0
        layout = self.ul_allocator.allocate(demand)
        self._record(k, "ul", layout)
        n_sched = int(np.count_nonzero(layout >= 0))
        if not n_sched:
            return 0.0
        n_sym = self._ul_symbols(n_sched, busy_us, continues)
        self._serve(self.ul_q, True, k, layout, ul_bpss * n_sym)
        for i in np.flatnonzero(layout >= 0).tolist():
            self._reported[i] = k  # its A-MPDU carries a BSR (HE A-Control, 9.2.4.6a.4)
        data_us = n_sym * self.ul_symbol_us
        self.stats.ul_ru_us += np.where(
            layout >= 0, self._sd[layout] / self._full_sd * data_us, 0.0
        )
        return self.config.mac.ul_overhead_us(n_sched, self.config.phy) + data_us

    def _known(self, i: int) -> bool:
        """Whether the AP knows of a queued camera frame of station ``i`` (from a BSR; with
        ``scheduled_uplink``, from its capture on)."""
        q = self.ul_q[i]
        return bool(q) and q[0].capture_tick <= self._reported[i]

    def _poll(self, k: int, ul_bpss: NDArray) -> float:
        """BSRP exchanges of tick ``k`` (every ``bsrp_interval_ticks``): airtime in us.

        Every station whose queue the AP believes empty is polled; each BSRP Trigger addresses
        at most as many stations as the channel has 26-tone RUs, each on an equal RU.
        """
        mac, phy = self.config.mac, self.config.phy
        if mac.scheduled_uplink or k % mac.bsrp_interval_ticks:
            return 0.0
        idle = [i for i in range(self.n) if not self._known(i)]
        airtime = 0.0
        for start in range(0, len(idle), self._max_users):
            group = idle[start : start + self._max_users]
            sd = self._equal_ru_sd(len(group))
            b = float(np.min(ul_bpss[group]))
            n_sym = mac.data_symbols(mac.qos_null_bytes + mac.delimiter_bytes, sd, b)
            airtime += mac.bsrp_exchange_us(len(group), n_sym, phy)
            self._reported[group] = k
        return airtime

    def _equal_ru_sd(self, n_users: int) -> int:
        """Data subcarriers of the largest RU size with room for ``n_users`` equal RUs."""
        plan = self.plan
        tones = max(t for t in plan.sizes if plan.count(t) >= min(n_users, self._max_users))
        return plan.of_size(tones)[0].data_subcarriers

    def _dl_symbols(
        self, users: list[int], dl_bpss: NDArray, sd: int, sd_of: NDArray | None = None
    ) -> tuple[int, int]:
        """Data symbols of a DL MU PPDU (its longest A-MPDU) and of the block-ack TB PPDU.

        Each user's A-MPDU is on ``sd_of[user]`` data subcarriers (default ``sd`` each); the
        acks come back on RUs of ``sd`` subcarriers.
        """
        mac = self.config.mac
        need = 1
        for i in users:
            nbytes = math.ceil(sum(f.dl_left for f in self.dl_q[i]) / 8)
            sub = sd if sd_of is None else int(sd_of[i])
            need = max(need, mac.data_symbols(nbytes, sub, float(dl_bpss[i])))
        b = float(np.min(dl_bpss[users]))
        ack = mac.data_symbols(mac.block_ack_bytes + mac.delimiter_bytes, sd, b)
        return min(mac.dl_data_symbols, need), ack

    def _ul_symbols(self, n_users: int, busy_us: float, continues: bool) -> int:
        """``MacTiming.ul_data_symbols``, cached by user count, busy time and TXOP state."""
        key = (n_users, round(busy_us, 6), continues)
        value = self._airtime_cache.get(key)
        if value is None:
            value = self.config.mac.ul_data_symbols(
                n_users, busy_us, self.config.phy, continues_txop=continues
            )
            self._airtime_cache[key] = value
        return value

    def _record(self, k: int, direction: str, layout: NDArray[np.int64]) -> None:
        if self.layouts is not None:
            self.layouts.append((k, direction, layout.copy()))

    def flush(self) -> None:
        """End of the horizon: every frame still queued is late."""
        for queues in (self.ul_q, self.dl_q):
            for q in queues:
                while q:
                    self._finish(q.popleft(), "late", self.tick)

    @property
    def fallbacks(self) -> FallbackCount:
        """Ticks whose allocator fell back from its solver since this engine started."""
        ul, ul_reason = _fallbacks_of(self.ul_allocator)
        dl, dl_reason = _fallbacks_of(self.dl_allocator)
        ul -= self._fallbacks_before[0]
        if self.dl_allocator is self.ul_allocator:  # one allocator for both: count it once
            dl, dl_reason = 0, None
        else:
            dl -= self._fallbacks_before[1]
        return FallbackCount(ul, dl, ul_reason if ul else None, dl_reason if dl else None)

    def summary(self) -> pd.DataFrame:
        """Per station: frames admitted, delivered in time, late, lost, mean latency, airtime."""
        s = self.stats
        with np.errstate(invalid="ignore", divide="ignore"):
            latency = np.where(s.delivered > 0, s.latency_sum_ms / s.delivered, np.nan)
        return pd.DataFrame(
            {
                "station": np.arange(self.n),
                "frames": s.frames,
                "delivered": s.delivered,
                "late": s.late,
                "lost": s.lost,
                "mean_latency_ms": latency,
                "ul_ru_airtime_ms": s.ul_ru_us / 1000.0,
                "dl_ru_airtime_ms": s.dl_ru_us / 1000.0,
            }
        )
