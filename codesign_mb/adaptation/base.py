"""The QoS policy interface ``pi_q, pi_tau`` (``eq_q_pol``, ``eq_t_pol``) and static QoS."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from codesign_mb.network.qos import QosRequest

__all__ = ["QosPolicy", "StaticQos"]


@runtime_checkable
class QosPolicy(Protocol):
    """Chooses the QoS of the packet sent at ``t`` from what was held at ``t - 1``.

    ``(q_t, tau_t) = pi(y_{t-1}, zeta_{t-1})`` (``eq_q_pol``, ``eq_t_pol``). The policy runs at
    the edge: it sees the remote observation and its age, not the robot's estimate.
    """

    def reset(self, *, seed: int | None = None) -> None:
        """Start an episode."""
        ...

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        """QoS for the next packet, given ``y_{t-1}`` and ``zeta_{t-1}``."""
        ...


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
