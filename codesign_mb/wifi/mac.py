"""802.11ax MAC airtime of one schedule tick: the frame exchanges, their PPDUs and overheads.

One tick is a sequence of frame exchanges of the AP ([air_ul], [air_dl])::

    access | [BSRP exchange] | [DL MU exchange] | [UL trigger-based exchange]

- **access**: AIFS[AC] + mean backoff ``CWmin / 2`` slots (IEEE 802.11ax-2021 10.23.2) when
  the tick opens a TXOP; a SIFS when it continues one (multiple frame exchanges in an EDCA
  TXOP, 10.23.2.8). The TXOP continues into the next tick when this tick's UL TB PPDU filled
  it (the exchanges run up to the tick's end) and the next tick ends within the AC's TXOP
  limit (AC_VI 4.096 ms, Table 9-155), so at most four 1 ms ticks share one access; a beacon
  ends the TXOP. The stations do not contend: they send only when triggered (their MU EDCA
  parameter set, 26.2.7, is assumed to keep them off the channel), so there are no collisions.
- **BSRP exchange**: the AP learns a station's queue only from a buffer status report (BSR,
  26.5.5): a BSRP Trigger frame solicits a QoS Null frame with a BSR from every polled station
  in one HE TB PPDU. A station that sends data reports its queue in the same A-MPDU (the BSR
  Control subfield of its HE A-Control, 9.2.4.6a.4), so only stations whose queue the AP
  believes empty are polled, every ``bsrp_interval_ticks``. With ``scheduled_uplink`` the AP
  knows each frame it admitted from its capture (a trigger-enabled TWT service period, 26.8)
  and polls no one.
- **DL MU exchange**: one HE MU PPDU carries every ready state frame (one A-MPDU per station
  on its RU); the stations return their block acks in an HE TB PPDU (26.5.2).
- **UL exchange**: basic Trigger frame, SIFS, HE TB PPDU with every data symbol left in the
  tick, SIFS, multi-STA BlockAck (26.5.3).

A beacon (non-HT, basic rate, after its own channel access) takes its airtime out of the tick
it falls in. Frame sizes count every header: per MSDU LLC/SNAP, IP and UDP; per MPDU the QoS
Data MAC header with HT Control and FCS; per A-MPDU subframe a delimiter and padding; per PPDU
and user the SERVICE field and tail bits; an A-MPDU that ends inside an MPDU sends it as a
dynamic fragment (26.3), one more MAC header, FCS and delimiter. Not modelled:
retransmissions (a frame the channel loses is lost, [per]), other BSSs, RTS/CTS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from codesign_mb.wifi.phy import PhyConfig

__all__ = ["MacTiming", "legacy_ppdu_us"]


def legacy_ppdu_us(payload_bytes: int, rate_mbps: float) -> float:
    """Airtime of a non-HT (legacy OFDM) PPDU: 20 us preamble + 4 us symbols.

    ``20 + 4 * ceil((16 + 8 L + 6) / (4 * rate))``: SERVICE (16) and tail (6) bits included
    (IEEE 802.11-2020 17.4.3, TXTIME of an OFDM PPDU).
    """
    bits_per_symbol = 4.0 * rate_mbps
    return 20.0 + 4.0 * math.ceil((16 + 8 * payload_bytes + 6) / bits_per_symbol)


@dataclass(frozen=True)
class MacTiming:
    """Every overhead of one schedule tick, explicit (IEEE 802.11ax-2021 clauses 9, 10, 26, 27).

    Parameters
    ----------
    tick_us:
        Schedule update period (paper Table II: 1 ms).
    sifs_us, slot_us:
        SIFS 16 us and slot 9 us of the 5 GHz OFDM PHY (Table 17-21), which the HE PHY
        characteristics (27.4) keep.
    aifsn, cw_min:
        The AP's EDCA parameters: AC_VI's default AIFSN 2 and CWmin 7 (Table 9-155).
    txop_limit_us:
        AC_VI's default TXOP limit for OFDM PHYs, 4.096 ms (Table 9-155); 0: every tick
        contends anew (one exchange sequence per access).
    legacy_rate_mbps:
        Non-HT rate of the Trigger and multi-STA BlockAck frames (6, 12, 24 Mb/s ...).
    trigger_base_bytes:
        Trigger frame without User Info: FC 2 + Duration 2 + RA 6 + TA 6 + Common Info 8
        + FCS 4 (9.3.1.22).
    trigger_user_bytes, bsrp_user_bytes:
        User Info field per station: 5 bytes, plus the 1-byte Trigger Dependent User Info of
        a basic Trigger (9.3.1.22.2); a BSRP Trigger has none.
    mba_base_bytes, mba_user_bytes:
        Multi-STA BlockAck: FC 2 + Duration 2 + RA 6 + TA 6 + BA Control 2 + FCS 4; per
        station AID TID Info 2 + Starting Sequence Control 2 + 64-bit bitmap 8 (9.3.1.9.7).
    block_ack_bytes:
        Compressed BlockAck a station returns for its DL A-MPDU: 16 + 2 + 2 + 8 + FCS 4
        (9.3.1.9.3).
    qos_null_bytes:
        QoS Null frame with HT Control (carrying the BSR): MAC header 26 + 4 + FCS 4.
    he_legacy_preamble_us:
        L-STF 8 + L-LTF 8 + L-SIG 4 + RL-SIG 4 + HE-SIG-A 8 us (27.3.11, Table 27-12).
    he_stf_tb_us, he_stf_mu_us:
        HE-STF of an HE TB PPDU (8 us) and of an HE MU PPDU (4 us) (27.3.11.9).
    sig_b_bits_per_symbol, sig_b_common_bits, sig_b_user_bits:
        HE-SIG-B at MCS 0 (26 bits per 4 us symbol and 20 MHz content channel), its common
        field and one 21-bit user field per station, split over the content channels
        (27.3.11.8).
    packet_extension_us:
        PE field at the end of every HE PPDU (0-16 us, 27.3.12).
    dl_data_symbols:
        Most data symbols of a DL MU PPDU; it gets the fewest that carry its longest A-MPDU.
    mac_header_bytes, fcs_bytes, delimiter_bytes:
        Per MPDU: QoS Data header 26 + HT Control 4 (9.3.2.1), FCS 4; per A-MPDU subframe a
        4-byte delimiter, subframes padded to 4 bytes (9.7.1).
    llc_snap_bytes, ip_udp_bytes, mtu_bytes:
        Per MSDU: LLC/SNAP 8 (RFC 1042), IPv4 20 + UDP 8; an application frame is cut into
        MSDUs of at most ``mtu_bytes`` of IP packet (1500).
    service_tail_bits:
        SERVICE field 16 + BCC tail 6 bits of every PSDU (27.3.12).
    bsrp_interval_ticks:
        Ticks between BSRP polls of the stations whose queue the AP believes empty (the AP's
        policy; the standard sets none). 8: a new camera frame waits at most 8 ms, a fifth
        of its 40 ms deadline, for the AP to learn of it, and each poll's airtime (about a
        fifth of a tick at MCS 0) is spent half as often as at 5, where the ns-3
        cross-check's MCS 0 synchronised cell loses a station (``codesign wifi crosscheck``:
        capacities at 5, 8, 10, 20 ticks in the issue note; 8 and above give the same).
    scheduled_uplink:
        ``True``: the AP knows every camera frame it admitted from its capture on and triggers
        the station without a buffer status report, and polls no one: the edge decided the
        request itself (the QoS policy runs on its replica of the robot's estimator), so it can
        serve the frame in a trigger-enabled TWT service period set at the capture (TWT, 26.8).
        ``False`` (default): the AP learns of frames from BSRs only, as in ns-3's model.
    beacon_interval_us, beacon_bytes, beacon_rate_mbps:
        Beacon every 100 TU (102.4 ms); its size (an assumption: 300 bytes with the HE
        elements) and its non-HT rate (the 6 Mb/s basic rate).
    """

    tick_us: float = 1000.0
    sifs_us: float = 16.0
    slot_us: float = 9.0
    aifsn: int = 2
    cw_min: int = 7
    txop_limit_us: float = 4096.0
    legacy_rate_mbps: float = 24.0
    trigger_base_bytes: int = 28
    trigger_user_bytes: int = 6
    bsrp_user_bytes: int = 5
    mba_base_bytes: int = 22
    mba_user_bytes: int = 12
    block_ack_bytes: int = 32
    qos_null_bytes: int = 34
    he_legacy_preamble_us: float = 32.0
    he_stf_tb_us: float = 8.0
    he_stf_mu_us: float = 4.0
    sig_b_bits_per_symbol: int = 26
    sig_b_common_bits: int = 18
    sig_b_user_bits: int = 21
    packet_extension_us: float = 4.0
    dl_data_symbols: int = 16
    mac_header_bytes: int = 30
    fcs_bytes: int = 4
    delimiter_bytes: int = 4
    llc_snap_bytes: int = 8
    ip_udp_bytes: int = 28
    mtu_bytes: int = 1500
    service_tail_bits: int = 22
    bsrp_interval_ticks: int = 8
    scheduled_uplink: bool = False
    beacon_interval_us: float = 102_400.0
    beacon_bytes: int = 300
    beacon_rate_mbps: float = 6.0

    def __post_init__(self) -> None:
        positive = (
            "tick_us",
            "slot_us",
            "legacy_rate_mbps",
            "sig_b_bits_per_symbol",
            "beacon_interval_us",
            "beacon_rate_mbps",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        non_negative = (
            "txop_limit_us",
            "sifs_us",
            "he_legacy_preamble_us",
            "he_stf_tb_us",
            "he_stf_mu_us",
            "packet_extension_us",
        )
        for name in non_negative:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0, got {value!r}")
        counts = (
            "aifsn",
            "cw_min",
            "trigger_base_bytes",
            "trigger_user_bytes",
            "bsrp_user_bytes",
            "mba_base_bytes",
            "mba_user_bytes",
            "block_ack_bytes",
            "qos_null_bytes",
            "sig_b_common_bits",
            "sig_b_user_bits",
            "mac_header_bytes",
            "fcs_bytes",
            "delimiter_bytes",
            "llc_snap_bytes",
            "ip_udp_bytes",
            "service_tail_bits",
            "beacon_bytes",
        )
        for name in counts:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
        for name in ("dl_data_symbols", "bsrp_interval_ticks"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not isinstance(self.scheduled_uplink, bool):
            raise ValueError(
                f"scheduled_uplink must be true or false, got {self.scheduled_uplink!r}"
            )
        if not (isinstance(self.mtu_bytes, int) and self.mtu_bytes > self.ip_udp_bytes):
            raise ValueError(f"mtu_bytes must exceed ip_udp_bytes, got {self.mtu_bytes!r}")

    # -- access ---------------------------------------------------------------------------------
    @property
    def channel_access_us(self) -> float:
        """AIFS + mean backoff: ``SIFS + AIFSN slot + CWmin / 2 slot`` (10.23.2)."""
        return self.sifs_us + self.aifsn * self.slot_us + self.cw_min / 2 * self.slot_us

    @property
    def txop_ticks(self) -> int:
        """Most ticks one TXOP spans: the first pays the access, the others a SIFS (10.23.2.8)."""
        if self.txop_limit_us <= 0:
            return 1
        # the TXOP starts after the first tick's access and must cover every later tick whole
        return max(
            1,
            1
            + math.floor(
                (self.txop_limit_us - self.tick_us + self.channel_access_us) / self.tick_us + 1e-9
            ),
        )

    def access_us(self, continues_txop: bool) -> float:
        """Gap before a tick's first exchange: a SIFS inside a TXOP, else the channel access."""
        return self.sifs_us if continues_txop else self.channel_access_us

    @property
    def beacon_us(self) -> float:
        """A beacon's channel access and non-HT PPDU."""
        return self.channel_access_us + legacy_ppdu_us(self.beacon_bytes, self.beacon_rate_mbps)

    def beacon_due(self, tick: int) -> bool:
        """Whether a beacon (every ``beacon_interval_us``, the first at 0) falls in ``tick``."""
        start, end = tick * self.tick_us, (tick + 1) * self.tick_us
        return math.ceil(start / self.beacon_interval_us - 1e-9) * self.beacon_interval_us < end

    # -- frame sizes ----------------------------------------------------------------------------
    def msdu_count(self, payload_bytes: int) -> int:
        """MSDUs (IP packets of at most ``mtu_bytes``) of an application frame."""
        return max(1, math.ceil(payload_bytes / (self.mtu_bytes - self.ip_udp_bytes)))

    def ampdu_bytes(self, payload_bytes: int) -> int:
        """A-MPDU carrying an application frame: every MSDU in its own MPDU and subframe."""
        n = self.msdu_count(payload_bytes)
        per_mpdu = self.llc_snap_bytes + self.ip_udp_bytes + self.mac_header_bytes + self.fcs_bytes
        chunk = self.mtu_bytes - self.ip_udp_bytes
        sizes = [chunk] * (n - 1) + [payload_bytes - chunk * (n - 1)]
        subframes = [self.delimiter_bytes + s + per_mpdu for s in sizes]
        return sum(4 * math.ceil(s / 4) for s in subframes[:-1]) + subframes[-1]

    def psdu_bits(self, payload_bytes: int) -> int:
        """Bits of the A-MPDU of an application frame of ``payload_bytes`` (all headers)."""
        return 8 * self.ampdu_bytes(payload_bytes)

    def data_symbols(self, psdu_bytes: int, data_subcarriers: int, bits_per_sc: float) -> int:
        """HE data symbols of one user's PSDU on its RU: ``ceil((22 + 8 L) / (N_SD b))``."""
        return math.ceil(
            (self.service_tail_bits + 8 * psdu_bytes) / (data_subcarriers * bits_per_sc)
        )

    # -- PPDUs ----------------------------------------------------------------------------------
    def trigger_us(self, n_users: int, *, bsrp: bool = False) -> float:
        """Basic (or BSRP) Trigger frame, non-HT PPDU, addressing ``n_users`` stations."""
        per_user = self.bsrp_user_bytes if bsrp else self.trigger_user_bytes
        size = self.trigger_base_bytes + per_user * max(n_users, 1)
        return legacy_ppdu_us(size, self.legacy_rate_mbps)

    def multi_sta_ba_us(self, n_users: int) -> float:
        """Multi-STA BlockAck (non-HT PPDU) acknowledging ``n_users`` stations."""
        size = self.mba_base_bytes + self.mba_user_bytes * max(n_users, 1)
        return legacy_ppdu_us(size, self.legacy_rate_mbps)

    def he_tb_ppdu_us(self, n_symbols: int, phy: PhyConfig) -> float:
        """HE TB PPDU: legacy part and HE-SIG-A, HE-STF 8 us, HE-LTFs, data at the UL GI, PE."""
        preamble = self.he_legacy_preamble_us + self.he_stf_tb_us + phy.ul_ltf_us
        return preamble + n_symbols * phy.ul_symbol_us + self.packet_extension_us

    def he_mu_ppdu_us(self, n_symbols: int, n_users: int, phy: PhyConfig) -> float:
        """HE MU PPDU: legacy part, HE-SIG-B (users over the content channels), STF, LTFs, data."""
        channels = 1 if phy.bandwidth_mhz == 20 else 2
        users_per_channel = math.ceil(max(n_users, 1) / channels)
        sig_b_bits = self.sig_b_common_bits + self.sig_b_user_bits * users_per_channel
        sig_b_us = 4.0 * math.ceil(sig_b_bits / self.sig_b_bits_per_symbol)
        preamble = self.he_legacy_preamble_us + sig_b_us + self.he_stf_mu_us + phy.dl_ltf_us
        return preamble + n_symbols * phy.symbol_us + self.packet_extension_us

    # -- exchanges ------------------------------------------------------------------------------
    def bsrp_exchange_us(self, n_users: int, n_symbols: int, phy: PhyConfig) -> float:
        """BSRP Trigger, SIFS, the stations' QoS Null + BSR in an HE TB PPDU, SIFS."""
        if n_users <= 0:
            return 0.0
        tb = self.he_tb_ppdu_us(n_symbols, phy)
        return self.trigger_us(n_users, bsrp=True) + self.sifs_us + tb + self.sifs_us

    def dl_exchange_us(
        self, n_users: int, n_symbols: int, ack_symbols: int, phy: PhyConfig
    ) -> float:
        """[air_dl]: MU PPDU + SIFS + block acks in a TB PPDU + SIFS (0 without DL users)."""
        if n_users <= 0:
            return 0.0
        mu = self.he_mu_ppdu_us(n_symbols, n_users, phy)
        return mu + self.sifs_us + self.he_tb_ppdu_us(ack_symbols, phy) + self.sifs_us

    def ul_overhead_us(self, n_users: int, phy: PhyConfig) -> float:
        """[air_ul] without the data symbols: trigger, SIFS, TB preamble, SIFS, M-BA."""
        return (
            self.trigger_us(n_users)
            + self.sifs_us
            + self.he_tb_ppdu_us(0, phy)
            + self.sifs_us
            + self.multi_sta_ba_us(n_users)
        )

    def ul_data_symbols(
        self, n_ul_users: int, busy_us: float, phy: PhyConfig, *, continues_txop: bool = False
    ) -> int:
        """Data symbols left for the UL TB PPDU in a tick whose other exchanges take ``busy_us``.

        ``continues_txop``: the tick continues the previous tick's TXOP (a SIFS, no access).
        """
        if n_ul_users <= 0:
            return 0
        access = self.access_us(continues_txop)
        left = self.tick_us - access - busy_us - self.ul_overhead_us(n_ul_users, phy)
        return max(0, math.floor(left / phy.ul_symbol_us + 1e-9))

    def max_ul_data_symbols(self, phy: PhyConfig, *, with_dl: bool) -> int:
        """Most UL data symbols of any tick (one user, no poll, no beacon), next to a DL exchange.

        The shortest DL exchange (one user, one data and one ack symbol) leaves the most, in a
        tick that continues a TXOP when the limit lets one span ticks: the offline LP's bound
        relies on no tick ever getting more.
        """
        busy = self.dl_exchange_us(1, 1, 1, phy) if with_dl else 0.0
        return self.ul_data_symbols(1, busy, phy, continues_txop=self.txop_ticks > 1)

    def breakdown(self, n_ul_users: int, n_dl_users: int, phy: PhyConfig) -> dict[str, float]:
        """Airtime of each part of a tick with one-symbol DL PPDU and acks, in us (for the docs)."""
        dl = self.dl_exchange_us(n_dl_users, 1, 1, phy)
        n_ul = self.ul_data_symbols(n_ul_users, dl, phy)
        return {
            "channel_access_us": self.channel_access_us,
            "dl_exchange_us": dl,
            "trigger_us": self.trigger_us(n_ul_users),
            "ul_overhead_us": self.ul_overhead_us(n_ul_users, phy),
            "ul_data_symbols": float(n_ul),
            "ul_data_us": n_ul * phy.ul_symbol_us,
            "multi_sta_ba_us": self.multi_sta_ba_us(n_ul_users),
        }
