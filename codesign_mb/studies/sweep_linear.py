"""The ``linear`` sweep scenario: a gripper tracking an object on a belt, LQG over a lossy link.

A linear stand-in for the pick-and-place task, milliseconds per trial, so sweeps and their
backends can be exercised (and the trends read) without MuJoCo. One trial runs ``n_robots``
independent robots for ``horizon_steps`` control periods of ``dt``, each one episode of THE
closed loop (:func:`~codesign_mb.rollout.rollout`) on the plant
:class:`~codesign_mb.plants.belt_tracking.BeltTracking`:

- **Object** (the remote state, perceived at the edge): ``o = [p, v]`` with
  ``p_{t+1} = p_t + dt v_t``, ``v_{t+1} = v_t + w_t``, ``w_t ~ N(0, velocity_noise_mps^2)``,
  ``v_0`` = the belt speed. The edge measures ``x_t = o_t + n_t``.
- **Network**: each robot's packets go over a :class:`~codesign_mb.network.BernoulliLink`
  (behind a :class:`~codesign_mb.network.LinkObservationWrapper` with a
  :class:`~codesign_mb.adaptation.base.StaticQos`) with latency ``latency_steps`` and
  reliability ``q = reliability * min(1, capacity_robots / n_robots)``: a crude shared
  channel that serves ``capacity_robots`` robots at the requested reliability and spreads the
  losses evenly beyond (the WiFi simulator is the real model).
- **Robot**: a double integrator gripper ``g = [pos, vel]`` (acceleration input, clipped to
  ``max_accel_mps2``), driven by the LQR ``u = -K (g - o_hat)`` of the error dynamics
  ``e = g - o`` with weights ``diag(1, velocity_weight)`` and ``control_weight``
  (:class:`~codesign_mb.control.tracking.TrackingLqr`).
- **Pipelines** (how ``o_hat`` is formed from ``y_t = x_{t - zeta_t}``):
  ``ideal`` (no estimator: ideal control on the edge's current measurement ``x_t``, no
  network: the upper bound), ``none`` (``y_t`` used as if current,
  :class:`~codesign_mb.estimation.base.PassThroughEstimator`), ``predictor`` (``A^zeta y_t``:
  extrapolated over its age with the model,
  :class:`~codesign_mb.estimation.extrapolation.ModelExtrapolation`) and ``kalman``
  (:class:`~codesign_mb.estimation.kalman.KalmanEstimator` of the object, fed with every
  packet that arrives, lost and delayed ones included).

Metrics (one row per trial, averaged over robots): ``success_rate`` (the paper's ``J``: the
mean ``|p - pos|`` over the last ``grasp_window_steps`` steps within ``success_radius_m``),
``within_radius_fraction`` (of steps), ``final_error_m`` (that mean distance),
``rms_error_m``, ``lqg_cost`` (mean stage cost ``e'Qe + u'Ru``), ``mean_reliability`` (the
requested ``q``: the paper's "average PDR"), ``delivered_fraction``, ``mean_age_steps``.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.tracking import TrackingLqr
from codesign_mb.core.config import STEPS_CAP, check_range
from codesign_mb.estimation.base import Estimator, PassThroughEstimator
from codesign_mb.estimation.extrapolation import ModelExtrapolation, RemotePartEstimator
from codesign_mb.estimation.kalman import KalmanEstimator
from codesign_mb.network import BernoulliLink, LinkObservationWrapper, QosRequest
from codesign_mb.plants.belt_tracking import BeltTracking
from codesign_mb.rollout import rollout

__all__ = ["DEFAULT_PIPELINES", "PIPELINES", "Params", "run_trial"]

PIPELINES: tuple[str, ...] = ("ideal", "none", "predictor", "kalman")
"""Pipelines this scenario accepts."""

DEFAULT_PIPELINES: tuple[str, ...] = tuple(
    p
    for p in PIPELINES
    if p != "kalman" or importlib.util.find_spec("codesign_mb.estimation.kalman") is not None
)
"""Pipelines swept when none are configured: all those whose code is installed."""


@dataclass(frozen=True)
class Params:
    """Settings of the linear scenario (``[sweep.params]`` in a sweep config file).

    Attributes
    ----------
    horizon_steps:
        Episode length ``T`` in control periods.
    control_period_s:
        ``dt`` in seconds (the paper's 40 ms).
    reliability:
        Requested delivery probability ``q`` in [0, 1].
    latency_steps:
        Latency ``tau`` in control periods (>= 0).
    capacity_robots:
        Robots the channel serves at the requested reliability (> 0).
    start_offset_m, start_spread_m:
        Mean and standard deviation of the object's start ahead of the gripper, in m.
    velocity_noise_mps:
        Per-step standard deviation of the belt velocity random walk, in m/s.
    measurement_noise_m, measurement_noise_mps:
        Edge perception noise on position (m) and velocity (m/s).
    velocity_weight, control_weight:
        LQR weights on the velocity error (1/s^2 units) and the acceleration.
    max_accel_mps2:
        Acceleration limit of the gripper, in m/s^2.
    success_radius_m:
        ``eps`` of the paper's success indicator, in m.
    grasp_window_steps:
        The grasp succeeds when the mean distance over the last ``grasp_window_steps``
        steps is within ``success_radius_m`` (the gripper stayed on the object while closing).
    """

    horizon_steps: int = 100
    control_period_s: float = 0.04
    reliability: float = 0.8
    latency_steps: int = 2
    capacity_robots: float = 2.0
    start_offset_m: float = 0.1
    start_spread_m: float = 0.02
    velocity_noise_mps: float = 0.02
    measurement_noise_m: float = 0.002
    measurement_noise_mps: float = 0.01
    velocity_weight: float = 0.1
    control_weight: float = 1e-3
    max_accel_mps2: float = 20.0
    success_radius_m: float = 0.01
    grasp_window_steps: int = 10

    def __post_init__(self) -> None:
        QosRequest(self.reliability, self.latency_steps)  # validates q and tau
        if isinstance(self.horizon_steps, bool) or not isinstance(self.horizon_steps, int):
            raise ValueError(f"horizon_steps must be an integer, got {self.horizon_steps!r}")
        check_range("horizon_steps", self.horizon_steps, ge=1, cap=STEPS_CAP)
        window = self.grasp_window_steps
        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise ValueError(f"grasp_window_steps must be an integer >= 1, got {window!r}")
        positive = ("control_period_s", "capacity_robots", "control_weight", "max_accel_mps2")
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        non_negative = (
            "start_spread_m",
            "velocity_noise_mps",
            "measurement_noise_m",
            "measurement_noise_mps",
            "velocity_weight",
            "success_radius_m",
        )
        for name in non_negative:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0, got {value!r}")


def channel_reliability(params: Params, n_robots: int) -> float:
    """The delivery probability each of ``n_robots`` robots gets on the shared channel."""
    return params.reliability * min(1.0, params.capacity_robots / n_robots)


def run_trial(config: Any, seed: int) -> dict[str, float]:
    """One trial of the linear scenario (see the module docstring); pure in ``seed``.

    ``config`` is a :class:`~codesign_mb.studies.sweep.TrialConfig` whose ``params`` is a
    :class:`Params`. Robot ``i`` runs one :func:`~codesign_mb.rollout.rollout` seeded with
    the ``i``-th stream spawned from ``seed``.
    """
    params: Params = config.params if config.params is not None else Params()
    if config.pipeline not in PIPELINES:
        raise ValueError(f"pipeline must be one of {', '.join(PIPELINES)}, got {config.pipeline!r}")
    env = _networked_plant(params, config.belt_speed_mps, config.n_robots)
    estimator = _estimator(config.pipeline, env, params)
    controller = TrackingLqr.for_env(env)
    robots = np.random.SeedSequence(seed).spawn(config.n_robots)
    per_robot = [
        _robot_metrics(
            rollout(env, estimator, controller, seed=int(ss.generate_state(1)[0])), params
        )
        for ss in robots
    ]
    return {key: _mean([m[key] for m in per_robot]) for key in per_robot[0]}


def _networked_plant(
    params: Params, belt_speed_mps: float, n_robots: int
) -> LinkObservationWrapper:
    """One robot's plant behind its share of the channel (reset per robot by the rollout)."""
    plant = BeltTracking(
        belt_speed_mps=belt_speed_mps,
        horizon=params.horizon_steps,
        control_period_s=params.control_period_s,
        start_offset_m=params.start_offset_m,
        start_spread_m=params.start_spread_m,
        velocity_noise_mps=params.velocity_noise_mps,
        measurement_noise_m=params.measurement_noise_m,
        measurement_noise_mps=params.measurement_noise_mps,
        velocity_weight=params.velocity_weight,
        control_weight=params.control_weight,
        max_accel_mps2=params.max_accel_mps2,
        success_radius_m=params.success_radius_m,
    )
    qos = StaticQos(channel_reliability(params, n_robots), params.latency_steps)
    return LinkObservationWrapper(plant, BernoulliLink(), qos)


def _estimator(pipeline: str, env: LinkObservationWrapper, params: Params) -> Estimator | None:
    """The estimator of ``pipeline`` (``None``: ideal control); reused across robots."""
    if pipeline == "ideal":
        return None
    if pipeline == "none":
        return PassThroughEstimator()
    plant = env.unwrapped
    assert isinstance(plant, BeltTracking)
    model = plant.remote_model
    if pipeline == "predictor":
        return RemotePartEstimator(ModelExtrapolation(model.A), plant.remote_slice)
    # The filter's covariances are floored so that it stays well posed when a noise is 0.
    floored = dataclasses.replace(
        model,
        W=np.maximum(model.W, np.diag([1e-12, 0.0])),
        V=np.maximum(model.V, np.diag([1e-12, 1e-12])),
    )
    kalman = KalmanEstimator(
        floored,
        x0_mean=plant.remote_prior(),
        x0_cov=np.maximum(plant.remote_prior_cov(), np.diag([1e-12, 1e-6])),
        max_delay_steps=max(64, params.latency_steps + 1),
        link_wrapper=env,
    )
    return RemotePartEstimator(kalman, plant.remote_slice)


def _robot_metrics(table: pd.DataFrame, params: Params) -> dict[str, float]:
    """The metrics of one robot from its per-step record (one row per control step)."""
    errors = table["tracking_error_m"].to_numpy(dtype=float)
    final_error = _mean(np.abs(errors[-params.grasp_window_steps :]))
    return {
        "success_rate": float(final_error <= params.success_radius_m),
        "within_radius_fraction": _mean(table["within_radius"]),
        "rms_error_m": math.sqrt(_mean(np.square(errors))),
        "final_error_m": final_error,
        "lqg_cost": _mean(table["stage_cost"]),
        "mean_reliability": _mean(table["qos_reliability"]),
        "delivered_fraction": _mean(table["delivered"]),
        "mean_age_steps": _mean(table["age"]),
    }


def _mean(values: Any) -> float:
    """The mean, shifted by the first value: exact for a constant column (a static ``q``)."""
    array = np.asarray(values, dtype=float)
    return float(array[0] + np.mean(array - array[0]))
