"""802.11ax PHY: RU plan against the standard's tone tables, rates against published values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from codesign_mb.wifi.channel import (
    SNR_THRESHOLDS_DB,
    ChannelConfig,
    choose_mcs,
    frame_delivery_probability,
    packet_error_rate,
)
from codesign_mb.wifi.mac import MacTiming, legacy_ppdu_us
from codesign_mb.wifi.phy import PhyConfig, data_rate_mbps, he_ltf_symbol_us, ru_plan
from codesign_mb.wifi.traffic import TrafficConfig, drop_probability


@pytest.mark.parametrize(
    ("tones", "mcs", "gi", "nss", "expected"),
    [
        (484, 11, 0.8, 1, 286.8),  # issue 7's reference values
        (484, 0, 0.8, 1, 17.2),
        (242, 7, 0.8, 1, 86.0),
        (242, 11, 0.8, 1, 143.4),  # 20 MHz HE SU MCS 11, 1 SS
        (242, 11, 0.8, 2, 286.8),
        (996, 11, 0.8, 1, 600.5),  # 80 MHz, 1 SS: 600.5 Mb/s
        (996, 11, 0.8, 2, 1201.0),
        (996, 0, 3.2, 1, 30.6),
        (26, 0, 0.8, 1, 0.9),
        (106, 5, 1.6, 1, 28.3),
    ],
)
def test_rates_match_published_values(tones, mcs, gi, nss, expected):
    rate = data_rate_mbps(tones, mcs, spatial_streams=nss, guard_interval_us=gi)
    assert rate == pytest.approx(expected, abs=0.06)


@pytest.mark.parametrize(
    ("bw", "counts", "n_units"),
    [(20, [9, 4, 2, 1], 9), (40, [18, 8, 4, 2, 1], 18), (80, [37, 16, 8, 4, 2, 1], 37)],
)
def test_ru_plan_counts_and_overlap(bw, counts, n_units):
    plan = ru_plan(bw)
    assert [plan.count(t) for t in plan.sizes] == counts
    assert plan.n_units == n_units
    for ru in plan.units:  # every RU has exactly its number of tones
        assert sum(hi - lo + 1 for lo, hi in ru.tone_ranges) == ru.tones
    units = np.array([[a.overlaps(b) for b in plan.units] for a in plan.units])
    np.testing.assert_array_equal(units, plan.overlap_matrix())  # masks == tone positions
    # the widest RU has the most data subcarriers of any layout: the LP bound relies on it
    assert plan.full_band_data_subcarriers == max(u.data_subcarriers for u in plan.units)
    assert plan.full_band_data_subcarriers >= plan.count(26) * 24


def test_centre_26_tone_ru_is_in_no_52_or_106():
    plan = ru_plan(20)
    centre = plan.of_size(26)[4]
    assert centre.tone_ranges == ((-16, -4), (4, 16))
    assert not any(centre.overlaps(r) for r in plan.of_size(52) + plan.of_size(106))
    # 106 + 26 + 106 is a valid 20 MHz layout
    assert plan.is_valid_layout(
        [plan.of_size(106)[0].index, centre.index, plan.of_size(106)[1].index]
    )
    assert not plan.is_valid_layout([plan.of_size(242)[0].index, centre.index])


def test_phy_table_rows():
    rows = PhyConfig(bandwidth_mhz=40).rate_table()
    assert len(rows) == 5 * 12
    best = max(rows, key=lambda r: r["rate_mbps"])
    assert (best["ru_tones"], best["mcs"]) == (484, 11)


def test_airtime_parts():
    mac, phy = MacTiming(), PhyConfig()
    # non-HT PPDU: 20 us preamble + 4 us symbols; 14-byte ACK at 24 Mb/s = 20 + 4*2 = 28 us
    assert legacy_ppdu_us(14, 24.0) == 28.0
    # AC_VI: SIFS 16 + AIFSN 2 x 9 + CWmin 7 / 2 x 9 (Table 9-155, 10.23.2)
    assert mac.channel_access_us == pytest.approx(65.5)
    # HE TB PPDU, default UL GI 1.6 us: 32 + HE-STF 8 + 2x HE-LTF (6.4 + 1.6) + 14.4 n + PE 4
    assert mac.he_tb_ppdu_us(10, phy) == pytest.approx(32 + 8 + 8 + 144 + 4)
    # ... and at 3.2 us with the 4x HE-LTF (12.8 + 3.2)
    gi32 = PhyConfig(ul_guard_interval_us=3.2)
    assert mac.he_tb_ppdu_us(10, gi32) == pytest.approx(32 + 8 + 16 + 160 + 4)
    # basic Trigger, 1 user: 28 + 6 bytes -> ceil((16 + 272 + 6) / 96) = 4 symbols -> 36 us
    assert mac.trigger_us(1) == 36.0
    assert mac.trigger_us(9) == 20 + 4 * math.ceil((16 + 8 * 82 + 6) / 96)
    assert mac.trigger_us(9, bsrp=True) == 20 + 4 * math.ceil((16 + 8 * 73 + 6) / 96)
    assert mac.multi_sta_ba_us(1) == 36.0
    # DL MU exchange, 1 user, 1 data and 1 ack symbol, 40 MHz, DL GI 0.8 us:
    # MU PPDU 32 + SIG-B ceil(39 / 26) x 4 + STF 4 + 2x LTF 7.2 + 13.6 + PE 4 = 68.8 us,
    # TB ack 32 + 8 + 8 + 14.4 + 4 = 66.4 us, two SIFS
    assert mac.dl_exchange_us(1, 1, 1, phy) == pytest.approx(68.8 + 16 + 66.4 + 16)
    # UL: 1000 - 65.5 - (trigger 36 + 16 + TB preamble 52 + 16 + M-BA 36) = 778.5 us of data
    assert mac.ul_data_symbols(1, 0.0, phy) == math.floor(778.5 / 14.4)
    # a tick inside a TXOP starts after a SIFS: 1000 - 16 - 156 = 828 us, the LP's bound
    assert mac.ul_data_symbols(1, 0.0, phy, continues_txop=True) == math.floor(828 / 14.4)
    assert mac.max_ul_data_symbols(phy, with_dl=False) == 57
    # AC_VI TXOP limit 4096 us from the end of the first access (65.5 us): ticks ending by
    # 4161.5 us share it, so 4; with the 2016 limit (3008 us) 3, without a limit 1
    assert mac.txop_ticks == 4
    assert MacTiming(txop_limit_us=3008.0).txop_ticks == 3
    assert MacTiming(txop_limit_us=0.0).txop_ticks == 1
    assert mac.ul_data_symbols(18, 0.0, phy) < mac.ul_data_symbols(1, 0.0, phy)
    parts = mac.breakdown(6, 6, phy)
    total = parts["channel_access_us"] + parts["dl_exchange_us"] + parts["ul_overhead_us"]
    assert total + parts["ul_data_us"] <= mac.tick_us


def test_frame_bytes_count_every_header():
    mac = MacTiming()
    # 13,500 B -> 9 UDP datagrams of 1472 B + one of 252 B; per MPDU LLC/SNAP 8 + IP/UDP 28
    # + MAC header 30 + FCS 4, per subframe a 4-byte delimiter, padded to 4 bytes but the last
    assert mac.msdu_count(13_500) == 10
    assert mac.ampdu_bytes(13_500) == 9 * 1548 + (4 + 252 + 70)
    assert mac.ampdu_bytes(32) == 4 + 32 + 70
    assert mac.psdu_bits(32) == 8 * 106
    # data symbols: SERVICE 16 + tail 6 bits on top; 106 B on a 26-tone RU (24 SD) at MCS 0
    assert mac.data_symbols(106, 24, 0.5) == math.ceil((22 + 848) / 12)


def test_beacons_every_100_tu():
    mac = MacTiming()
    due = [k for k in range(400) if mac.beacon_due(k)]
    assert due == [0, 102, 204, 307]  # 0, 102.4, 204.8, 307.2 ms
    assert mac.beacon_us == pytest.approx(65.5 + 20 + 4 * math.ceil((22 + 2400) / 24))


def test_uplink_guard_interval_follows_the_standard():
    # HE TB PPDUs allow 1.6 us (1x/2x HE-LTF) and 3.2 us (4x), never 0.8 us (9.3.1.22)
    with pytest.raises(ValueError, match="ul_guard_interval_us"):
        PhyConfig(ul_guard_interval_us=0.8)
    with pytest.raises(ValueError, match="HE TB"):
        he_ltf_symbol_us(0.8, trigger_based=True)
    assert he_ltf_symbol_us(0.8, trigger_based=False) == pytest.approx(7.2)
    phy = PhyConfig()
    assert (phy.symbol_us, phy.ul_symbol_us) == (pytest.approx(13.6), pytest.approx(14.4))
    # the uplink rate at 1.6 us is 13.6 / 14.4 of the 0.8 us one: the "6 % too high"
    row = next(r for r in phy.rate_table() if (r["ru_tones"], r["mcs"]) == (484, 7))
    assert row["ul_rate_mbps"] == pytest.approx(468 * 5 / 14.4, abs=1e-3)
    assert row["ul_rate_mbps"] / row["rate_mbps"] == pytest.approx(13.6 / 14.4, abs=1e-4)


def test_per_model_and_link_adaptation():
    for m, snr in enumerate(SNR_THRESHOLDS_DB):
        assert float(packet_error_rate(m, snr)) == pytest.approx(0.1)
    assert np.all(np.diff(SNR_THRESHOLDS_DB) > 0)
    # longer frames fail more often
    assert frame_delivery_probability(3, 18.0, 13_500) < frame_delivery_probability(3, 18.0, 32)
    mcs = choose_mcs(np.array([0.0, 15.0, 45.0]), 0.95, 4096)
    assert mcs.tolist()[0] == 0 and mcs.tolist()[2] == 11
    assert float(frame_delivery_probability(mcs[1], 15.0, 4096)) >= 0.95
    assert float(frame_delivery_probability(mcs[1] + 1, 15.0, 4096)) < 0.95


def test_drop_probability_eq_drop():
    assert drop_probability(0.45, 0.9) == pytest.approx(0.5)
    assert drop_probability(1.0, 0.9) == 0.0
    assert drop_probability(0.0, 0.9) == 1.0


def test_staggered_offsets():
    t = TrafficConfig()
    assert t.offsets_ticks(4, 1000.0).tolist() == [0, 10, 20, 30]
    assert TrafficConfig(capture="synchronised").offsets_ticks(3, 1000.0).tolist() == [0, 0, 0]


@pytest.mark.parametrize(
    ("factory", "field"),
    [
        (lambda: PhyConfig(bandwidth_mhz=30), "bandwidth_mhz"),
        (lambda: PhyConfig(guard_interval_us=0.4), "guard_interval_us"),
        (lambda: PhyConfig(spatial_streams=3), "spatial_streams"),
        (lambda: MacTiming(sifs_us=-1.0), "sifs_us"),
        (lambda: MacTiming(tick_us=0.0), "tick_us"),
        (lambda: ChannelConfig(q0=1.5), "q0"),
        (lambda: ChannelConfig(distance_range_m=(10.0, 5.0)), "distance_range_m"),
        (lambda: ChannelConfig(fixed_mcs=12), "fixed_mcs"),
        (lambda: TrafficConfig(capture="random"), "capture"),
        (lambda: TrafficConfig(ul_frame_bytes=0), "ul_frame_bytes"),
        (lambda: data_rate_mbps(100, 0), "ru_tones"),
        (lambda: data_rate_mbps(26, 12), "mcs"),
    ],
)
def test_bad_config_names_the_field(factory, field):
    with pytest.raises(ValueError, match=field):
        factory()


def test_rician_gain_has_unit_mean():
    rng = np.random.default_rng(0)
    for k in (None, 6.0):
        g = ChannelConfig(rician_k_db=k).fading_gain((20_000,), rng)
        assert g.mean() == pytest.approx(1.0, abs=0.03)
    assert np.all(ChannelConfig(rician_k_db=math.inf).fading_gain((5,), rng) == 1.0)
