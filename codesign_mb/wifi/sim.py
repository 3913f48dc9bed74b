"""The slot-level WiFi 6 simulator: queues served by RU allocations every 1 ms tick.

One tick ``k`` (``MacTiming``): expired frames leave the queues (``eq_deadline``; a camera
frame expires ``1 + processing`` ticks before its deadline, the least its state frame needs,
and allocators see that earlier deadline for it); if state
frames are queued, the allocator lays out the DL MU PPDU and each scheduled station is served
``N_SD(r) * e_dl`` bits (``eq_serve``); then, if camera frames are queued, it lays out the UL
TB PPDU with every data symbol left in the tick (``eq_air_ul``): the allocator sizes RUs with
the symbols left if every queued station were triggered, and the PPDU then gets the symbols
left by the Trigger frame and multi-STA BlockAck of the stations it scheduled (their User Info
and per-station fields are what grow with the users). A camera frame served in full
at tick ``k`` queues its state frame at tick ``k + 1 + processing``; a state frame served in
full at tick ``k`` is at the robot at time ``k + 1`` (ticks). A frame whose channel fate (drawn
from the hop's delivery probability, ``eq_per``) is "lost" is sent but never delivered.

The channel state (bits per data subcarrier and symbol of every station, per tick) and the
admitted frames form a :class:`Trace`; :func:`replay` runs any allocator on a trace, and
:func:`codesign_mb.wifi.offline.offline_optimum` bounds what any allocator can do on it.
"""

from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from codesign_mb.core.config import from_mapping, to_mapping
from codesign_mb.wifi.allocators import Allocator, TickDemand
from codesign_mb.wifi.config import WifiConfig, make_allocator

__all__ = [
    "TRACE_FORMAT",
    "ChannelEngine",
    "Frame",
    "ReplayResult",
    "Trace",
    "replay",
]

TRACE_FORMAT = "codesign-wifi-trace/1"


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
        self._airtime_cache: dict[tuple[str, int, int], float] = {}
        self.layouts: list[tuple[int, str, NDArray[np.int64]]] | None = None

    # ------------------------------------------------------------------ frames
    def add(self, frame: Frame) -> None:
        """Queue an admitted frame; its capture must not be in the past."""
        if frame.capture_tick < self.tick:
            raise ValueError(
                f"frame captured at tick {frame.capture_tick} but the channel is at {self.tick}"
            )
        self.ul_q[frame.station].append(frame)
        self.stats.frames[frame.station] += 1

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
        bits = self._sd[layout] * e_sc
        for i in np.flatnonzero(layout >= 0).tolist():
            budget = bits[i]
            q = queues[i]
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
        """Advance one tick with the stations' bits per subcarrier-symbol for UL and DL."""
        k = self.tick
        if not any(self.ul_q) and not any(self.dl_q):  # an idle tick
            self.tick = k + 1
            return
        mac = self.config.mac
        for queues, reserve in ((self.ul_q, self.dl_reserve_ticks), (self.dl_q, 0)):
            for q in queues:
                if q and any(f.deadline_tick - reserve <= k for f in q):
                    for f in [f for f in q if f.deadline_tick - reserve <= k]:
                        q.remove(f)
                        self._finish(f, "late", k)
        busy = 0.0
        n_dl = 0
        e_dl = dl_bpss * mac.dl_data_symbols
        demand = self._demand(self.dl_q, False, k, e_dl)
        if demand is not None:
            layout = self.dl_allocator.allocate(demand)
            self._record(k, "dl", layout)
            n_dl = int(np.count_nonzero(layout >= 0))
            if n_dl:
                self._serve(self.dl_q, False, k, layout, e_dl)
                data_us = mac.dl_data_symbols * self.symbol_us
                self.stats.dl_ru_us += np.where(
                    layout >= 0, self._sd[layout] / self._full_sd * data_us, 0.0
                )
                busy += self._airtime("dl", n_dl, 0)
        n_ul = sum(1 for q in self.ul_q if q)
        if n_ul:
            # The allocator sizes RUs with the PPDU length it would get if every queued station
            # were triggered (a lower bound); the Trigger frame and the multi-STA BlockAck then
            # address the stations it scheduled, so the PPDU gets the symbols that leaves.
            n_sym = self._airtime("sym", min(n_ul, self._max_users), n_dl)
            if n_sym > 0:
                demand = self._demand(self.ul_q, True, k, ul_bpss * n_sym)
                if demand is not None:
                    layout = self.ul_allocator.allocate(demand)
                    self._record(k, "ul", layout)
                    n_sched = int(np.count_nonzero(layout >= 0))
                    if n_sched:
                        n_sym = self._airtime("sym", n_sched, n_dl)
                        self._serve(self.ul_q, True, k, layout, ul_bpss * n_sym)
                        data_us = n_sym * self.symbol_us
                        self.stats.ul_ru_us += np.where(
                            layout >= 0, self._sd[layout] / self._full_sd * data_us, 0.0
                        )
                        busy += self._airtime("ul", n_sched, 0)
                        busy += data_us
        if busy:
            busy += mac.channel_access_us
        self.busy_us += busy
        self.tick = k + 1

    def _airtime(self, what: str, n_users: int, n_dl: int) -> float:
        """``MacTiming`` figures of a tick, cached by user counts (they are pure functions)."""
        key = (what, n_users, n_dl)
        value = self._airtime_cache.get(key)
        if value is None:
            mac, bw, sym = self.config.mac, self.config.phy.bandwidth_mhz, self.symbol_us
            if what == "sym":
                value = mac.ul_data_symbols(n_users, n_dl, sym, bw)
            elif what == "ul":
                value = mac.ul_overhead_us(n_users, sym)
            else:
                value = mac.dl_exchange_us(n_users, sym, bw)
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


# --------------------------------------------------------------------------- traces


@dataclass(frozen=True)
class Trace:
    """A recorded traffic and channel trace: what every allocator faces, and the LP's data.

    Attributes
    ----------
    config:
        The cell (PHY, MAC, traffic; the scheduler field is ignored on replay).
    horizon_ticks:
        Number of ticks ``T``.
    ul_bpss, dl_bpss:
        ``(n_stations, T)`` bits per data subcarrier and symbol, UL and DL, at each tick
        (``N_BPSCS * R * N_SS`` of the MCS link adaptation chose).
    frames:
        One row per admitted frame: ``station, step, capture_tick, deadline_tick, ul_bits,
        dl_bits, ul_ok, dl_ok``.
    """

    config: WifiConfig
    horizon_ticks: int
    ul_bpss: NDArray[np.float64]
    dl_bpss: NDArray[np.float64]
    frames: pd.DataFrame

    COLUMNS = (
        "station",
        "step",
        "capture_tick",
        "deadline_tick",
        "ul_bits",
        "dl_bits",
        "ul_ok",
        "dl_ok",
    )

    def __post_init__(self) -> None:
        ul = np.asarray(self.ul_bpss, dtype=float)
        dl = np.asarray(self.dl_bpss, dtype=float)
        if ul.ndim != 2 or ul.shape != dl.shape or ul.shape[1] != self.horizon_ticks:
            raise ValueError(
                f"ul_bpss and dl_bpss must both have shape (n_stations, horizon_ticks="
                f"{self.horizon_ticks}), got {ul.shape} and {dl.shape}"
            )
        if np.any(ul < 0) or np.any(dl < 0):
            raise ValueError("ul_bpss and dl_bpss must be >= 0")
        missing = [c for c in self.COLUMNS if c not in self.frames.columns]
        if missing:
            raise ValueError(f"frames lacks columns {missing}")
        f = self.frames
        if len(f) and (
            f["station"].min() < 0
            or f["station"].max() >= ul.shape[0]
            or (f["deadline_tick"] <= f["capture_tick"]).any()
            or f["capture_tick"].min() < 0
        ):
            raise ValueError(
                "frames must have 0 <= station < n_stations, capture_tick >= 0 and "
                "deadline_tick > capture_tick"
            )
        object.__setattr__(self, "ul_bpss", ul)
        object.__setattr__(self, "dl_bpss", dl)

    @property
    def n_stations(self) -> int:
        return int(self.ul_bpss.shape[0])

    def to_json(self) -> dict[str, Any]:
        """The instance-file form (``solvers/README.md``)."""
        return {
            "format": TRACE_FORMAT,
            "config": to_mapping(self.config),
            "n_stations": self.n_stations,
            "horizon_ticks": self.horizon_ticks,
            "ul_bpss": self.ul_bpss.round(6).tolist(),
            "dl_bpss": self.dl_bpss.round(6).tolist(),
            "frames": {c: self.frames[c].astype(int).tolist() for c in self.COLUMNS},
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Trace:
        """Parse the instance-file form; errors name the offending field."""
        if not isinstance(data, dict) or data.get("format") != TRACE_FORMAT:
            raise ValueError(
                f"instance format must be {TRACE_FORMAT!r}, got {data.get('format')!r}"
            )
        unknown = sorted(
            set(data) - {"format", "config", "n_stations", "horizon_ticks", "ul_bpss", "dl_bpss",
                         "frames", "comment"}
        )  # fmt: skip
        if unknown:
            raise ValueError(f"unknown keys {unknown} in the instance")
        config = from_mapping(WifiConfig, data.get("config", {}), where="config")
        frames = data.get("frames", {})
        if not isinstance(frames, dict):
            raise ValueError("frames must be a table of columns")
        table = pd.DataFrame(
            {c: np.asarray(frames.get(c, []), dtype=np.int64) for c in cls.COLUMNS}
        )
        trace = cls(
            config=config,
            horizon_ticks=int(data["horizon_ticks"]),
            ul_bpss=np.asarray(data["ul_bpss"], dtype=float),
            dl_bpss=np.asarray(data["dl_bpss"], dtype=float),
            frames=table,
        )
        if "n_stations" in data and int(data["n_stations"]) != trace.n_stations:
            raise ValueError(
                f"n_stations is {data['n_stations']} but ul_bpss has {trace.n_stations} rows"
            )
        return trace

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json()) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Trace:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"instance file {str(path)!r} does not exist")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"instance file {str(path)!r} is not valid JSON: {exc}") from exc
        return cls.from_json(data)


@dataclass(frozen=True)
class ReplayResult:
    """Outcome of :func:`replay`: per-station summary, per-frame fates, layouts (optional)."""

    summary: pd.DataFrame
    frames: pd.DataFrame
    layouts: list[tuple[int, str, NDArray[np.int64]]] | None

    @property
    def delivered(self) -> int:
        """Frames whose state reached the robot in time."""
        return int(self.summary["delivered"].sum())


def replay(
    trace: Trace,
    allocator: str | tuple[Allocator, Allocator],
    *,
    record_layouts: bool = False,
) -> ReplayResult:
    """Run a scheduler on a recorded trace (deterministic: no randomness left in a trace).

    Parameters
    ----------
    trace:
        The trace.
    allocator:
        A scheduler name (``"greedy"``, ``"convex"``, ``"convex-cvxpy"``) or a
        ``(ul_allocator, dl_allocator)`` pair.
    record_layouts:
        Keep every tick's layout (for validity tests).
    """
    n = trace.n_stations
    if isinstance(allocator, str):
        ul, dl = (
            make_allocator(trace.config, n, allocator),
            make_allocator(trace.config, n, allocator),
        )
    else:
        ul, dl = allocator
    engine = ChannelEngine(trace.config, n, ul, dl)
    if record_layouts:
        engine.layouts = []
    order = trace.frames.sort_values(["capture_tick", "station"], kind="stable")
    rows = order.to_dict("records")
    frames: list[Frame] = []
    j = 0
    for k in range(trace.horizon_ticks):
        while j < len(rows) and rows[j]["capture_tick"] <= k:
            r = rows[j]
            f = Frame(
                int(r["station"]),
                int(r["step"]),
                int(r["capture_tick"]),
                int(r["deadline_tick"]),
                int(r["ul_bits"]),
                int(r["dl_bits"]),
                bool(r["ul_ok"]),
                bool(r["dl_ok"]),
            )
            engine.add(f)
            frames.append(f)
            j += 1
        engine.run_tick(trace.ul_bpss[:, k], trace.dl_bpss[:, k])
    engine.flush()
    fates = pd.DataFrame(
        {
            "station": [f.station for f in frames],
            "step": [f.step for f in frames],
            "fate": [f.fate for f in frames],
            "delivered_tick": [f.delivered_tick for f in frames],
        }
    )
    return ReplayResult(engine.summary(), fates, engine.layouts)
