"""Capacity of our cell model against ns-3's 802.11ax model on the same robot traffic.

Both sides run ``N`` stations, each with one camera frame (13,500 B up) and one state frame
(32 B down) per 40 ms period, at one fixed MCS, captures staggered or synchronised, and no
channel errors. A frame is delivered if its state frame reaches the robot within the period
([deadline], ``tau = 1``); the *capacity* is the largest ``N`` with at least 95 % of the
frames delivered, found by bisection (the delivered fraction falls with ``N``).

Ours: the slot simulator (:class:`~codesign_mb.wifi.engine.ChannelEngine`) replays the
traffic as a :class:`~codesign_mb.wifi.sim.Trace` under an allocator. ns-3:
:mod:`codesign_mb.wifi.ns3_driver`, in the schemes of :data:`NS3_SCHEMES`: single-user EDCA
as ns-3 sets it up by default, the same with RTS/CTS for the camera frames and a TXOP for the
AP (what a network engineer sets for a dense cell with synchronised bursts), and the
round-robin OFDMA scheduler.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import numbers
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.core.config import Cap, check_range, show
from codesign_mb.wifi.channel import ChannelConfig
from codesign_mb.wifi.config import WifiConfig
from codesign_mb.wifi.mac import MacTiming
from codesign_mb.wifi.phy import PhyConfig
from codesign_mb.wifi.sim import Trace, replay
from codesign_mb.wifi.traffic import CAPTURE_MODES, TrafficConfig

__all__ = [
    "CROSSCHECK_TARGET",
    "NS3_SCHEMES",
    "CrosscheckConfig",
    "MissingNs3Result",
    "capacity",
    "crosscheck",
    "ns3_missing",
    "ours_delivered_fraction",
    "read_ns3_run",
]

PERIODS_CAP = Cap(1_000, "40 ms periods of one cross-check run (40 s)")

CROSSCHECK_TARGET = 0.95
"""Delivered fraction that defines capacity."""

OURS_ASSUMPTIONS = (
    "AP schedules every 1 ms tick, contending by AC_VI EDCA (mean backoff, no collisions: "
    "stations send only when triggered) and holding its TXOP (4.096 ms limit) across busy "
    "ticks, a SIFS apart; BSRP polls of idle stations every 8 ticks, BSR piggybacked on UL "
    "data; one DL MU PPDU sends every ready state frame in full, block acks in an HE TB PPDU; "
    "basic "
    "Trigger + HE TB PPDU (UL GI 1.6 us, 2x HE-LTF) + multi-STA BlockAck; LLC/SNAP, IP, UDP, "
    "MAC header, FCS, A-MPDU delimiters; beacons every 102.4 ms; no retransmissions."
)
NS3_SCHEMES: dict[str, dict[str, Any]] = {
    "su": {"access": "su"},
    "su-rts": {"access": "su", "rts_cts_threshold_bytes": 1000, "ap_txop_limit_us": 8160},
    "ofdma": {"access": "ofdma"},
}
"""ns-3 set-ups compared (:class:`~codesign_mb.wifi.ns3_driver.Ns3Scenario` fields)."""

NS3_ASSUMPTIONS = {
    "su": "ns-3 3.44 802.11ax, EDCA single-user (AC_BE, A-MPDU + block ack), GI 0.8 us, "
    "control frames at the MCS's non-HT reference rate, stations 2 m from the AP.",
    "su-rts": f"as su, with RTS/CTS before every PSDU over "
    f"{NS3_SCHEMES['su-rts']['rts_cts_threshold_bytes']} B (the camera frames: a collision "
    f"costs an RTS) and an AC_BE TXOP limit of "
    f"{NS3_SCHEMES['su-rts']['ap_txop_limit_us'] / 1000:g} ms for the AP (several state "
    "frames per access; stations keep 0).",
    "ofdma": "ns-3 3.44 802.11ax, RrMultiUserScheduler (DL OFDMA with aggregated MU-BAR "
    "trigger, UL OFDMA after BSRP, access request every 1 ms, at most `mu_stations` per MU "
    "PPDU), GI 1.6 us; stations also contend by EDCA.",
}


@dataclass(frozen=True)
class CrosscheckConfig:
    """The grid of a cross-check and how long each run simulates.

    Parameters
    ----------
    mcs:
        MCS values (the rows).
    captures:
        ``"staggered"`` and/or ``"synchronised"``.
    schedulers:
        Our allocators (``greedy``, ``convex``, ...); the best is compared.
    ns3_access:
        ns-3 set-ups (:data:`NS3_SCHEMES`: ``su``, ``su-rts``, ``ofdma``); the best is
        compared.
    bandwidth_mhz:
        Channel width of both sides.
    periods:
        Frame periods per station counted (after ``skip_periods``).
    max_stations:
        Upper end of the capacity search.
    mu_stations:
        ns-3 round-robin scheduler's most stations per MU PPDU.
    tolerance:
        Allowed relative gap of our capacity to ns-3's best (the issue's 25 %).
    """

    mcs: tuple[int, ...] = (0, 3, 7)
    captures: tuple[str, ...] = CAPTURE_MODES
    schedulers: tuple[str, ...] = ("greedy", "convex")
    ns3_access: tuple[str, ...] = ("su", "su-rts", "ofdma")
    bandwidth_mhz: int = 40
    periods: int = 8
    skip_periods: int = 2
    max_stations: int = 64
    mu_stations: int = 9
    tolerance: float = 0.25
    mac: MacTiming = field(default_factory=MacTiming)

    def __post_init__(self) -> None:
        for name in ("mcs", "captures", "schedulers"):
            if not getattr(self, name):
                raise ValueError(f"{name} must name at least one, got none")
        for m in self.mcs:
            if not (isinstance(m, int) and 0 <= m <= 11):
                raise ValueError(f"mcs must be integers in [0, 11], got {self.mcs!r}")
        for a in self.ns3_access:
            if a not in NS3_SCHEMES:
                raise ValueError(f"ns3_access must be in {tuple(NS3_SCHEMES)}, got {a!r}")
        for c in self.captures:
            if c not in CAPTURE_MODES:
                raise ValueError(f"captures must be in {CAPTURE_MODES}, got {self.captures!r}")
        if not 1 <= self.max_stations <= 200:
            raise ValueError(f"max_stations must be in [1, 200], got {self.max_stations!r}")
        check_range("periods", self.periods, ge=1, cap=PERIODS_CAP)
        check_range("skip_periods", self.skip_periods, ge=0, cap=PERIODS_CAP)
        if not 0 < self.tolerance < 1:
            raise ValueError(f"tolerance must be in (0, 1), got {self.tolerance!r}")

    def cell(self, mcs: int, capture: str) -> WifiConfig:
        """Our cell: fixed MCS, no frame errors, the traffic of paper Table II."""
        return WifiConfig(
            phy=PhyConfig(bandwidth_mhz=self.bandwidth_mhz),
            mac=self.mac,
            channel=ChannelConfig(fixed_mcs=mcs, q0=1.0),
            traffic=TrafficConfig(capture=capture),
        )


def _trace(config: WifiConfig, n: int, periods: int) -> Trace:
    """Every station's frames over ``periods`` periods at the cell's fixed MCS, none lost."""
    tick_us = config.mac.tick_us
    period = config.traffic.period_ticks(tick_us)
    offsets = config.traffic.offsets_ticks(n, tick_us)
    horizon = (periods + 1) * period
    mcs = config.channel.fixed_mcs or 0
    bpss = float(config.phy.bits_per_subcarrier_symbol(mcs))
    ul_bits = config.mac.psdu_bits(config.traffic.ul_frame_bytes)
    dl_bits = config.mac.psdu_bits(config.traffic.dl_frame_bytes)
    rows = [
        (i, t, int(t * period + offsets[i]), int((t + 1) * period + offsets[i]), ul_bits, dl_bits)
        for t in range(periods)
        for i in range(n)
    ]
    frames = pd.DataFrame(rows, columns=list(Trace.COLUMNS[:6])).assign(ul_ok=1, dl_ok=1)
    full = np.full((n, horizon), bpss)
    return Trace(config, horizon, full, full.copy(), frames)


def ours_delivered_fraction(
    config: WifiConfig, n: int, *, scheduler: str, periods: int, skip_periods: int
) -> float:
    """Delivered fraction of our cell with ``n`` stations (frames after ``skip_periods``)."""
    result = replay(_trace(config, n, periods + skip_periods), scheduler)
    fates = result.frames
    counted = fates[fates["step"] >= skip_periods]
    return float((counted["fate"] == "delivered").mean())


def capacity(
    fraction: Callable[[int], float],
    max_stations: int,
    target: float = CROSSCHECK_TARGET,
    *,
    guess: int | None = None,
    step: float = 2.0,
    known: dict[int, float] | None = None,
) -> tuple[int, dict[int, float]]:
    """Largest ``N`` in ``[0, max_stations]`` with ``fraction(N) >= target``.

    Assumes the fraction falls with ``N`` (more stations share the channel): brackets the
    capacity from ``guess`` (multiplying or dividing by ``step``), then bisects. Returns the
    capacity and every fraction evaluated. ``known``: fractions already measured (an
    earlier run's), used as if evaluated; when they bracket the capacity, the search starts
    from that bracket, else from the largest known count reaching ``target``.
    """
    seen: dict[int, float] = dict(known or {})

    def ok(n: int) -> bool:
        if n not in seen:
            seen[n] = fraction(n)
        return seen[n] >= target

    lo, hi = 0, max_stations + 1  # ok(lo) holds (no stations), ok(hi) is taken to fail
    reached = sorted(n for n, v in seen.items() if v >= target)
    missed = sorted(n for n, v in seen.items() if not v >= target and reached and n > reached[0])
    if missed:  # known counts already bracket the capacity: bisect between them
        hi = missed[0]
        lo = max(n for n in reached if n < hi)
        guess = None
    elif reached:  # start the search where the known counts left it
        guess = reached[-1]
    if guess is not None and 1 <= guess <= max_stations:
        probe = guess
        if ok(probe):
            lo = probe
            while lo < max_stations:
                probe = min(max_stations, max(lo + 1, math.ceil(step * lo)))
                if not ok(probe):
                    hi = probe
                    break
                lo = probe
        else:
            hi = probe
            while hi > 1:
                probe = min(hi - 1, math.floor(hi / step))
                if ok(probe):
                    lo = probe
                    break
                hi = probe
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return lo, seen


class MissingNs3Result(ValueError):
    """A point the capacity search needs is neither recorded nor can be simulated (no ns-3)."""


def read_ns3_run(path: str | Path) -> list[dict[str, Any]]:
    """The rows of a cross-check written by ``codesign wifi crosscheck --out``, checked.

    Reading them needs no ns-3: the file is JSON. It must hold an object with ``rows``, a
    list of objects each with an integer ``mcs``, a ``capture`` string and, for at least one
    row, ns-3 delivered fractions ``ns3_<scheme>_fractions`` (:data:`NS3_SCHEMES`): station
    counts (integers >= 1, as strings) -> fractions in [0, 1] (NaN: ns-3 aborted there).

    Raises
    ------
    ValueError
        The file is missing, is not JSON, or is not such a run; the message names the file
        and the entry at fault.
    """
    path = Path(path)
    where = f"recorded ns-3 run {str(path)!r}"
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        raise ValueError(f"{where} cannot be read ({reason})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{where} is not valid JSON: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("rows"), list):
        got = (
            f"an object with keys {', '.join(map(repr, list(data)[:5]))}"
            if isinstance(data, dict) and data
            else show(data)
        )
        raise ValueError(
            f"{where} must be a JSON object with a list 'rows' (the --out file of "
            f"codesign wifi crosscheck), got {got}"
        )
    found = False
    for i, row in enumerate(data["rows"]):
        entry = f"{where}: rows[{i}]"
        if not isinstance(row, dict):
            raise ValueError(f"{entry} must be an object, got {show(row)}")
        mcs = row.get("mcs")
        if isinstance(mcs, bool) or not isinstance(mcs, int):
            raise ValueError(f"{entry}.mcs must be an integer, got {show(mcs)}")
        if not isinstance(row.get("capture"), str):
            raise ValueError(f"{entry}.capture must be a string, got {show(row.get('capture'))}")
        for access in NS3_SCHEMES:
            key = f"ns3_{access}_fractions"
            if key not in row:
                continue
            found = True
            fractions = row[key]
            if not isinstance(fractions, dict):
                raise ValueError(f"{entry}.{key} must be an object, got {show(fractions)}")
            for n, value in fractions.items():
                if not (isinstance(n, str) and n.isdigit() and int(n) >= 1):
                    raise ValueError(
                        f"{entry}.{key} keys must be station counts >= 1, got {show(n)}"
                    )
                ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
                if not ok or not (math.isnan(value) or 0.0 <= value <= 1.0):
                    raise ValueError(
                        f"{entry}.{key}[{n!r}] must be a fraction in [0, 1], got {show(value)}"
                    )
    if not found:
        raise ValueError(
            f"{where} holds no ns-3 results (no row has ns3_<scheme>_fractions, schemes "
            f"{', '.join(NS3_SCHEMES)}): not the --out file of a cross-check that ran ns-3"
        )
    return list(data["rows"])


def ns3_missing(
    cfg: CrosscheckConfig, rows: list[dict[str, Any]] | None
) -> list[tuple[int, str, str]]:
    """The ``(mcs, capture, scheme)`` cells of ``cfg``'s grid with no ns-3 result in ``rows``.

    Without ns-3 installed, a cross-check can only reuse a recorded run that covers them all.
    """
    recorded = {(r["mcs"], r["capture"]): r for r in rows or []}
    return [
        (mcs, capture, access)
        for mcs in cfg.mcs
        for capture in cfg.captures
        for access in cfg.ns3_access
        if not recorded.get((mcs, capture), {}).get(f"ns3_{access}_fractions")
    ]


def _ours_fraction(
    cfg: CrosscheckConfig, cell: WifiConfig, scheduler: str
) -> Callable[[int], float]:
    def fraction(n: int) -> float:
        return ours_delivered_fraction(
            cell, n, scheduler=scheduler, periods=cfg.periods, skip_periods=cfg.skip_periods
        )

    return fraction


def _ns3_fraction(
    cfg: CrosscheckConfig,
    mcs: int,
    capture: str,
    access: str,
    known: dict[int, float],
    progress: Callable[[str], None] | None = None,
    failed: list[int] | None = None,
    simulate: bool = True,
) -> Callable[[int], float]:
    from codesign_mb.wifi.ns3_driver import Ns3Scenario

    failed = [] if failed is None else failed

    def fraction(n: int) -> float:
        if n in known:
            return known[n]
        if not simulate:
            raise MissingNs3Result(
                f"the recorded ns-3 run has no {access} result at MCS {mcs}, {capture}, "
                f"{n} stations, which the capacity search needs (recorded with other settings?), "
                "and ns-3 is not installed to simulate it: pip install 'codesign-mb[ns3]'"
            )
        if progress is not None:
            progress(f"  ns-3 {access}, MCS {mcs}, {capture}, {n} stations ...")
        scheme = NS3_SCHEMES[access]
        scenario = Ns3Scenario(
            n_stations=n,
            mcs=mcs,
            **scheme,
            bandwidth_mhz=cfg.bandwidth_mhz,
            guard_interval_us=0.8 if scheme["access"] == "su" else 1.6,
            capture=capture,
            frames=cfg.periods,
            skip_frames=cfg.skip_periods,
            mu_stations=cfg.mu_stations,
        )
        value = _isolated(scenario)
        if value is None:  # ns-3 aborted (an assertion of its own): counted as not reached
            failed.append(n)
            if progress is not None:
                progress(f"  ns-3 {access}, MCS {mcs}, {capture}, {n} stations: ns-3 aborted")
            return math.nan
        return value

    return fraction


def _ns3_delivered_fraction(scenario: Any) -> float:
    from codesign_mb.wifi.ns3_driver import run_ns3

    return run_ns3(scenario).delivered_fraction


def _isolated(scenario: Any) -> float | None:
    """One ns-3 run in a child process: ``None`` when ns-3 aborts it (``NS_ASSERT``).

    ns-3 3.44's round-robin OFDMA scheduler asserts on some large station counts (35 at
    MCS 7); in a child process that costs the point, not the cross-check.
    """
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as executor:
        try:
            return float(executor.submit(_ns3_delivered_fraction, scenario).result())
        except BrokenProcessPool:
            return None


def crosscheck(
    cfg: CrosscheckConfig,
    *,
    progress: Callable[[str], None] | None = None,
    ns3_known: list[dict[str, Any]] | None = None,
    on_row: Callable[[list[dict[str, Any]]], None] | None = None,
    simulate_ns3: bool = True,
) -> list[dict[str, Any]]:
    """One row per (MCS, capture): our capacity and ns-3's, per scheme, and the relative gap.

    ``ns3_known``: rows of an earlier cross-check (same ns-3 settings, e.g. from
    :func:`read_ns3_run`) whose ns-3 delivered fractions are reused instead of simulated
    again; ``on_row`` gets the rows so far after each (to save partial results). With
    ``simulate_ns3=False`` (no ns-3 installed) a point the search needs that ``ns3_known``
    lacks is a ``ValueError``.
    """
    rows: list[dict[str, Any]] = []
    earlier = {(r["mcs"], r["capture"]): r for r in ns3_known or []}
    for mcs in cfg.mcs:
        for capture in cfg.captures:
            cell = cfg.cell(mcs, capture)
            row: dict[str, Any] = {"mcs": mcs, "capture": capture}
            guess = None
            for name in cfg.schedulers:
                cap, seen = capacity(_ours_fraction(cfg, cell, name), cfg.max_stations)
                row[f"ours_{name}"] = cap
                guess = max(guess or 1, cap)
                row[f"ours_{name}_fractions"] = {
                    str(k): round(v, 4) for k, v in sorted(seen.items())
                }
            for access in cfg.ns3_access:
                if progress:
                    progress(f"ns-3 {access}, MCS {mcs}, {capture}")
                old = earlier.get((mcs, capture), {}).get(f"ns3_{access}_fractions", {})
                known = {int(n): float(v) for n, v in old.items()}
                failed: list[int] = []
                fraction = _ns3_fraction(
                    cfg, mcs, capture, access, known, progress, failed, simulate_ns3
                )
                # from the earlier runs' counts when there are some, else from ours
                cap, seen = capacity(
                    fraction, cfg.max_stations, guess=guess, step=1.25, known=known
                )
                row[f"ns3_{access}"] = cap
                if failed:
                    row[f"ns3_{access}_aborted"] = sorted(failed)
                row[f"ns3_{access}_fractions"] = {
                    str(k): round(v, 4) for k, v in sorted(seen.items())
                }
            ours = max(row[f"ours_{s}"] for s in cfg.schedulers)
            best = max(row[f"ns3_{a}"] for a in cfg.ns3_access) if cfg.ns3_access else 0
            row["ours_best"], row["ns3_best"] = ours, best
            row["gap"] = round((ours - best) / best, 4) if best else None
            row["within_tolerance"] = best > 0 and abs(ours - best) <= cfg.tolerance * best
            rows.append(row)
            if on_row is not None:
                on_row(rows)
    return rows


def assumptions(cfg: CrosscheckConfig) -> dict[str, str]:
    """What each side models, for the report next to the table."""
    out = {
        "ours": OURS_ASSUMPTIONS.replace(
            "every 8 ticks", f"every {cfg.mac.bsrp_interval_ticks} ticks"
        )
    }
    for access in cfg.ns3_access:
        out[f"ns3_{access}"] = NS3_ASSUMPTIONS[access].replace(
            "`mu_stations`", str(cfg.mu_stations)
        )
    return out


def with_mac(cfg: CrosscheckConfig, **changes: Any) -> CrosscheckConfig:
    """The same grid with MAC settings changed (e.g. the BSRP interval)."""
    return replace(cfg, mac=replace(cfg.mac, **changes))
