"""Static QoS: the paper's baseline policy (the interface, :class:`QosPolicy`, is the network's)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from codesign_mb.network.qos import QosPolicy, QosRequest

__all__ = ["QosPolicy", "StaticQos"]


@dataclass(frozen=True)
class StaticQos:
    """The same QoS for every packet: the paper's "static QoS" baseline."""

    reliability: float = 1.0
    latency_steps: int = 0

    def __post_init__(self) -> None:
        # Validates both fields; the request is immutable, so every packet can share it.
        object.__setattr__(self, "_request", QosRequest(self.reliability, self.latency_steps))

    def reset(self, *, seed: int | None = None) -> None:
        return None

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        return self._request  # type: ignore[attr-defined]
