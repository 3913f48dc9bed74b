"""802.11ax MAC in the slot simulator: BSR-only queue knowledge, one DL MU PPDU, and the ns-3
cross-check (ours fast; ns-3 itself slow and optional)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from codesign_mb.wifi.allocators import GreedyEdfAllocator
from codesign_mb.wifi.config import WifiConfig
from codesign_mb.wifi.crosscheck import CrosscheckConfig, capacity, ours_delivered_fraction
from codesign_mb.wifi.engine import ChannelEngine, Frame
from codesign_mb.wifi.mac import MacTiming
from codesign_mb.wifi.ns3_driver import Ns3Scenario, ns3_available

CELL = WifiConfig()


def _engine(n: int, config: WifiConfig = CELL) -> ChannelEngine:
    return ChannelEngine(config, n, GreedyEdfAllocator(40), GreedyEdfAllocator(40))


def test_ap_sees_a_camera_frame_only_after_a_bsr():
    engine = _engine(1)
    engine.layouts = []
    engine.run_tick(np.ones(1), np.ones(1))  # tick 0: beacon, poll of an empty queue
    frame = Frame(0, 0, 1, 40, 10_000, 848)
    engine.add(frame)
    poll = CELL.mac.bsrp_interval_ticks
    for _ in range(1, poll):  # the AP believes the queue empty until the next poll is due
        engine.run_tick(np.ones(1), np.ones(1))
        assert frame.ul_left == frame.ul_bits
    engine.run_tick(np.ones(1), np.ones(1))  # tick `poll`: BSRP poll, then the basic Trigger
    assert frame.ul_left < frame.ul_bits
    mac, phy = CELL.mac, CELL.phy
    bsrp = mac.bsrp_exchange_us(1, mac.data_symbols(38, 468, 1.0), phy)
    n_sym = mac.ul_data_symbols(1, bsrp, phy)
    (tick, direction, layout) = engine.layouts[-1]
    assert (tick, direction) == (poll, "ul")
    sd = engine.plan.units[int(layout[0])].data_subcarriers
    # SERVICE + tail bits, and a dynamic fragment: one more MAC header, FCS and delimiter
    assert frame.ul_bits - frame.ul_left == pytest.approx(sd * n_sym - 22 - 8 * 38)


def test_a_station_with_data_reports_new_frames_without_a_poll():
    engine = _engine(1)
    first = Frame(0, 0, 0, 40, 50_000, 848)  # longer than one tick
    engine.add(first)
    engine.run_tick(np.ones(1), np.ones(1))  # polled at tick 0, served, BSR with its data
    second = Frame(0, 1, 1, 41, 1_000, 848)
    engine.add(second)
    engine.run_tick(np.ones(1), np.ones(1))  # tick 1 (no poll): its BSR of tick 0 is old
    before = second.ul_left
    for _ in range(38):
        if first.ul_left <= 0 or first.fate != "queued":
            break
        engine.run_tick(np.ones(1), np.ones(1))
    assert first.ul_left <= 0
    # the BSR sent with tick-1 data reported the second frame: it is served without a poll
    engine.run_tick(np.ones(1), np.ones(1))
    assert before == second.ul_bits and second.ul_left < second.ul_bits
    assert engine.tick % CELL.mac.bsrp_interval_ticks != 0 or engine.tick > 8


def test_one_dl_mu_ppdu_carries_every_ready_state_frame():
    mac, phy = CELL.mac, CELL.phy
    engine = _engine(3)
    for i in range(3):
        f = Frame(i, 0, 0, 2, 8, mac.psdu_bits(32))  # due next tick: served in full now
        f.ul_left = 0.0
        f.dl_ready_tick = 1
        engine.dl_q[i].append(f)
    engine.tick = 1  # no beacon, no poll
    engine.run_tick(np.full(3, 5.0), np.full(3, 5.0))  # MCS 7: 5 bits per subcarrier-symbol
    assert all(not q for q in engine.dl_q)
    # 3 users -> 106-tone RUs (102 SD): ceil((22 + 8 * 106) / 510) = 2 symbols, ack 1 symbol
    n_sym = math.ceil((22 + 8 * 106) / (102 * 5.0))
    ack = math.ceil((22 + 8 * 36) / (102 * 5.0))
    expected = mac.channel_access_us + mac.dl_exchange_us(3, n_sym, ack, phy)
    assert engine.busy_us == pytest.approx(expected)


def test_busy_ticks_share_a_txop_up_to_its_limit():
    # one long frame at MCS 7, polled at tick 0: ticks 0-3 form one TXOP (access once, then a
    # SIFS before each tick's exchanges), tick 4 contends again (4096 us limit)
    mac, phy = CELL.mac, CELL.phy
    engine = _engine(1)
    engine.layouts = []
    frame = Frame(0, 0, 0, 7, 2_000_000, 848)  # due soon: the whole band every tick
    engine.add(frame)
    served, before = [], frame.ul_left
    for _ in range(6):
        engine.run_tick(np.full(1, 5.0), np.full(1, 5.0))
        served.append(before - frame.ul_left)
        before = frame.ul_left
    bsrp = mac.bsrp_exchange_us(1, mac.data_symbols(38, 468, 5.0), phy)
    fresh = mac.ul_data_symbols(1, 0.0, phy)
    inside = mac.ul_data_symbols(1, 0.0, phy, continues_txop=True)
    # tick 0 carries a beacon (its own access, then the AP contends anew) and the poll
    # (beacon_us already counts its access, so the UL gets what the tick leaves after both)
    first = mac.ul_data_symbols(1, bsrp + mac.beacon_us, phy)
    per_symbol = 468 * 5.0
    expected = [first, inside, inside, inside, fresh, inside]
    assert inside - fresh == math.floor(828 / 14.4) - math.floor(778.5 / 14.4)
    # each tick ends inside the frame: SERVICE + tail, and a dynamic fragment's header + FCS +
    # delimiter (38 B)
    assert served == pytest.approx([n * per_symbol - 22 - 8 * 38 for n in expected])


def test_bsrp_interval_trades_airtime_for_delay():
    # polling every tick costs capacity against polling every 8 ticks (staggered, MCS 7)
    base = CrosscheckConfig()
    every_tick = WifiConfig(
        phy=CELL.phy,
        mac=MacTiming(bsrp_interval_ticks=1),
        channel=base.cell(7, "staggered").channel,
    )
    n = 30
    slow = ours_delivered_fraction(
        base.cell(7, "staggered"), n, scheduler="greedy", periods=4, skip_periods=1
    )
    fast = ours_delivered_fraction(every_tick, n, scheduler="greedy", periods=4, skip_periods=1)
    assert slow >= fast


def test_capacity_search_finds_the_threshold():
    for true_cap in (0, 1, 7, 33, 64):
        f = lambda n, c=true_cap: 1.0 if n <= c else 0.5  # noqa: E731
        for guess in (None, 1, 10, 64):
            cap, seen = capacity(f, 64, guess=guess)
            assert cap == true_cap
            assert len(seen) <= 16


def test_capacity_search_starts_from_known_fractions():
    # an earlier run's fractions bracket the capacity: only the counts between are evaluated
    calls: list[int] = []

    def f(n: int) -> float:
        calls.append(n)
        return 1.0 if n <= 13 else 0.5

    known = {10: 1.0, 12: 1.0, 16: 0.5, 20: 0.4}
    cap, seen = capacity(f, 64, guess=40, known=known)
    assert cap == 13
    assert set(calls) <= {13, 14, 15} and 40 not in seen
    assert all(seen[n] == v for n, v in known.items())


def test_our_capacity_falls_with_the_mcs():
    cfg = CrosscheckConfig(periods=3, skip_periods=1)
    caps = []
    for mcs in (0, 3, 7):
        cell = cfg.cell(mcs, "staggered")
        cap, _ = capacity(
            lambda n, cell=cell: ours_delivered_fraction(
                cell, n, scheduler="greedy", periods=3, skip_periods=1
            ),
            64,
        )
        caps.append(cap)
    # airtime per frame ~ 1 / rate: MCS 0 (0.5 bit/sc) ... MCS 7 (5 bits/sc)
    assert caps[0] < caps[1] < caps[2]
    assert 2 <= caps[0] <= 6 and caps[2] >= 20


def test_ns3_scenario_traffic():
    s = Ns3Scenario(n_stations=4, mcs=7)
    assert s.datagram_sizes() == [1472] * 9 + [252]
    assert s.offsets_ns() == [0, 10_000_000, 20_000_000, 30_000_000]
    with pytest.raises(ValueError, match="guard_interval_us"):
        Ns3Scenario(n_stations=2, mcs=7, access="ofdma", guard_interval_us=0.8)
    with pytest.raises(ValueError, match="multiple of 32"):  # the TXOP Limit field's unit
        Ns3Scenario(n_stations=2, mcs=7, ap_txop_limit_us=5000)
    with pytest.raises(ValueError, match="ns3_access"):
        CrosscheckConfig(ns3_access=("su", "edca"))


@pytest.mark.slow
@pytest.mark.skipif(not ns3_available(), reason="ns-3 (optional extra [ns3]) not installed")
def test_ns3_delivered_fraction_falls_with_load():
    from codesign_mb.wifi.ns3_driver import run_ns3

    light = run_ns3(Ns3Scenario(n_stations=2, mcs=3, access="su", frames=4, guard_interval_us=0.8))
    heavy = run_ns3(Ns3Scenario(n_stations=30, mcs=3, access="su", frames=4, guard_interval_us=0.8))
    assert light.delivered_fraction == 1.0
    assert heavy.delivered_fraction < 0.95
    # a frame's latency is at least its airtime: 13,500 B at MCS 3 on 40 MHz (~ 2 ms)
    assert np.nanmin(light.latency_ms) > 8 * 13_500 / 103.2e3


@pytest.mark.slow
@pytest.mark.skipif(not ns3_available(), reason="ns-3 (optional extra [ns3]) not installed")
def test_ns3_rts_cts_rescues_synchronised_bursts():
    """With every station's camera frame captured at once, single-user EDCA collides whole
    A-MPDUs (~0.7 ms each at MCS 7); with RTS/CTS a collision costs an RTS, so the same cell
    delivers far more (the su-rts set-up of the cross-check)."""
    from codesign_mb.wifi.crosscheck import NS3_SCHEMES
    from codesign_mb.wifi.ns3_driver import run_ns3

    common = {"n_stations": 24, "mcs": 7, "capture": "synchronised", "frames": 4}
    plain = run_ns3(Ns3Scenario(**common, guard_interval_us=0.8, **NS3_SCHEMES["su"]))
    rts = run_ns3(Ns3Scenario(**common, guard_interval_us=0.8, **NS3_SCHEMES["su-rts"]))
    assert rts.delivered_fraction >= 0.95
    assert rts.delivered_fraction > plain.delivered_fraction + 0.3


@pytest.mark.slow
@pytest.mark.skipif(not ns3_available(), reason="ns-3 (optional extra [ns3]) not installed")
def test_crosscheck_runs_ns3_in_a_child_process_and_survives_its_abort():
    """The cross-check's ns-3 runs go through a child process: the same fraction as in this
    process, and ``None`` (the point counted as not reached) when ns-3 aborts the run: 3.44's
    round-robin OFDMA scheduler asserts (``userInfoIt != m_muUserInfos.cend()``) at 35
    staggered stations at MCS 7."""
    from codesign_mb.wifi.crosscheck import NS3_SCHEMES, _isolated
    from codesign_mb.wifi.ns3_driver import run_ns3

    light = Ns3Scenario(n_stations=2, mcs=3, access="su", frames=4, guard_interval_us=0.8)
    assert _isolated(light) == run_ns3(light).delivered_fraction == 1.0
    aborts = Ns3Scenario(
        n_stations=35, mcs=7, guard_interval_us=1.6, capture="staggered", frames=10,
        skip_frames=2, mu_stations=9, **NS3_SCHEMES["ofdma"],
    )  # fmt: skip
    assert _isolated(aborts) is None


def test_crosscheck_cli_ours_only(runner):
    import json

    from codesign_mb.cli import app

    args = ["wifi", "crosscheck", "--mcs", "3", "--captures", "staggered", "--ns3", "none"]
    args += ["--periods", "2", "--max-stations", "20", "--json"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    row = json.loads(result.stdout)["rows"][0]
    assert row["ours_best"] == max(row["ours_greedy"], row["ours_convex"])
    fractions = row["ours_greedy_fractions"]
    assert fractions[str(row["ours_greedy"])] >= 0.95
    if str(row["ours_greedy"] + 1) in fractions:
        assert fractions[str(row["ours_greedy"] + 1)] < 0.95


def test_phy_table_uplink_gi(runner):
    import json

    from codesign_mb.cli import app

    result = runner.invoke(app, ["wifi", "phy-table", "--ul-gi", "3.2", "--json"])
    assert result.exit_code == 0, result.output
    row = next(r for r in json.loads(result.stdout) if (r["ru_tones"], r["mcs"]) == (484, 11))
    assert row["ul_rate_mbps"] == pytest.approx(468 * 10 * 5 / 6 / 16.0, abs=1e-3)
    bad = runner.invoke(app, ["wifi", "phy-table", "--ul-gi", "0.8"])
    assert bad.exit_code == 2 and "ul_guard_interval_us" in bad.output


def test_scheduled_uplink_serves_a_frame_at_its_capture_without_polls():
    # BSR-only: a frame captured at tick 1 waits for the poll at tick 8; scheduled: served at
    # tick 1, and no tick carries a BSRP exchange (an idle station is never polled)
    from dataclasses import replace

    scheduled = replace(CELL, mac=replace(CELL.mac, scheduled_uplink=True))
    waits, now = _engine(2), _engine(2, scheduled)
    for engine in (waits, now):
        engine.layouts = []
        engine.run_tick(np.ones(2), np.ones(2))  # tick 0
        engine.add(Frame(0, 0, 1, 40, 10_000, 848))
        engine.run_tick(np.ones(2), np.ones(2))  # tick 1
    assert [k for k, d, _ in now.layouts if d == "ul"] == [1]
    assert [k for k, d, _ in waits.layouts if d == "ul"] == []
    mac, phy = scheduled.mac, scheduled.phy
    # scheduled: tick 0 a beacon only (no poll of the idle stations), tick 1 the access and a UL
    # exchange whose TB PPDU fills the tick (the paper's greedy gives the frame the smallest RU
    # that finishes it by its deadline: served in part)
    n_sym = mac.ul_data_symbols(1, 0.0, phy)
    tick1 = mac.channel_access_us + mac.ul_overhead_us(1, phy) + n_sym * phy.ul_symbol_us
    assert now.busy_us == pytest.approx(mac.beacon_us + tick1)
    head_now, head_waits = now.ul_q[0][0], waits.ul_q[0][0]
    assert head_now.ul_left < head_now.ul_bits and head_waits.ul_left == head_waits.ul_bits
    with pytest.raises(ValueError, match="scheduled_uplink"):
        MacTiming(scheduled_uplink=1)  # type: ignore[arg-type]
