"""Static, random and scheduled QoS: the paper's baseline, the reference that sends at random,
and a fixed schedule (the clairvoyant search replays one).

The interface, :class:`QosPolicy`, is the network's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from codesign_mb.network.qos import QosPolicy, QosRequest

__all__ = ["QosPolicy", "RandomQos", "ScheduledQos", "StaticQos"]


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


class RandomQos:
    """Send each packet with probability ``probability``, blind to the data: a reference.

    Each request is ``q = 1`` with probability ``p`` and ``q = 0`` otherwise, drawn
    independently per step, so the mean requested reliability is ``p``: the same network
    budget as a co-design policy whose average PDR is ``p``, spent without choosing *when*.
    The draws come from the generator seeded by ``reset(seed=)``; ``reset()`` without a seed
    continues the stream (an unseeded policy draws from fresh OS entropy).

    Parameters
    ----------
    probability:
        ``p`` in [0, 1], the chance that a packet is requested at all.
    latency_steps:
        The latency ``tau`` of every request (control steps; 1 is the paper's link).

    Examples
    --------
    >>> policy = RandomQos(probability=0.25)
    >>> policy.reset(seed=0)
    >>> [policy.request(np.zeros(3), 0).reliability for _ in range(6)]
    [0.0, 0.0, 1.0, 1.0, 0.0, 0.0]
    """

    def __init__(self, probability: float, latency_steps: int = 1) -> None:
        p = float(probability)
        if not 0.0 <= p <= 1.0:  # also rejects NaN
            raise ValueError(f"probability must be in [0, 1], got {probability!r}")
        self.probability = p
        self._send = QosRequest(1.0, latency_steps)  # validates latency_steps
        self._skip = QosRequest(0.0, latency_steps)
        self.latency_steps = self._send.latency_steps
        self._rng = np.random.default_rng()

    def __repr__(self) -> str:
        return f"RandomQos(probability={self.probability!r}, latency_steps={self.latency_steps})"

    def reset(self, *, seed: int | None = None) -> None:
        if seed is not None:
            self._rng = np.random.default_rng(seed)

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        return self._send if self._rng.random() < self.probability else self._skip


class ScheduledQos:
    """Ask ``q = 1`` at the given steps of the episode and ``q = 0`` at every other: open loop.

    A schedule found offline (:mod:`codesign_mb.evaluation.clairvoyant`) replays exactly: the
    ``k``-th request of an episode is step ``k`` (``reset`` starts the count again).

    Parameters
    ----------
    steps:
        The steps that ask for a packet (integers >= 0).
    latency_steps:
        The latency ``tau`` of every request.

    Examples
    --------
    >>> policy = ScheduledQos(steps=(1, 3))
    >>> policy.reset()
    >>> [policy.request(np.zeros(3), 0).reliability for _ in range(5)]
    [0.0, 1.0, 0.0, 1.0, 0.0]
    """

    def __init__(self, steps: tuple[int, ...] | list[int] = (), latency_steps: int = 1) -> None:
        chosen = tuple(steps)
        if any(isinstance(t, bool) or not isinstance(t, (int, np.integer)) for t in chosen):
            raise TypeError(f"steps must be integers, got {chosen!r}")
        if any(t < 0 for t in chosen):
            raise ValueError(f"steps must be >= 0, got {chosen!r}")
        self.steps = frozenset(int(t) for t in chosen)
        self._send = QosRequest(1.0, latency_steps)  # validates latency_steps
        self._skip = QosRequest(0.0, latency_steps)
        self.latency_steps = self._send.latency_steps
        self._t = 0

    def __repr__(self) -> str:
        return f"ScheduledQos(steps={sorted(self.steps)!r}, latency_steps={self.latency_steps})"

    def reset(self, *, seed: int | None = None) -> None:
        self._t = 0

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        t, self._t = self._t, self._t + 1
        return self._send if t in self.steps else self._skip
