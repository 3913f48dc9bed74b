"""The abstract wireless link of paper.tex sec. 2: Bernoulli loss, latency and age.

A packet carrying the state ``x_t`` is sent at step ``t`` with a :class:`QosRequest`
``(q_t, tau_t)``; it is delivered with probability ``q_t`` (``eq_d``) and arrives at
``t + tau_t``. The receiver keeps the freshest packet that has arrived, so the age is
``zeta_t = t - max{t' <= t : t' + tau_t' <= t, delta_t' = 1}`` (``eq_time``) and the
observation is ``y_t = x_{t - zeta_t}`` (``eq_output``). A packet that arrives after a fresher
one does not change ``y_t``; it is still reported in :attr:`Reception.arrivals`, so an
estimator can use out-of-sequence data.

Before any delivery the receiver holds the *prior* given to :meth:`Link.reset`, stamped
``t = -1``: the age is ``t + 1``, the number of steps since the episode started.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.network.qos import QosRequest

__all__ = [
    "PRIOR_TIMESTAMP",
    "BernoulliLink",
    "Link",
    "ObservationBuffer",
    "Packet",
    "Reception",
]

PRIOR_TIMESTAMP = -1
"""Timestamp of the prior observation held before the first delivery."""


@dataclass(frozen=True, slots=True)
class Packet:
    """A state packet: the value ``x_t`` stamped with its capture step ``t``."""

    timestamp: int
    value: NDArray[np.float64]

    def __post_init__(self) -> None:
        stamp = self.timestamp
        if isinstance(stamp, bool) or not isinstance(stamp, (int, np.integer)):
            raise TypeError(f"Packet timestamp must be an integer step, got {stamp!r}")
        if not isinstance(self.value, np.ndarray):  # the link's own packets already are
            try:
                value = np.array(self.value, dtype=float)
            except (TypeError, ValueError):
                raise TypeError(f"Packet value must be numbers, got {self.value!r}") from None
            object.__setattr__(self, "value", value)


@dataclass(frozen=True, slots=True)
class Reception:
    """What the receiver holds after step ``t``.

    Attributes
    ----------
    t:
        The current step.
    observation:
        ``y_t = x_{t - zeta_t}`` (``eq_output``), a copy of the freshest delivered packet.
    age:
        ``zeta_t`` (``eq_time``), in steps; ``t + 1`` before the first delivery.
    delivered:
        ``delta_t``: whether the packet sent at ``t`` survived the channel (it may arrive later).
    arrivals:
        Every packet that arrived at ``t``, fresher or not, in timestamp order.
    """

    t: int
    observation: NDArray[np.float64]
    age: int
    delivered: bool
    arrivals: tuple[Packet, ...] = ()

    @property
    def timestamp(self) -> int:
        """Capture step of :attr:`observation`: ``t - zeta_t``."""
        return self.t - self.age

    @property
    def fresh(self) -> bool:
        """Whether :attr:`observation` changed at this step."""
        return any(p.timestamp == self.timestamp for p in self.arrivals)


@runtime_checkable
class Link(Protocol):
    """A unidirectional state link, stepped once per control period.

    Implementations: :class:`BernoulliLink` (the paper's abstract link) and the WiFi 6
    simulator's per-station link (``codesign_mb.wifi``).
    """

    def reset(self, *, seed: int | None = None, prior: ArrayLike | None = None) -> None:
        """Start an episode at ``t = 0``; ``prior`` is held until the first delivery."""
        ...

    def step(self, state: ArrayLike, qos: QosRequest) -> Reception:
        """Send ``x_t`` with ``qos``, advance the channel by one step, return what is held."""
        ...


class ObservationBuffer:
    """The receiver side: packets in flight and the freshest one delivered (``eq_time``).

    Works for states of any shape; values are copied on the way in and out.
    """

    def __init__(self, prior: ArrayLike | None = None) -> None:
        self._in_flight: list[tuple[int, int, int, Packet]] = []
        self._seq = 0
        self._latest: Packet | None = None
        if prior is not None:
            try:
                held = np.array(prior, dtype=float)
            except (TypeError, ValueError):
                raise TypeError(f"prior must be numbers, got {prior!r}") from None
            if not np.all(np.isfinite(held)):
                raise ValueError(f"prior must be finite, got {prior!r}")
            self._latest = Packet(PRIOR_TIMESTAMP, held)

    @property
    def latest(self) -> Packet | None:
        """The freshest packet held, or ``None`` when there is no prior and nothing arrived."""
        return self._latest

    @property
    def in_flight(self) -> int:
        """Number of delivered packets that have not arrived yet."""
        return len(self._in_flight)

    def push(self, packet: Packet, arrival_step: int) -> None:
        """Schedule a delivered packet to arrive at ``arrival_step``."""
        if arrival_step < packet.timestamp:
            raise ValueError(
                f"arrival_step must be >= the packet timestamp {packet.timestamp}, "
                f"got {arrival_step}"
            )
        self._schedule(Packet(packet.timestamp, np.array(packet.value, dtype=float)), arrival_step)

    def _schedule(self, packet: Packet, arrival_step: int) -> None:
        """:meth:`push` of a packet whose value the buffer may keep (no copy, no check)."""
        heapq.heappush(self._in_flight, (arrival_step, packet.timestamp, self._seq, packet))
        self._seq += 1

    def receive(self, t: int, *, delivered: bool, like: NDArray[np.float64]) -> Reception:
        """Deliver every packet due by ``t``, keep the freshest (the max in ``eq_time``).

        ``delivered`` is the fate of the packet sent at ``t``; ``like`` gives the shape of the
        zero observation returned when there is neither a prior nor a delivery yet.
        """
        arrived: list[Packet] = []
        while self._in_flight and self._in_flight[0][0] <= t:
            arrived.append(heapq.heappop(self._in_flight)[3])
        if len(arrived) > 1:
            arrived.sort(key=lambda p: p.timestamp)
        for packet in arrived:
            if self._latest is None or packet.timestamp > self._latest.timestamp:
                self._latest = packet
        latest = self._latest or Packet(PRIOR_TIMESTAMP, np.zeros_like(like, dtype=float))
        return Reception(
            t=t,
            observation=latest.value.copy(),
            age=t - latest.timestamp,  # eq_time
            delivered=delivered,
            arrivals=tuple(arrived),
        )


@dataclass
class BernoulliLink:
    """The paper's link: ``delta_t ~ Bernoulli(q_t)`` (``eq_d``), arrival after ``tau_t`` steps.

    Parameters
    ----------
    seed:
        Seed of the link's own ``numpy.random.Generator``; :meth:`reset` may replace it.

    Examples
    --------
    >>> link = BernoulliLink(seed=0)
    >>> link.reset(prior=[0.0])
    >>> rx = link.step([1.0], QosRequest(reliability=1.0, latency_steps=0))
    >>> (rx.observation.tolist(), rx.age)
    ([1.0], 0)
    """

    seed: int | None = None
    _rng: np.random.Generator = field(init=False, repr=False)
    _buffer: ObservationBuffer = field(init=False, repr=False)
    _t: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        _check_seed(self.seed)
        self.reset(seed=self.seed)

    @property
    def t(self) -> int:
        """The step the next :meth:`step` call sends at."""
        return self._t

    def reset(self, *, seed: int | None = None, prior: ArrayLike | None = None) -> None:
        _check_seed(seed)
        if seed is not None or not hasattr(self, "_rng"):
            self._rng = np.random.default_rng(seed if seed is not None else self.seed)
        self._buffer = ObservationBuffer(prior)
        self._t = 0

    def step(self, state: ArrayLike, qos: QosRequest) -> Reception:
        t = self._t
        value = np.array(state, dtype=float)
        # eq_d: one uniform draw per step, whatever q is, so streams stay aligned across policies.
        delivered = bool(self._rng.random() < qos.reliability)
        if delivered:  # value is this step's own copy: the buffer keeps it as it is
            self._buffer._schedule(Packet(t, value), t + qos.latency_steps)
        self._t = t + 1
        return self._buffer.receive(t, delivered=delivered, like=value)


def _check_seed(seed: Any) -> None:
    """A seed is ``None`` or a non-negative integer (not a bool: ``True`` is no seed)."""
    if seed is None:
        return
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed must be a non-negative integer or None, got {seed!r}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed!r}")
