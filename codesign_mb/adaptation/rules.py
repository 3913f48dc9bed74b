"""Model-based QoS rules: ask for a packet only when the robot's prediction needs one.

No learning: the rule runs, at the edge, a replica of the robot's
:class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor`, fed with the same
``(y_{t-1}, zeta_{t-1})`` stream the robot receives (``eq_q_pol``), so it knows the robot's
error covariance exactly: for a Kalman filter ``P`` depends on the delivery pattern only, not
on the data. The packet sent at ``t`` is requested with high reliability when the predicted
position uncertainty at ``t`` exceeds a threshold, with low reliability otherwise, and with
the lift reliability once the object is seen lifted off the belt (the grasp is done; the
paper's learned policy likewise drops to a fixed low value after the lift, ``fig_lat``).

:func:`tune_threshold` finds, by bisection, the largest threshold (the least network) that
still meets a success constraint.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.network.qos import QosRequest

__all__ = ["CovarianceTriggeredQos", "ThresholdSearch", "tune_threshold"]


@dataclass
class CovarianceTriggeredQos:
    """High reliability when the predicted object position std exceeds ``std_threshold_m``.

    Parameters
    ----------
    predictor:
        The replica: a predictor built like the robot's (same model and settings), reset by
        the rule at every episode.
    std_threshold_m:
        Trigger: request ``high_reliability`` when ``sqrt(trace P_oo)`` predicted for the
        packet's step exceeds this (m).
    high_reliability, low_reliability:
        ``q`` when triggered / not triggered.
    lifted_reliability:
        ``q`` once the held observation shows the object ``lift_height_m`` above the belt.
    latency_steps:
        ``tau`` of every request (the paper fixes one step).
    belt_height_m:
        Height of the object's centre resting on the belt (from the plant's prior).
    """

    predictor: Any
    std_threshold_m: float = 0.01
    high_reliability: float = 1.0
    low_reliability: float = 0.0
    lifted_reliability: float = 0.0
    latency_steps: int = 1
    lift_height_m: float = 0.03
    belt_height_m: float | None = None
    _calls: int = field(init=False, default=0, repr=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.std_threshold_m) and self.std_threshold_m > 0):
            raise ValueError(f"std_threshold_m must be > 0, got {self.std_threshold_m}")
        for name in ("high_reliability", "low_reliability", "lifted_reliability"):
            q = getattr(self, name)
            if not (math.isfinite(q) and 0.0 <= q <= 1.0):
                raise ValueError(f"{name} must be in [0, 1], got {q!r}")
        QosRequest(self.high_reliability, self.latency_steps)  # validates latency_steps
        if self.lift_height_m <= 0:
            raise ValueError(f"lift_height_m must be > 0, got {self.lift_height_m}")

    @classmethod
    def from_env(cls, env: Any, **options: Any) -> CovarianceTriggeredQos:
        """For a conveyor env: the replica predictor of ``env`` and its belt height."""
        from codesign_mb.estimation.predictor import DelayCompensatingPredictor

        predictor = DelayCompensatingPredictor.from_env(env, **(options.pop("predictor", {}) or {}))
        options.setdefault("belt_height_m", float(np.asarray(env.unwrapped.remote_prior())[2]))
        return cls(predictor, **options)

    def reset(self, *, seed: int | None = None) -> None:
        self._calls = 0

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        y = np.asarray(observation, dtype=float)
        if self._calls == 0:
            # The packet x_0: the robot holds only the prior (stamped t = -1).
            P = self.predictor.prior_covariance
        else:
            # The replica's clock is the robot's: (y_{t-1}, zeta_{t-1}) is its step t - 1.
            networked = self._networked(y, age)
            if self._calls == 1:
                self.predictor.reset(networked)
            else:
                self.predictor.estimate(networked, np.zeros(0))
            P = self.predictor.covariance
        self._calls += 1
        if self._lifted(y):
            return QosRequest(self.lifted_reliability, self.latency_steps)
        A, Q = self.predictor.A, self.predictor.Q
        P_next = A @ P @ A.T + Q  # the robot's prior for the step this packet is sent at
        std = math.sqrt(max(float(np.trace(P_next[:3, :3])), 0.0))
        q = self.high_reliability if std > self.std_threshold_m else self.low_reliability
        return QosRequest(q, self.latency_steps)

    def _networked(self, y: NDArray[np.float64], age: int) -> NDArray[np.float64]:
        """A plant-layout observation holding ``y`` in its remote part, then the age."""
        layout = self.predictor.layout
        size = max(s.stop for s in layout.values())
        obs = np.zeros(size + 1)
        remote = _remote_slice(layout)
        obs[remote] = y
        obs[-1] = age
        return obs

    def _lifted(self, y: NDArray[np.float64]) -> bool:
        if self.belt_height_m is None:
            return False
        return bool(y[2] - self.belt_height_m >= self.lift_height_m)


def _remote_slice(layout: dict[str, slice]) -> slice:
    names = [n for n in ("object_pos", "object_vel") if n in layout]
    return slice(layout[names[0]].start, layout[names[-1]].stop)


@dataclass(frozen=True)
class ThresholdSearch:
    """One bisection probe: the threshold, the measured success rate and mean reliability."""

    threshold: float
    success_rate: float
    mean_reliability: float


def tune_threshold(
    measure: Callable[[float], tuple[float, float]],
    *,
    target_success: float,
    low: float,
    high: float,
    iterations: int = 6,
) -> tuple[float, list[ThresholdSearch]]:
    """Largest threshold in ``[low, high]`` whose success rate is at least ``target_success``.

    ``measure(threshold) -> (success_rate, mean_reliability)`` runs an evaluation. Success is
    assumed to fall as the threshold grows (fewer packets); bisection on a log scale, since
    thresholds span decades. Returns the best feasible threshold (``low`` if none probed was
    feasible) and every probe made.
    """
    if not 0.0 < low < high:
        raise ValueError(f"need 0 < low < high, got low={low}, high={high}")
    if not 0.0 <= target_success <= 1.0:
        raise ValueError(f"target_success must be in [0, 1], got {target_success}")
    probes: list[ThresholdSearch] = []
    best = low
    lo, hi = math.log(low), math.log(high)
    for _ in range(iterations):
        mid = math.exp((lo + hi) / 2)
        success, reliability = measure(mid)
        probes.append(ThresholdSearch(mid, success, reliability))
        if success >= target_success:
            best, lo = mid, math.log(mid)
        else:
            hi = math.log(mid)
    return best, probes
