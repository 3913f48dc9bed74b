"""Model-based QoS rules: ask for a packet only when the robot's prediction needs one.

No learning. Both rules are :class:`~codesign_mb.network.qos.QosPolicy` objects: at step
``t`` they choose ``(q_t, tau_t)`` from what the robot holds, ``(y_{t-1}, zeta_{t-1})``
(``eq_q_pol``), at the edge.

:class:`AgeTriggeredQos`
    ``high`` reliability once the held state is ``max_age_steps`` old, ``low`` otherwise.
:class:`CovarianceTriggeredQos`
    The edge runs a replica of the robot's delay-compensating predictor
    (:class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor`) on exactly what the
    robot holds, so it knows the robot's error covariance ``P`` (for a Kalman filter ``P``
    depends on the delivery pattern, not on the data). It asks for ``high`` reliability when
    the object's position uncertainty ``sqrt(tr P_oo)``, predicted to the step the packet
    sent now is used at (``t + tau``) without that packet, exceeds ``threshold_m``; ``low``
    otherwise, and ``low`` once the object is lifted (the paper's learned policy likewise
    drops to a fixed low value after the lift, ``fig_lat``). With ``innovation_gate`` it
    also reads the data: a delivered packet the predictor did not expect (normalised
    innovation squared above the chi-square quantile: a belt stop, a speed step, a slip, a
    perception outlier) makes it ask ``high`` until a packet it expects arrives, so two
    episodes with different belt events get different request timelines.

:class:`PredictorReplica` is that replica (also what a learned QoS policy may be given, the
``predictor_std`` feature of :mod:`codesign_mb.adaptation.learned`).

:func:`tune_threshold` finds, by bisection, the largest threshold (the least network) that
still meets a success constraint.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from codesign_mb.network.qos import QosRequest

__all__ = [
    "AgeTriggeredQos",
    "CovarianceTriggeredQos",
    "PredictorReplica",
    "ThresholdSearch",
    "tune_threshold",
]


@dataclass(frozen=True)
class AgeTriggeredQos:
    """QoS rule: ``high`` reliability once ``age >= max_age_steps``, else ``low``."""

    low: float = 0.2
    high: float = 1.0
    max_age_steps: int = 3
    latency_steps: int = 1

    def __post_init__(self) -> None:
        QosRequest(self.low, self.latency_steps)
        QosRequest(self.high, self.latency_steps)
        if (
            isinstance(self.max_age_steps, bool)
            or not isinstance(self.max_age_steps, int)
            or (self.max_age_steps < 1)
        ):
            raise ValueError(f"max_age_steps must be an integer >= 1, got {self.max_age_steps!r}")

    def reset(self, *, seed: int | None = None) -> None:
        return None

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        q = self.high if age >= self.max_age_steps else self.low
        return QosRequest(q, self.latency_steps)


class PredictorReplica:
    """The robot's delay-compensating predictor, replicated at the edge from what it holds.

    What the model-based QoS rule (:class:`CovarianceTriggeredQos`) and the learned QoS
    policy's ``predictor_std`` feature
    (:class:`~codesign_mb.adaptation.learned.PredictorStdFeature`) know of the robot: fed,
    once per packet, exactly what the robot holds, its
    :class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor` has the robot's
    error covariance ``P`` one step behind (``P`` depends on the delivery pattern only).
    It also latches whether the held object has been lifted ``lift_margin_m`` above where it
    was first seen (a measurement, not the prior).

    Parameters
    ----------
    predictor:
        A fresh :class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor` with
        the robot's settings, on the *remote* layout (built by
        :func:`codesign_mb.rollout.compose.predictor_replica`; the replica only reads it
        through ``reset``/``estimate`` and its covariance model ``A``, ``Q``, ``P``).
    lift_margin_m:
        Height above the first held position that counts as lifted (``None``: never).
    """

    def __init__(self, predictor: Any, *, lift_margin_m: float | None = 0.03) -> None:
        if lift_margin_m is not None and not lift_margin_m > 0:
            raise ValueError(f"lift_margin_m must be > 0 or None, got {lift_margin_m!r}")
        self.lift_margin_m = lift_margin_m
        self.predictor = predictor
        self._pos = predictor._pos
        self.calls = 0
        self._start_z: float | None = None
        self.lifted = False
        self.nis = math.nan

    def reset(self) -> None:
        """Start an episode (the predictor restarts from the next held state)."""
        self.calls = 0
        self._start_z = None
        self.lifted = False
        self.nis = math.nan

    def observe(self, observation: NDArray[np.float64], age: int) -> None:
        """Take in ``(y_{t-1}, zeta_{t-1})``, what the robot held when packet ``t`` is sent."""
        calls, self.calls = self.calls, self.calls + 1
        held = np.asarray(observation, dtype=float)
        if calls == 0:  # t = 0: the robot holds the prior, nothing measured yet
            self._start_z = float(held[self._pos[2]])
            return
        wrapped = np.append(held, float(age))
        if calls == 1:
            self.predictor.reset(wrapped)
            self.nis = math.nan
        else:
            updates = self.predictor.updates
            self.predictor.estimate(wrapped, np.zeros(0))
            if self.predictor.updates > updates:  # a new packet: how surprising it was
                self.nis = self.predictor.last_nis
        if (  # the held state is a measurement (not the prior) of a lifted object
            self.lift_margin_m is not None
            and self._start_z is not None
            and age < calls
            and held[self._pos[2]] > self._start_z + self.lift_margin_m
        ):
            self.lifted = True

    @property
    def covariance(self) -> NDArray[np.float64]:
        """The robot's ``P`` at the latest held step (the prior's before anything is held)."""
        if self.calls < 2:  # the predictor starts from the second held state, (y_0, zeta_0)
            return self.predictor.prior_covariance
        return self.predictor.covariance

    def position_std_ahead(self, steps: int) -> float:
        """RMS position uncertainty ``steps`` steps after the latest held state, no new data."""
        P = self.covariance
        A, Q = self.predictor.A, self.predictor.Q
        for _ in range(steps):
            P = A @ P @ A.T + Q
        return float(math.sqrt(max(np.trace(P[:3, :3]), 0.0)))


class CovarianceTriggeredQos:
    """QoS rule: reliable delivery only when the robot's predictor is about to lose the object.

    Parameters
    ----------
    replica:
        The edge's :class:`PredictorReplica` of the robot's predictor
        (:func:`codesign_mb.rollout.compose.covariance_rule` builds the rule for a plant).
    threshold_m:
        Position uncertainty (RMS, m) above which a packet is asked for with ``high``.
    low, high:
        Reliabilities requested (``high`` also before anything has arrived).
    latency_steps:
        ``tau`` requested with every packet (>= 1 on WiFi).
    innovation_gate:
        Probability of the chi-square quantile above which a delivered packet's normalised
        innovation squared counts as a surprise (``None``: the covariance alone decides, the
        fixed timetable of a linear filter). After a surprise the rule asks ``high`` until a
        packet within the gate arrives.

    Examples
    --------
    >>> from codesign_mb.rollout.compose import covariance_rule_on
    >>> rule = covariance_rule_on({"object_pos": slice(0, 3)}, 0.04, threshold_m=0.01)
    >>> rule.reset(seed=0)
    >>> rule.request(np.zeros(3), 0).reliability  # only the prior: ask for the state
    1.0
    """

    def __init__(
        self,
        replica: PredictorReplica,
        *,
        threshold_m: float = 0.01,
        low: float = 0.2,
        high: float = 1.0,
        latency_steps: int = 1,
        innovation_gate: float | None = None,
    ) -> None:
        QosRequest(low, latency_steps)
        QosRequest(high, latency_steps)
        if latency_steps < 1:
            raise ValueError(f"latency_steps must be >= 1, got {latency_steps}")
        if not (math.isfinite(threshold_m) and threshold_m > 0):
            raise ValueError(f"threshold_m must be > 0, got {threshold_m!r}")
        if innovation_gate is not None and not 0.0 < innovation_gate < 1.0:
            raise ValueError(f"innovation_gate must be in (0, 1) or None, got {innovation_gate!r}")
        self.innovation_gate = innovation_gate
        self.nis_limit = (
            math.inf
            if innovation_gate is None
            else float(chi2.ppf(innovation_gate, replica.predictor.measured_dims))
        )
        self.low, self.high = float(low), float(high)
        self.latency_steps = int(latency_steps)
        self.threshold_m = float(threshold_m)
        self.replica = replica
        self.lift_margin_m = replica.lift_margin_m

    @property
    def predictor(self) -> Any:
        """The edge's replica of the robot's predictor."""
        return self.replica.predictor

    def reset(self, *, seed: int | None = None) -> None:
        self.replica.reset()

    def position_std_ahead(self, steps: int) -> float:
        """RMS position uncertainty ``steps`` steps after the latest held state, no new data."""
        return self.replica.position_std_ahead(steps)

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        """``(q_t, tau)`` from ``y_{t-1}`` (the remote part the robot holds) and ``zeta_{t-1}``."""
        self.replica.observe(observation, age)
        if self.replica.calls == 1:  # t = 0: the robot holds the prior, nothing measured yet
            return QosRequest(self.high, self.latency_steps)
        if self.replica.lifted:
            return QosRequest(self.low, self.latency_steps)
        if self.replica.nis > self.nis_limit:  # the last packet surprised the model
            return QosRequest(self.high, self.latency_steps)
        # The packet sent now (step t) is used from t + tau on: the uncertainty then without it.
        std = self.position_std_ahead(1 + self.latency_steps)
        q = self.high if std > self.threshold_m else self.low
        return QosRequest(q, self.latency_steps)


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
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
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
