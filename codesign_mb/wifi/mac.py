"""802.11ax MAC airtime of one schedule tick: the frame exchanges, their PPDUs and overheads.

:class:`MacTiming` holds every overhead of the two frame exchanges of a schedule tick
explicitly: a downlink multi-user exchange (``eq_air_dl``: HE MU PPDU, SIFS, the stations'
block acks in an HE TB PPDU, SIFS) and a trigger-based uplink exchange (``eq_air_ul``: basic
Trigger frame, SIFS, HE TB PPDU, SIFS, multi-STA BlockAck, SIFS), after one channel access.
The PHY rates and the RU plan the data symbols carry are in :mod:`codesign_mb.wifi.phy`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["MacTiming", "legacy_ppdu_us"]


def legacy_ppdu_us(payload_bytes: int, rate_mbps: float) -> float:
    """Airtime of a non-HT (legacy OFDM) PPDU: 20 us preamble + 4 us symbols.

    ``20 + 4 * ceil((16 + 8 L + 6) / (4 * rate))``: SERVICE (16) and tail (6) bits included.
    """
    bits_per_symbol = 4.0 * rate_mbps
    return 20.0 + 4.0 * math.ceil((16 + 8 * payload_bytes + 6) / bits_per_symbol)


@dataclass(frozen=True)
class MacTiming:
    """Every overhead of one schedule tick, explicit (IEEE 802.11ax-2021 clauses 26, 27).

    One tick of ``tick_us`` holds one channel access, then (if any downlink frame is queued)
    a DL MU exchange, then (if any uplink frame is queued) a trigger-based UL exchange:

    ``T_DL = T_MU(N_dl) + SIFS + T_TB(ack) + SIFS`` (``eq_air_dl``),
    ``T_UL = T_trig(n) + SIFS + T_TB(N_ul) + SIFS + T_MBA(n) + SIFS`` (``eq_air_ul``),

    and the UL PPDU gets every data symbol that fits: ``N_ul = floor((tick - access - T_DL -
    overheads of T_UL) / T_sym)``.

    Parameters
    ----------
    tick_us:
        Schedule update period (paper Table II: 1 ms).
    sifs_us:
        Short interframe space (5 GHz: 16 us).
    channel_access_us:
        AIFS plus mean backoff of the AP once per tick (e.g. AC_VI: 34 + 3.5 * 9 us).
    legacy_rate_mbps:
        Non-HT rate of the Trigger and multi-STA BlockAck frames (6, 12, 24 Mb/s ...).
    trigger_base_bytes:
        Basic Trigger frame without user info: MAC header 16 + common info 8 + FCS 4 (+ pad).
    trigger_user_bytes:
        User Info field per scheduled station (basic trigger: 6).
    mba_base_bytes, mba_user_bytes:
        Multi-STA BlockAck: header 16 + BA control 2 + FCS 4; per station AID/TID 2 + SSN 2
        + 8-byte bitmap.
    he_legacy_preamble_us:
        L-STF 8 + L-LTF 8 + L-SIG 4 + RL-SIG 4 + HE-SIG-A 8 us.
    he_stf_tb_us, he_stf_mu_us:
        HE-STF of an HE TB PPDU (8 us) and of an HE MU PPDU (4 us).
    he_ltf_us, he_ltf_count:
        One HE-LTF symbol (2x LTF + 1.6 us GI = 8 us) and how many (one per stream).
    sig_b_bits_per_symbol, sig_b_common_bits, sig_b_user_bits:
        HE-SIG-B at MCS 0 (26 bits per 4 us symbol and 20 MHz content channel), its common
        field and one 21-bit user field per station, split over the content channels.
    packet_extension_us:
        PE field at the end of every HE PPDU (0-16 us).
    dl_data_symbols:
        Data symbols of the DL MU PPDU when downlink frames are queued.
    dl_ack_symbols:
        Data symbols of the HE TB PPDU that carries the stations' block acks of the DL.
    mpdu_payload_bytes, mpdu_overhead_bytes:
        Frames are split into MPDUs of at most ``mpdu_payload_bytes``; each costs
        ``mpdu_overhead_bytes`` more (MAC header 26 + FCS 4 + A-MPDU delimiter 4).
    """

    tick_us: float = 1000.0
    sifs_us: float = 16.0
    channel_access_us: float = 66.0
    legacy_rate_mbps: float = 24.0
    trigger_base_bytes: int = 28
    trigger_user_bytes: int = 6
    mba_base_bytes: int = 22
    mba_user_bytes: int = 12
    he_legacy_preamble_us: float = 32.0
    he_stf_tb_us: float = 8.0
    he_stf_mu_us: float = 4.0
    he_ltf_us: float = 8.0
    he_ltf_count: int = 1
    sig_b_bits_per_symbol: int = 26
    sig_b_common_bits: int = 18
    sig_b_user_bits: int = 21
    packet_extension_us: float = 4.0
    dl_data_symbols: int = 6
    dl_ack_symbols: int = 2
    mpdu_payload_bytes: int = 1500
    mpdu_overhead_bytes: int = 34

    def __post_init__(self) -> None:
        for name in (
            "tick_us",
            "legacy_rate_mbps",
            "he_ltf_us",
            "sig_b_bits_per_symbol",
            "mpdu_payload_bytes",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        for name in (
            "sifs_us",
            "channel_access_us",
            "trigger_base_bytes",
            "trigger_user_bytes",
            "mba_base_bytes",
            "mba_user_bytes",
            "he_legacy_preamble_us",
            "he_stf_tb_us",
            "he_stf_mu_us",
            "sig_b_common_bits",
            "sig_b_user_bits",
            "packet_extension_us",
            "dl_ack_symbols",
            "mpdu_overhead_bytes",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0, got {value!r}")
        for name in ("he_ltf_count", "dl_data_symbols"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")

    # -- frame sizes --------------------------------------------------------------------------
    def psdu_bits(self, payload_bytes: int) -> int:
        """Bits on the air for a MAC frame of ``payload_bytes``, MPDU overheads included."""
        n_mpdu = max(1, math.ceil(payload_bytes / self.mpdu_payload_bytes))
        return 8 * (payload_bytes + n_mpdu * self.mpdu_overhead_bytes)

    # -- PPDUs --------------------------------------------------------------------------------
    def trigger_us(self, n_users: int) -> float:
        """Basic Trigger frame (non-HT PPDU) addressing ``n_users`` stations."""
        size = self.trigger_base_bytes + self.trigger_user_bytes * max(n_users, 1)
        return legacy_ppdu_us(size, self.legacy_rate_mbps)

    def multi_sta_ba_us(self, n_users: int) -> float:
        """Multi-STA BlockAck (non-HT PPDU) acknowledging ``n_users`` stations."""
        size = self.mba_base_bytes + self.mba_user_bytes * max(n_users, 1)
        return legacy_ppdu_us(size, self.legacy_rate_mbps)

    def he_tb_ppdu_us(self, n_symbols: int, symbol_us: float) -> float:
        """HE trigger-based PPDU: legacy part, HE-STF 8 us, HE-LTFs, data, PE."""
        preamble = self.he_legacy_preamble_us + self.he_stf_tb_us
        return (
            preamble
            + self.he_ltf_count * self.he_ltf_us
            + n_symbols * symbol_us
            + (self.packet_extension_us)
        )

    def he_mu_ppdu_us(
        self, n_symbols: int, n_users: int, symbol_us: float, bandwidth_mhz: int
    ) -> float:
        """HE MU PPDU: legacy part, HE-SIG-B (users over the content channels), STF, LTFs, data."""
        channels = 1 if bandwidth_mhz == 20 else 2
        users_per_channel = math.ceil(max(n_users, 1) / channels)
        sig_b_bits = self.sig_b_common_bits + self.sig_b_user_bits * users_per_channel
        sig_b_us = 4.0 * math.ceil(sig_b_bits / self.sig_b_bits_per_symbol)
        preamble = self.he_legacy_preamble_us + sig_b_us + self.he_stf_mu_us
        return (
            preamble
            + self.he_ltf_count * self.he_ltf_us
            + n_symbols * symbol_us
            + (self.packet_extension_us)
        )

    # -- the tick -----------------------------------------------------------------------------
    def dl_exchange_us(self, n_users: int, symbol_us: float, bandwidth_mhz: int) -> float:
        """``eq_air_dl``: MU PPDU + SIFS + block acks in a TB PPDU + SIFS (0 without DL users)."""
        if n_users <= 0:
            return 0.0
        mu = self.he_mu_ppdu_us(self.dl_data_symbols, n_users, symbol_us, bandwidth_mhz)
        ack = self.he_tb_ppdu_us(self.dl_ack_symbols, symbol_us)
        return mu + self.sifs_us + ack + self.sifs_us

    def ul_overhead_us(self, n_users: int, symbol_us: float) -> float:
        """``eq_air_ul`` without the data symbols: trigger, SIFS, TB preamble, SIFS, M-BA, SIFS."""
        return (
            self.trigger_us(n_users)
            + self.sifs_us
            + self.he_tb_ppdu_us(0, symbol_us)
            + self.sifs_us
            + self.multi_sta_ba_us(n_users)
            + self.sifs_us
        )

    def ul_data_symbols(
        self, n_ul_users: int, n_dl_users: int, symbol_us: float, bandwidth_mhz: int
    ) -> int:
        """Data symbols left for the UL TB PPDU in one tick (0 if none fit)."""
        if n_ul_users <= 0:
            return 0
        left = (
            self.tick_us
            - self.channel_access_us
            - self.dl_exchange_us(n_dl_users, symbol_us, bandwidth_mhz)
            - self.ul_overhead_us(n_ul_users, symbol_us)
        )
        return max(0, math.floor(left / symbol_us + 1e-9))

    def breakdown(
        self, n_ul_users: int, n_dl_users: int, symbol_us: float, bandwidth_mhz: int
    ) -> dict[str, float]:
        """Airtime of each part of a tick, in us (for the docs and ``phy-table``)."""
        n_ul = self.ul_data_symbols(n_ul_users, n_dl_users, symbol_us, bandwidth_mhz)
        return {
            "channel_access_us": self.channel_access_us,
            "dl_exchange_us": self.dl_exchange_us(n_dl_users, symbol_us, bandwidth_mhz),
            "dl_data_us": self.dl_data_symbols * symbol_us if n_dl_users else 0.0,
            "trigger_us": self.trigger_us(n_ul_users),
            "ul_overhead_us": self.ul_overhead_us(n_ul_users, symbol_us),
            "ul_data_symbols": float(n_ul),
            "ul_data_us": n_ul * symbol_us,
            "multi_sta_ba_us": self.multi_sta_ba_us(n_ul_users),
        }
