"""QoS requests, their cost and the policy that chooses them (paper.tex sec. 3)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from codesign_mb.core.config import LATENCY_STEPS_CAP, check_range

__all__ = ["QosCost", "QosPolicy", "QosRequest", "reliability_cost"]


@dataclass(frozen=True, slots=True)
class QosRequest:
    """The QoS one state packet is sent with.

    Parameters
    ----------
    reliability:
        Delivery probability ``q`` in [0, 1] (``eq_d``); 0 means "do not send".
    latency_steps:
        Delivery latency ``tau`` in control steps (>= 0, capped at
        :data:`~codesign_mb.core.config.LATENCY_STEPS_CAP`); the packet stamped ``t`` arrives at
        ``t + tau`` when delivered (``eq_time``).
    """

    reliability: float
    latency_steps: int = 0

    def __post_init__(self) -> None:
        q = float(self.reliability)
        if not (math.isfinite(q) and 0.0 <= q <= 1.0):
            raise ValueError(f"reliability must be in [0, 1], got {self.reliability!r}")
        object.__setattr__(self, "reliability", q)
        tau = self.latency_steps
        if isinstance(tau, bool) or int(tau) != tau:
            raise ValueError(f"latency_steps must be an integer, got {tau!r}")
        if tau < 0:
            raise ValueError(f"latency_steps must be >= 0, got {tau!r}")
        if tau > LATENCY_STEPS_CAP.value:  # compared first: requests are made every step
            check_range("latency_steps", tau, cap=LATENCY_STEPS_CAP)
        object.__setattr__(self, "latency_steps", int(tau))


QosCost = Callable[[QosRequest], float]
"""The network cost ``C(q, tau)`` of serving one request (paper sec. 3)."""


def reliability_cost(qos: QosRequest) -> float:
    """The paper's cost ``C(q) = q`` (``eq_robot``): requested reliability, latency free."""
    if not isinstance(qos, QosRequest):
        raise TypeError(f"qos must be a QosRequest, got {qos!r}")
    return qos.reliability


@runtime_checkable
class QosPolicy(Protocol):
    """Chooses the QoS of the packet sent at ``t`` from what was held at ``t - 1``.

    ``(q_t, tau_t) = pi(y_{t-1}, zeta_{t-1})`` (``eq_q_pol``, ``eq_t_pol``). The policy sees the
    remote observation and its age; one that also reads the robot's estimate (a learned policy
    on the learned estimator's belief) has a ``bind_belief(estimator)`` method, which the closed
    loop calls with the robot's estimator: that policy runs with the robot.
    """

    def reset(self, *, seed: int | None = None) -> None:
        """Start an episode."""
        ...

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        """QoS for the next packet, given ``y_{t-1}`` and ``zeta_{t-1}``."""
        ...
