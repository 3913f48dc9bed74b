"""IEEE 802.11ax (WiFi 6) PHY: the OFDMA resource-unit plan and the MCS rates.

Resource units (RUs)
--------------------
An HE PPDU of 20/40/80 MHz is cut into RUs of 26, 52, 106, 242, 484 and 996 tones with
24, 48, 102, 234, 468 and 980 data subcarriers (IEEE 802.11ax-2021, 27.3.2.2). Their tone
positions are those of Tables 27-7 to 27-9 (subcarrier index ranges, DC at 0). Two RUs
*overlap* when their tone sets intersect; an OFDMA layout is a set of pairwise non-overlapping
RUs, one per station ([layout]). We also describe every RU by the 26-tone RUs it covers
(its *units*, a bit mask): the tone plan is laminar, so two RUs overlap iff their unit masks
intersect, which is what the allocators use. The centre 26-tone RU of a 20 MHz (and of the
80 MHz) channel is covered by no 52- or 106-tone RU.

Rates
-----
``rate = N_SD * N_BPSCS * R * N_SS / (T_DFT + T_GI)`` ([rate]) with ``T_DFT = 12.8 us``
and ``T_GI`` in {0.8, 1.6, 3.2} us. E.g. 484-tone RU, MCS 11, 1 stream, 0.8 us GI:
468 * 10 * 5/6 / 13.6 us = 286.8 Mb/s.

Guard interval and HE-LTF
-------------------------
Not every GI goes with every PPDU: an HE TB PPDU (the uplink of OFDMA) uses 1.6 us with the
1x or 2x HE-LTF or 3.2 us with the 4x HE-LTF (the Trigger frame's GI And HE-LTF Type subfield,
IEEE 802.11ax-2021 9.3.1.22); an HE MU PPDU (the OFDMA downlink) uses 0.8 us with 2x or 4x,
1.6 us with 2x, or 3.2 us with 4x (HE-SIG-A GI+LTF Size, 27.3.11.7). The DL and UL GI are
therefore separate settings (:class:`PhyConfig`), and each HE-LTF symbol lasts its DFT period
(1x 3.2, 2x 6.4, 4x 12.8 us, 27.3.11.10) plus its GI: 8 us for 2x + 1.6 us, 16 us for 4x +
3.2 us.

The airtime of a schedule tick (frame exchanges, MAC overheads) is in :mod:`codesign_mb.wifi.mac`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "BANDWIDTHS_MHZ",
    "DATA_SUBCARRIERS",
    "GUARD_INTERVALS_US",
    "HE_LTF_DFT_US",
    "HE_MU_GI_LTF",
    "HE_TB_GI_LTF",
    "HE_TB_GUARD_INTERVALS_US",
    "MCS_TABLE",
    "RU_TONES",
    "SYMBOL_DFT_US",
    "Mcs",
    "PhyConfig",
    "ResourceUnit",
    "RuPlan",
    "data_rate_mbps",
    "he_ltf_symbol_us",
    "ru_plan",
]

SYMBOL_DFT_US = 12.8
"""HE OFDM symbol duration without guard interval (78.125 kHz subcarrier spacing)."""

GUARD_INTERVALS_US = (0.8, 1.6, 3.2)
"""HE guard intervals (IEEE 802.11ax-2021 27.3.9: T_GI1.6 ... 0.8, 1.6, 3.2 us)."""
HE_TB_GUARD_INTERVALS_US = (1.6, 3.2)
"""GIs an HE TB PPDU may use (9.3.1.22, GI And HE-LTF Type: 1x/2x LTF + 1.6, 4x LTF + 3.2)."""
HE_LTF_DFT_US = {1: 3.2, 2: 6.4, 4: 12.8}
"""DFT period of a 1x, 2x and 4x HE-LTF symbol (27.3.11.10; the GI comes on top)."""
HE_TB_GI_LTF = ((1.6, 1), (1.6, 2), (3.2, 4))
"""(GI us, HE-LTF size) pairs allowed in an HE TB PPDU (9.3.1.22, Common Info field)."""
HE_MU_GI_LTF = ((0.8, 2), (0.8, 4), (1.6, 2), (3.2, 4))
"""(GI us, HE-LTF size) pairs allowed in an HE MU PPDU (27.3.11.7, HE-SIG-A GI+LTF Size)."""
BANDWIDTHS_MHZ = (20, 40, 80)
RU_TONES = (26, 52, 106, 242, 484, 996)
DATA_SUBCARRIERS = {26: 24, 52: 48, 106: 102, 242: 234, 484: 468, 996: 980}
"""Data subcarriers ``N_SD`` of each RU size (the rest are pilots)."""


@dataclass(frozen=True, slots=True)
class Mcs:
    """One HE-MCS: modulation order (bits per subcarrier ``N_BPSCS``) and code rate ``R``."""

    index: int
    modulation: str
    bits_per_subcarrier: int
    code_rate: float

    @property
    def bits_per_data_subcarrier(self) -> float:
        """Information bits per data subcarrier per symbol and stream: ``N_BPSCS * R``."""
        return self.bits_per_subcarrier * self.code_rate


MCS_TABLE: tuple[Mcs, ...] = (
    Mcs(0, "BPSK", 1, 1 / 2),
    Mcs(1, "QPSK", 2, 1 / 2),
    Mcs(2, "QPSK", 2, 3 / 4),
    Mcs(3, "16-QAM", 4, 1 / 2),
    Mcs(4, "16-QAM", 4, 3 / 4),
    Mcs(5, "64-QAM", 6, 2 / 3),
    Mcs(6, "64-QAM", 6, 3 / 4),
    Mcs(7, "64-QAM", 6, 5 / 6),
    Mcs(8, "256-QAM", 8, 3 / 4),
    Mcs(9, "256-QAM", 8, 5 / 6),
    Mcs(10, "1024-QAM", 10, 3 / 4),
    Mcs(11, "1024-QAM", 10, 5 / 6),
)
"""HE-MCS 0-11 (IEEE 802.11ax-2021, Tables 27-55 ff.)."""


def _check_mcs(mcs: int) -> Mcs:
    if isinstance(mcs, bool) or int(mcs) != mcs or not 0 <= mcs < len(MCS_TABLE):
        raise ValueError(f"mcs must be an integer in [0, 11], got {mcs!r}")
    return MCS_TABLE[int(mcs)]


def _check_gi(gi_us: float) -> float:
    if not any(math.isclose(gi_us, g) for g in GUARD_INTERVALS_US):
        raise ValueError(f"guard_interval_us must be one of 0.8, 1.6, 3.2, got {gi_us!r}")
    return float(gi_us)


def he_ltf_symbol_us(guard_interval_us: float, *, trigger_based: bool) -> float:
    """One HE-LTF symbol: the LTF size that goes with the GI, plus the GI (27.3.11.10).

    The 2x HE-LTF with 0.8 and 1.6 us (HE MU) or 1.6 us (HE TB), the 4x HE-LTF with 3.2 us:
    the pairs every HE PPDU format allows (:data:`HE_MU_GI_LTF`, :data:`HE_TB_GI_LTF`).

    Examples
    --------
    >>> he_ltf_symbol_us(1.6, trigger_based=True), he_ltf_symbol_us(3.2, trigger_based=True)
    (8.0, 16.0)
    >>> he_ltf_symbol_us(0.8, trigger_based=False)
    7.2
    """
    gi = _check_gi(guard_interval_us)
    size = 4 if math.isclose(gi, 3.2) else 2
    allowed = HE_TB_GI_LTF if trigger_based else HE_MU_GI_LTF
    if not any(math.isclose(gi, g) and size == n for g, n in allowed):
        kind = "HE TB" if trigger_based else "HE MU"
        raise ValueError(f"guard_interval_us {gi} is not allowed in an {kind} PPDU")
    return round(HE_LTF_DFT_US[size] + gi, 9)


def data_rate_mbps(
    ru_tones: int, mcs: int, *, spatial_streams: int = 1, guard_interval_us: float = 0.8
) -> float:
    """PHY data rate of one RU ([rate]), in Mb/s.

    Parameters
    ----------
    ru_tones:
        RU size in tones (26, 52, 106, 242, 484 or 996).
    mcs:
        HE-MCS index 0-11.
    spatial_streams:
        ``N_SS`` (1-8).
    guard_interval_us:
        0.8, 1.6 or 3.2 us.

    Examples
    --------
    >>> round(data_rate_mbps(484, 11), 1), round(data_rate_mbps(484, 0), 1)
    (286.8, 17.2)
    >>> round(data_rate_mbps(242, 7), 1)
    86.0
    """
    if ru_tones not in DATA_SUBCARRIERS:
        raise ValueError(f"ru_tones must be one of {RU_TONES}, got {ru_tones!r}")
    if isinstance(spatial_streams, bool) or spatial_streams not in range(1, 9):
        raise ValueError(f"spatial_streams must be an integer in [1, 8], got {spatial_streams!r}")
    m = _check_mcs(mcs)
    symbol_us = SYMBOL_DFT_US + _check_gi(guard_interval_us)
    bits = DATA_SUBCARRIERS[ru_tones] * m.bits_per_data_subcarrier * spatial_streams
    return bits / symbol_us  # [rate] (bits per us = Mb/s)


# --------------------------------------------------------------------------- RU plan

# Tone ranges (inclusive) of each RU, IEEE 802.11ax-2021 Tables 27-7 (20 MHz), 27-8 (40 MHz)
# and 27-9 (80 MHz). Two ranges for RUs split by the DC tones.
_Ranges = tuple[tuple[int, int], ...]
_TONE_PLAN: dict[int, dict[int, tuple[_Ranges, ...]]] = {
    20: {
        26: (
            ((-121, -96),), ((-95, -70),), ((-68, -43),), ((-42, -17),), ((-16, -4), (4, 16)),
            ((17, 42),), ((43, 68),), ((70, 95),), ((96, 121),),
        ),
        52: (((-121, -70),), ((-68, -17),), ((17, 68),), ((70, 121),)),
        106: (((-122, -17),), ((17, 122),)),
        242: (((-122, -2), (2, 122)),),
    },
    40: {
        26: (
            ((-243, -218),), ((-217, -192),), ((-189, -164),), ((-163, -138),), ((-136, -111),),
            ((-109, -84),), ((-83, -58),), ((-55, -30),), ((-29, -4),), ((4, 29),), ((30, 55),),
            ((58, 83),), ((84, 109),), ((111, 136),), ((138, 163),), ((164, 189),),
            ((192, 217),), ((218, 243),),
        ),
        52: (
            ((-243, -192),), ((-189, -138),), ((-109, -58),), ((-55, -4),), ((4, 55),),
            ((58, 109),), ((138, 189),), ((192, 243),),
        ),
        106: (((-243, -138),), ((-109, -4),), ((4, 109),), ((138, 243),)),
        242: (((-244, -3),), ((3, 244),)),
        484: (((-244, -3), (3, 244)),),
    },
    80: {
        26: (
            ((-499, -474),), ((-473, -448),), ((-445, -420),), ((-419, -394),), ((-392, -367),),
            ((-365, -340),), ((-339, -314),), ((-311, -286),), ((-285, -260),), ((-257, -232),),
            ((-231, -206),), ((-203, -178),), ((-177, -152),), ((-150, -125),), ((-123, -98),),
            ((-97, -72),), ((-69, -44),), ((-43, -18),), ((-16, -4), (4, 16)), ((18, 43),),
            ((44, 69),), ((72, 97),), ((98, 123),), ((125, 150),), ((152, 177),),
            ((178, 203),), ((206, 231),), ((232, 257),), ((260, 285),), ((286, 311),),
            ((314, 339),), ((340, 365),), ((367, 392),), ((394, 419),), ((420, 445),),
            ((448, 473),), ((474, 499),),
        ),
        52: (
            ((-499, -448),), ((-445, -394),), ((-365, -314),), ((-311, -260),), ((-257, -206),),
            ((-203, -152),), ((-123, -72),), ((-69, -18),), ((18, 69),), ((72, 123),),
            ((152, 203),), ((206, 257),), ((260, 311),), ((314, 365),), ((394, 445),),
            ((448, 499),),
        ),
        106: (
            ((-499, -394),), ((-365, -260),), ((-257, -152),), ((-123, -18),), ((18, 123),),
            ((152, 257),), ((260, 365),), ((394, 499),),
        ),
        242: (((-500, -259),), ((-258, -17),), ((17, 258),), ((259, 500),)),
        484: (((-500, -259), (-258, -17)), ((17, 258), (259, 500))),
        996: (((-500, -3), (3, 500)),),
    },
}  # fmt: skip


@dataclass(frozen=True, slots=True)
class ResourceUnit:
    """One RU of a channel's plan.

    Attributes
    ----------
    index:
        Position in :attr:`RuPlan.units` (sorted by size, then frequency).
    tones:
        RU size (26, 52, ...); :attr:`data_subcarriers` is its ``N_SD``.
    position:
        Index among the RUs of the same size, from the lowest frequency (``RU1`` is 0).
    tone_ranges:
        Inclusive subcarrier-index ranges of the RU (DC = 0).
    unit_mask:
        Bit ``k`` set iff the RU covers the ``k``-th 26-tone RU.
    """

    index: int
    tones: int
    position: int
    tone_ranges: tuple[tuple[int, int], ...]
    unit_mask: int

    @property
    def data_subcarriers(self) -> int:
        return DATA_SUBCARRIERS[self.tones]

    @property
    def n_units(self) -> int:
        """Number of 26-tone RUs it covers."""
        return self.unit_mask.bit_count()

    def overlaps(self, other: ResourceUnit) -> bool:
        """Whether the two RUs share a subcarrier ([layout])."""
        return bool(self.unit_mask & other.unit_mask)


@dataclass(frozen=True)
class RuPlan:
    """Every RU of one channel bandwidth and how they overlap.

    Attributes
    ----------
    bandwidth_mhz:
        20, 40 or 80.
    units:
        All RUs, smallest first (``units[i].index == i``).
    sizes:
        The RU sizes available, ascending.
    n_units:
        Number of 26-tone RUs (9, 18, 37): the finest partition of the channel.
    """

    bandwidth_mhz: int
    units: tuple[ResourceUnit, ...]
    sizes: tuple[int, ...]
    n_units: int

    @property
    def full_band_data_subcarriers(self) -> int:
        """``N_SD`` of the widest RU: an upper bound on the data subcarriers of any layout."""
        return DATA_SUBCARRIERS[self.sizes[-1]]

    def of_size(self, tones: int) -> tuple[ResourceUnit, ...]:
        """The RUs of one size, from low to high frequency."""
        return tuple(u for u in self.units if u.tones == tones)

    def count(self, tones: int) -> int:
        """How many RUs of one size fit in the channel."""
        return len(self.of_size(tones))

    def is_valid_layout(self, ru_indices: list[int] | tuple[int, ...] | NDArray) -> bool:
        """Whether the RUs (indices into :attr:`units`, ``-1`` = none) are pairwise disjoint."""
        used = 0
        for r in np.asarray(ru_indices, dtype=int).ravel():
            if r < 0:
                continue
            if r >= len(self.units):
                return False
            mask = self.units[r].unit_mask
            if used & mask:
                return False
            used |= mask
        return True

    def overlap_matrix(self) -> NDArray[np.bool_]:
        """``M[i, j]`` is True iff RUs ``i`` and ``j`` share a subcarrier (by tone positions)."""
        tones = [_tone_set(u.tone_ranges) for u in self.units]
        n = len(tones)
        out = np.zeros((n, n), dtype=bool)
        for i in range(n):
            for j in range(n):
                out[i, j] = bool(tones[i] & tones[j])
        return out


def _tone_set(ranges: tuple[tuple[int, int], ...]) -> set[int]:
    return {k for lo, hi in ranges for k in range(lo, hi + 1)}


@cache
def ru_plan(bandwidth_mhz: int) -> RuPlan:
    """The 802.11ax RU plan of a 20, 40 or 80 MHz channel (Tables 27-7 to 27-9).

    Examples
    --------
    >>> plan = ru_plan(40)
    >>> [plan.count(t) for t in plan.sizes]
    [18, 8, 4, 2, 1]
    """
    if bandwidth_mhz not in _TONE_PLAN:
        raise ValueError(f"bandwidth_mhz must be one of {BANDWIDTHS_MHZ}, got {bandwidth_mhz!r}")
    table = _TONE_PLAN[bandwidth_mhz]
    small = [_tone_set(r) for r in table[26]]
    units: list[ResourceUnit] = []
    for tones in sorted(table):
        for position, ranges in enumerate(table[tones]):
            tone_set = _tone_set(ranges)
            if len(tone_set) != tones:  # guards the transcription of the tables
                raise AssertionError(f"{tones}-tone RU {position} has {len(tone_set)} tones")
            mask = sum(1 << k for k, s in enumerate(small) if s & tone_set)
            units.append(ResourceUnit(len(units), tones, position, ranges, mask))
    return RuPlan(bandwidth_mhz, tuple(units), tuple(sorted(table)), len(small))


# --------------------------------------------------------------------------- config


@dataclass(frozen=True)
class PhyConfig:
    """PHY settings of the channel.

    Parameters
    ----------
    bandwidth_mhz:
        Channel width: 20, 40 or 80 MHz (the paper: 40).
    guard_interval_us:
        GI of the downlink (HE MU PPDU) and of single-user PPDUs: 0.8, 1.6 or 3.2 us.
    ul_guard_interval_us:
        GI of the uplink HE TB PPDU: 1.6 or 3.2 us (0.8 is not allowed, 9.3.1.22).
    spatial_streams:
        ``N_SS`` of every station (1 or 2).
    """

    bandwidth_mhz: int = 40
    guard_interval_us: float = 0.8
    ul_guard_interval_us: float = 1.6
    spatial_streams: int = 1

    def __post_init__(self) -> None:
        if self.bandwidth_mhz not in BANDWIDTHS_MHZ:
            raise ValueError(
                f"bandwidth_mhz must be one of {BANDWIDTHS_MHZ}, got {self.bandwidth_mhz!r}"
            )
        _check_gi(self.guard_interval_us)
        if not any(math.isclose(self.ul_guard_interval_us, g) for g in HE_TB_GUARD_INTERVALS_US):
            raise ValueError(
                "ul_guard_interval_us must be 1.6 or 3.2 (HE TB PPDU, IEEE 802.11ax-2021 "
                f"9.3.1.22), got {self.ul_guard_interval_us!r}"
            )
        if isinstance(self.spatial_streams, bool) or self.spatial_streams not in (1, 2):
            raise ValueError(f"spatial_streams must be 1 or 2, got {self.spatial_streams!r}")

    @property
    def symbol_us(self) -> float:
        """Downlink HE data symbol duration ``12.8 us + GI``."""
        return SYMBOL_DFT_US + self.guard_interval_us

    @property
    def ul_symbol_us(self) -> float:
        """Uplink (HE TB PPDU) data symbol duration ``12.8 us + UL GI``."""
        return SYMBOL_DFT_US + self.ul_guard_interval_us

    @property
    def dl_ltf_us(self) -> float:
        """HE-LTFs of an HE MU PPDU: one symbol per stream (27.3.11.10, ``N_HE-LTF = N_SS``)."""
        return self.spatial_streams * he_ltf_symbol_us(self.guard_interval_us, trigger_based=False)

    @property
    def ul_ltf_us(self) -> float:
        """HE-LTFs of an HE TB PPDU: one symbol per stream."""
        return self.spatial_streams * he_ltf_symbol_us(
            self.ul_guard_interval_us, trigger_based=True
        )

    @property
    def plan(self) -> RuPlan:
        return ru_plan(self.bandwidth_mhz)

    def bits_per_subcarrier_symbol(self, mcs: int | NDArray) -> NDArray[np.float64]:
        """Information bits per data subcarrier per HE symbol: ``N_BPSCS * R * N_SS``."""
        table = np.array([m.bits_per_data_subcarrier for m in MCS_TABLE])
        return table[np.asarray(mcs, dtype=int)] * self.spatial_streams

    def rate_table(self) -> list[dict[str, float | int | str]]:
        """Rate of every (RU size, MCS) of this channel at the DL and UL GI, Mb/s ([rate])."""
        rows: list[dict[str, float | int | str]] = []
        for tones in self.plan.sizes:
            for m in MCS_TABLE:
                rate, ul_rate = (
                    data_rate_mbps(
                        tones,
                        m.index,
                        spatial_streams=self.spatial_streams,
                        guard_interval_us=gi,
                    )
                    for gi in (self.guard_interval_us, self.ul_guard_interval_us)
                )
                rows.append(
                    {
                        "ru_tones": tones,
                        "data_subcarriers": DATA_SUBCARRIERS[tones],
                        "ru_count": self.plan.count(tones),
                        "mcs": m.index,
                        "modulation": m.modulation,
                        "code_rate": round(m.code_rate, 4),
                        "rate_mbps": round(rate, 4),
                        "ul_rate_mbps": round(ul_rate, 4),
                    }
                )
        return rows
