"""Per-station channel, packet error rate per MCS, and link adaptation to a delivery target.

SNR ([snr])
----------------
``SNR_i = P_tx - PL(d_i) + 10 log10 g_i - N``, with the TGax indoor path loss (IEEE
802.11-14/0980r16, models B-D) ``PL(d) = 40.05 + 20 log10(f_c / 2.4 GHz) + 20 log10(min(d,
d_bp)) + 35 log10(max(d / d_bp, 1))`` plus a fixed wall/clutter loss, noise ``N = -174 dBm/Hz
+ 10 log10(B) + NF`` over the channel width, and a block-fading power gain ``g_i`` drawn once
per coherence block from a Rician distribution of factor ``K`` (``K = 0``: Rayleigh; ``K =
inf``: no fading), seeded. The SNR per subcarrier is taken to be the same on every RU (the AP
spreads its power evenly; an uplink station's power concentration on a small RU is ignored,
which is conservative).

PER ([per])
----------------
For a PSDU of ``L_ref = 4096`` bytes the PER of MCS ``m`` is a logistic fit of an AWGN
waterfall, ``PER_m(s) = 1 / (1 + exp(a (s - s50_m)))``, placed so that ``PER = 10 %`` at the
SNR implied by the standard's minimum receiver sensitivity (IEEE 802.11ax-2021 Table 27-51,
20 MHz: -82, -79, -77, -74, -70, -66, -65, -64, -59, -57, -54, -52 dBm for MCS 0-11, which are
specified at 10 % PER for 4096-byte PSDUs) over the standard's reference noise floor -174 +
10 log10(20 MHz) + 10 dB = -91 dBm. These thresholds (9 ... 39 dB) include the standard's
implementation margin. A frame of ``L`` bytes is delivered with ``(1 - PER_m)^(L / L_ref)``.

Link adaptation
---------------
Each hop (UL camera frame, DL state frame) uses the highest MCS whose frame delivery
probability is at least ``sqrt(q0)``, so the two hops together deliver at least ``q0``; if none
reaches it, MCS 0. ``q0`` here is the *target* of link adaptation only: ``eq_drop`` divides by
the delivery the chosen MCS actually achieves in the block
(:attr:`codesign_mb.wifi.cell.ChannelProcess.delivery`), which is ``q0`` or more, or less when
even MCS 0 misses the target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from codesign_mb.core.config import FloatOrInf

__all__ = [
    "PER_REFERENCE_BYTES",
    "SENSITIVITY_20MHZ_DBM",
    "SNR_THRESHOLDS_DB",
    "ChannelConfig",
    "choose_mcs",
    "frame_delivery_probability",
    "packet_error_rate",
]

SENSITIVITY_20MHZ_DBM = (-82, -79, -77, -74, -70, -66, -65, -64, -59, -57, -54, -52)
"""Minimum receiver sensitivity, 20 MHz, MCS 0-11 (IEEE 802.11ax-2021 Table 27-51)."""

_REFERENCE_NOISE_DBM = -174.0 + 10.0 * math.log10(20e6) + 10.0
SNR_THRESHOLDS_DB = tuple(s - _REFERENCE_NOISE_DBM for s in SENSITIVITY_20MHZ_DBM)
"""SNR at which each MCS has 10 % PER on a 4096-byte PSDU ([per]), in dB."""

PER_REFERENCE_BYTES = 4096


def packet_error_rate(
    mcs: int | NDArray, snr_db: float | NDArray, *, slope_per_db: float = 2.0
) -> NDArray[np.float64]:
    """PER of a 4096-byte PSDU at ``snr_db`` ([per]), broadcast over ``mcs`` and SNR.

    Examples
    --------
    >>> float(packet_error_rate(0, SNR_THRESHOLDS_DB[0])).__round__(3)
    0.1
    """
    thresholds = np.asarray(SNR_THRESHOLDS_DB)[np.asarray(mcs, dtype=int)]
    snr50 = thresholds - math.log(9.0) / slope_per_db  # PER(threshold) = 0.1
    z = np.clip(slope_per_db * (np.asarray(snr_db, dtype=float) - snr50), -700.0, 700.0)
    return 1.0 / (1.0 + np.exp(z))


def frame_delivery_probability(
    mcs: int | NDArray,
    snr_db: float | NDArray,
    frame_bytes: float,
    *,
    slope_per_db: float = 2.0,
) -> NDArray[np.float64]:
    """Probability that a frame of ``frame_bytes`` is received: ``(1 - PER)^(L / L_ref)``."""
    per = packet_error_rate(mcs, snr_db, slope_per_db=slope_per_db)
    return np.power(1.0 - per, frame_bytes / PER_REFERENCE_BYTES)


def choose_mcs(
    snr_db: float | NDArray,
    target: float,
    frame_bytes: float,
    *,
    slope_per_db: float = 2.0,
    max_mcs: int = 11,
) -> NDArray[np.int64]:
    """Highest MCS <= ``max_mcs`` whose frame delivery probability is >= ``target`` (else 0)."""
    snr = np.atleast_1d(np.asarray(snr_db, dtype=float))
    mcs = np.arange(max_mcs + 1)
    ok = (
        frame_delivery_probability(
            mcs[None, :], snr[:, None], frame_bytes, slope_per_db=slope_per_db
        )
        >= target
    )
    best = np.where(ok.any(axis=1), max_mcs - np.argmax(ok[:, ::-1], axis=1), 0)
    return best.reshape(np.shape(snr_db)).astype(np.int64)


@dataclass(frozen=True)
class ChannelConfig:
    """Link budget, geometry, fading and link adaptation of every station.

    Parameters
    ----------
    carrier_ghz:
        Carrier frequency (5 GHz band: e.g. 5.5).
    ap_tx_power_dbm, sta_tx_power_dbm:
        Transmit power of the AP (downlink) and of the stations (uplink).
    noise_figure_db:
        Receiver noise figure.
    breakpoint_m:
        TGax breakpoint distance ``d_bp``.
    extra_loss_db:
        Fixed extra loss (walls, machinery, body) on every link.
    distances_m:
        Distance of each station to the AP; stations beyond the tuple (or all, when empty)
        are placed uniformly at random in ``distance_range_m`` (seeded).
    distance_range_m:
        ``(min, max)`` for the random placement.
    rician_k_db:
        Rician K factor of the block fading in dB; ``None`` = Rayleigh, ``inf`` = no fading.
    coherence_ms:
        Block-fading coherence time: one gain per station and block.
    per_slope_per_db:
        Slope ``a`` of the logistic PER curves ([per]).
    q0:
        Link adaptation's delivery target, end to end (UL then DL): each hop's MCS is the
        highest whose delivery is at least ``sqrt(q0)``. Unused with ``fixed_mcs``. It is not
        ``eq_drop``'s divisor, which is the delivery the chosen MCS achieves
        (:attr:`codesign_mb.wifi.cell.ChannelProcess.delivery`).
    fixed_mcs:
        If set, every station uses this MCS (no link adaptation); the delivery probability
        still follows from the SNR.
    max_mcs:
        Highest MCS link adaptation may pick.
    """

    carrier_ghz: float = 5.5
    ap_tx_power_dbm: float = 20.0
    sta_tx_power_dbm: float = 17.0
    noise_figure_db: float = 7.0
    breakpoint_m: float = 10.0
    extra_loss_db: float = 10.0
    distances_m: tuple[float, ...] = ()
    distance_range_m: tuple[float, float] = (5.0, 30.0)
    rician_k_db: FloatOrInf | None = 6.0
    coherence_ms: float = 40.0
    per_slope_per_db: float = 2.0
    q0: float = 0.95
    fixed_mcs: int | None = None
    max_mcs: int = 11

    def __post_init__(self) -> None:
        for name in ("carrier_ghz", "breakpoint_m", "coherence_ms", "per_slope_per_db"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        for name in ("ap_tx_power_dbm", "sta_tx_power_dbm", "noise_figure_db", "extra_loss_db"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value)):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        object.__setattr__(self, "distances_m", tuple(float(d) for d in self.distances_m))
        if any(not (math.isfinite(d) and d > 0) for d in self.distances_m):
            raise ValueError(f"distances_m must all be > 0, got {self.distances_m!r}")
        lo, hi = (float(x) for x in self.distance_range_m)
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise ValueError(
                f"distance_range_m must be (min, max) with 0 < min <= max, "
                f"got {self.distance_range_m!r}"
            )
        object.__setattr__(self, "distance_range_m", (lo, hi))
        if self.rician_k_db is not None and math.isnan(self.rician_k_db):
            raise ValueError("rician_k_db must be a number, inf or None, got nan")
        if not (isinstance(self.q0, int | float) and 0.0 < self.q0 <= 1.0):
            raise ValueError(f"q0 must be in (0, 1], got {self.q0!r}")
        if not (isinstance(self.max_mcs, int) and 0 <= self.max_mcs <= 11):
            raise ValueError(f"max_mcs must be an integer in [0, 11], got {self.max_mcs!r}")
        if self.fixed_mcs is not None and not (
            isinstance(self.fixed_mcs, int) and 0 <= self.fixed_mcs <= 11
        ):
            raise ValueError(
                f"fixed_mcs must be an integer in [0, 11] or None, got {self.fixed_mcs!r}"
            )

    def path_loss_db(self, distance_m: NDArray | float) -> NDArray[np.float64]:
        """TGax indoor path loss plus :attr:`extra_loss_db` ([snr])."""
        d = np.maximum(np.asarray(distance_m, dtype=float), 1.0)
        near = np.minimum(d, self.breakpoint_m)
        far = np.maximum(d / self.breakpoint_m, 1.0)
        return (
            40.05
            + 20.0 * math.log10(self.carrier_ghz / 2.4)
            + 20.0 * np.log10(near)
            + 35.0 * np.log10(far)
            + self.extra_loss_db
        )

    def noise_dbm(self, bandwidth_mhz: float) -> float:
        """Thermal noise over the channel plus the noise figure."""
        return -174.0 + 10.0 * math.log10(bandwidth_mhz * 1e6) + self.noise_figure_db

    def place(self, n_stations: int, rng: np.random.Generator) -> NDArray[np.float64]:
        """Distances of ``n_stations`` stations: :attr:`distances_m`, then random ones."""
        given = np.asarray(self.distances_m[:n_stations], dtype=float)
        extra = rng.uniform(*self.distance_range_m, size=n_stations - given.size)
        return np.concatenate([given, extra])

    def fading_gain(self, shape: tuple[int, ...], rng: np.random.Generator) -> NDArray[np.float64]:
        """Block-fading power gains ``|h|^2`` (mean 1), Rician with factor :attr:`rician_k_db`."""
        # Draw the same number of normals whatever K is, so streams stay aligned across configs.
        re = rng.standard_normal(shape)
        im = rng.standard_normal(shape)
        if self.rician_k_db is not None and math.isinf(self.rician_k_db):
            return np.ones(shape)
        k = 0.0 if self.rician_k_db is None else 10.0 ** (self.rician_k_db / 10.0)
        los = math.sqrt(k / (k + 1.0))
        scatter = math.sqrt(1.0 / (2.0 * (k + 1.0)))
        return (los + scatter * re) ** 2 + (scatter * im) ** 2

    def snr_db(
        self, distance_m: NDArray, gain: NDArray, bandwidth_mhz: float, *, uplink: bool
    ) -> NDArray[np.float64]:
        """[snr] for the uplink (station power) or the downlink (AP power)."""
        power = self.sta_tx_power_dbm if uplink else self.ap_tx_power_dbm
        return (
            power
            - self.path_loss_db(distance_m)
            + 10.0 * np.log10(np.maximum(gain, 1e-12))
            - self.noise_dbm(bandwidth_mhz)
        )

    def adapt(self, snr_db: NDArray, frame_bytes: float) -> tuple[NDArray[np.int64], NDArray]:
        """MCS per station for one hop and its frame delivery probability (hop target sqrt(q0))."""
        if self.fixed_mcs is not None:
            mcs = np.full(np.shape(snr_db), self.fixed_mcs, dtype=np.int64)
        else:
            mcs = choose_mcs(
                snr_db,
                math.sqrt(self.q0),
                frame_bytes,
                slope_per_db=self.per_slope_per_db,
                max_mcs=self.max_mcs,
            )
        pdr = frame_delivery_probability(
            mcs, snr_db, frame_bytes, slope_per_db=self.per_slope_per_db
        )
        return mcs, pdr
