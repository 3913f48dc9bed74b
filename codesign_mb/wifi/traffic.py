"""Robot traffic (paper Table II, ``tab_network``) and probabilistic frame dropping (``eq_drop``).

Every control step (40 ms) robot ``i`` captures one uplink camera frame (13,500 bytes) at
``t * period + offset_i``; the edge turns it into one downlink state frame (32 bytes). Both
must arrive before the robot reads its observation at step ``t + tau`` (its latency request),
i.e. by ``capture + tau * period`` ([deadline]): a state reaches the robot only if its
camera frame and then its state frame arrive in time. Before the queue, a frame is dropped with
probability ``1 - q / q0`` (``eq_drop``), so that with a link-level delivery ``q0`` the frame is
delivered with probability ``q``; in the cell (:class:`codesign_mb.wifi.cell.SharedChannel`)
``q0`` is each station's own delivery in the current coherence block.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["CAPTURE_MODES", "TrafficConfig", "drop_probability"]

CAPTURE_MODES = ("staggered", "synchronised")


def drop_probability(reliability: float, q0: float) -> float:
    """``eq_drop``: ``1 - q / q0``, clipped to [0, 1] (``q >= q0`` is never dropped).

    ``q0`` is the link-level delivery probability of the frame (its UL and DL hops), in (0, 1].
    """
    if not 0.0 < q0 <= 1.0:
        raise ValueError(f"q0 must be in (0, 1], got {q0!r}")
    return min(1.0, max(0.0, 1.0 - reliability / q0))


@dataclass(frozen=True)
class TrafficConfig:
    """Per-robot traffic (paper Table II).

    Parameters
    ----------
    ul_frame_bytes:
        Uplink camera frame (13,500 bytes).
    dl_frame_bytes:
        Downlink state frame (32 bytes).
    period_ms:
        Frame period = control step (40 ms); a multiple of the schedule tick.
    capture:
        ``"staggered"``: robot ``i`` of ``n`` captures at offset ``floor(i * period / n)``;
        ``"synchronised"``: all at offset 0.
    edge_processing_ms:
        Time from the camera frame's arrival at the AP to its state frame being queued, on
        top of the one tick the AP needs to see the arrival.
    """

    ul_frame_bytes: int = 13_500
    dl_frame_bytes: int = 32
    period_ms: float = 40.0
    capture: str = "staggered"
    edge_processing_ms: float = 0.0

    def __post_init__(self) -> None:
        for name in ("ul_frame_bytes", "dl_frame_bytes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not (isinstance(self.period_ms, int | float) and self.period_ms > 0):
            raise ValueError(f"period_ms must be > 0, got {self.period_ms!r}")
        if self.capture not in CAPTURE_MODES:
            raise ValueError(f"capture must be one of {CAPTURE_MODES}, got {self.capture!r}")
        if not (isinstance(self.edge_processing_ms, int | float) and self.edge_processing_ms >= 0):
            raise ValueError(f"edge_processing_ms must be >= 0, got {self.edge_processing_ms!r}")

    def period_ticks(self, tick_us: float) -> int:
        """Frame period in schedule ticks (must be a whole number)."""
        ticks = self.period_ms * 1000.0 / tick_us
        if abs(ticks - round(ticks)) > 1e-9 or round(ticks) < 1:
            raise ValueError(
                f"period_ms must be a whole number of ticks of {tick_us} us, got {self.period_ms}"
            )
        return round(ticks)

    def processing_ticks(self, tick_us: float) -> int:
        """Edge processing time in whole ticks (rounded up)."""
        return math.ceil(self.edge_processing_ms * 1000.0 / tick_us - 1e-9)

    def offsets_ticks(self, n_stations: int, tick_us: float) -> NDArray[np.int64]:
        """Capture offset of each robot within the period, in ticks."""
        period = self.period_ticks(tick_us)
        if self.capture == "synchronised":
            return np.zeros(n_stations, dtype=np.int64)
        return (np.arange(n_stations) * period) // max(n_stations, 1)
