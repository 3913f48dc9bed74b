"""The ``linear`` sweep scenario: a gripper tracking an object on a belt, LQG over a lossy link.

A linear stand-in for the pick-and-place task, milliseconds per trial, so sweeps and their
backends can be exercised (and the trends read) without MuJoCo. One trial simulates
``n_robots`` independent robots for ``horizon_steps`` control periods of ``dt``:

- **Object** (the remote state, perceived at the edge): ``o = [p, v]`` with
  ``p_{t+1} = p_t + dt v_t``, ``v_{t+1} = v_t + w_t``, ``w_t ~ N(0, velocity_noise_mps^2)``,
  ``v_0`` = the belt speed. The edge measures ``x_t = o_t + n_t``.
- **Network**: each robot's packets go over a :class:`~codesign_mb.network.BernoulliLink`
  with latency ``latency_steps`` and reliability ``q = reliability * min(1, capacity_robots /
  n_robots)``: a crude shared channel that serves ``capacity_robots`` robots at the requested
  reliability and spreads the losses evenly beyond (the WiFi simulator is the real model).
- **Robot**: a double integrator gripper ``g = [pos, vel]`` (acceleration input, clipped to
  ``max_accel_mps2``), driven by the LQR ``u = -K (g - o_hat)`` of the error dynamics
  ``e = g - o`` with weights ``diag(1, velocity_weight)`` and ``control_weight``.
- **Pipelines** (how ``o_hat`` is formed from ``y_t = x_{t - zeta_t}``):
  ``ideal`` (the true ``o_t``, no network: the upper bound), ``none`` (``y_t`` used as if
  current), ``predictor`` (``A^zeta y_t``: extrapolated over its age with the model) and
  ``kalman`` (:class:`~codesign_mb.estimation.kalman.IntermittentKalmanFilter` with lost and
  delayed measurements).

Metrics (one row per trial, averaged over robots): ``success_rate`` (the paper's ``J``: the
mean ``|p - pos|`` over the last ``grasp_window_steps`` steps within ``success_radius_m``),
``within_radius_fraction`` (of steps), ``final_error_m`` (that mean distance),
``rms_error_m``, ``lqg_cost`` (mean stage cost ``e'Qe + u'Ru``), ``mean_reliability`` (the
requested ``q``: the paper's "average PDR"), ``delivered_fraction``, ``mean_age_steps``.
"""

from __future__ import annotations

import functools
import importlib.util
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.estimation.kalman import IntermittentKalmanFilter
from codesign_mb.network import BernoulliLink, QosRequest

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
        if self.horizon_steps < 1:
            raise ValueError(f"horizon_steps must be >= 1, got {self.horizon_steps}")
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


def _object_matrix(dt: float) -> NDArray[np.float64]:
    return np.array([[1.0, dt], [0.0, 1.0]])


@functools.lru_cache(maxsize=64)
def _lqr_gain(dt: float, velocity_weight: float, control_weight: float) -> NDArray[np.float64]:
    """Infinite-horizon discrete LQR gain of the double-integrator error dynamics."""
    from scipy.linalg import solve_discrete_are

    a = _object_matrix(dt)
    b = np.array([[0.5 * dt * dt], [dt]])
    q = np.diag([1.0, velocity_weight])
    r = np.array([[control_weight]])
    p = solve_discrete_are(a, b, q, r)
    gain = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
    gain.setflags(write=False)
    return gain


def channel_reliability(params: Params, n_robots: int) -> float:
    """The delivery probability each of ``n_robots`` robots gets on the shared channel."""
    return params.reliability * min(1.0, params.capacity_robots / n_robots)


def run_trial(config: Any, seed: int) -> dict[str, float]:
    """One trial of the linear scenario (see the module docstring); pure in ``seed``.

    ``config`` is a :class:`~codesign_mb.studies.sweep.TrialConfig` whose ``params`` is a
    :class:`Params`.
    """
    params: Params = config.params if config.params is not None else Params()
    if config.pipeline not in PIPELINES:
        raise ValueError(f"pipeline must be one of {', '.join(PIPELINES)}, got {config.pipeline!r}")
    robots = np.random.SeedSequence(seed).spawn(config.n_robots)
    per_robot = [
        _simulate_robot(params, config.pipeline, config.belt_speed_mps, config.n_robots, ss)
        for ss in robots
    ]
    return {key: float(np.mean([m[key] for m in per_robot])) for key in per_robot[0]}


def _simulate_robot(
    params: Params,
    pipeline: str,
    belt_speed_mps: float,
    n_robots: int,
    seed_seq: np.random.SeedSequence,
) -> dict[str, float]:
    plant_ss, link_ss = seed_seq.spawn(2)
    rng = np.random.default_rng(plant_ss)
    dt = params.control_period_s
    a_obj = _object_matrix(dt)
    b_grip = np.array([0.5 * dt * dt, dt])
    gain = _lqr_gain(dt, float(params.velocity_weight), float(params.control_weight))[0]
    q_weight = np.diag([1.0, params.velocity_weight])
    noise_std = np.array([params.measurement_noise_m, params.measurement_noise_mps])

    prior = np.array([params.start_offset_m, belt_speed_mps])
    obj = prior + np.array([rng.normal(0.0, params.start_spread_m), 0.0])
    grip = np.zeros(2)
    qos = QosRequest(channel_reliability(params, n_robots), params.latency_steps)
    link = BernoulliLink()
    link.reset(seed=int(link_ss.generate_state(1)[0]), prior=prior)
    kalman = _make_kalman(params, prior) if pipeline == "kalman" else None

    errors, costs, ages, delivered = [], [], [], []
    within = 0
    for _ in range(params.horizon_steps):
        measured = obj + rng.normal(0.0, 1.0, size=2) * noise_std
        rx = link.step(measured, qos)
        if pipeline == "ideal":
            estimate = obj
        elif pipeline == "none":
            estimate = rx.observation
        elif pipeline == "predictor":
            estimate = np.linalg.matrix_power(a_obj, rx.age) @ rx.observation
        else:
            assert kalman is not None
            for packet in rx.arrivals:
                kalman.update(packet.value, packet.timestamp)
            estimate = np.asarray(kalman.x, dtype=float)
        error = grip - obj
        u = float(np.clip(-gain @ (grip - estimate), -params.max_accel_mps2, params.max_accel_mps2))
        errors.append(error[0])
        costs.append(float(error @ q_weight @ error + params.control_weight * u * u))
        ages.append(rx.age)
        delivered.append(rx.delivered)
        within += abs(error[0]) <= params.success_radius_m
        # Advance: gripper under u, object along the belt with a velocity random walk.
        grip = a_obj @ grip + b_grip * u
        obj = a_obj @ obj + np.array([0.0, rng.normal(0.0, params.velocity_noise_mps)])
        if kalman is not None:
            kalman.predict()
    final_error = float(np.mean(np.abs(errors[-params.grasp_window_steps :])))
    return {
        "success_rate": float(final_error <= params.success_radius_m),
        "within_radius_fraction": within / params.horizon_steps,
        "rms_error_m": float(np.sqrt(np.mean(np.square(errors)))),
        "final_error_m": float(final_error),
        "lqg_cost": float(np.mean(costs)),
        "mean_reliability": qos.reliability,
        "delivered_fraction": float(np.mean(delivered)),
        "mean_age_steps": float(np.mean(ages)),
    }


def _make_kalman(params: Params, prior: NDArray[np.float64]) -> Any:
    dt = params.control_period_s
    process = np.diag([1e-12, params.velocity_noise_mps**2])
    noise = np.diag(
        [max(params.measurement_noise_m, 1e-6) ** 2, max(params.measurement_noise_mps, 1e-6) ** 2]
    )
    kf = IntermittentKalmanFilter(
        _object_matrix(dt),
        np.eye(2),
        process,
        noise,
        max_delay_steps=max(64, params.latency_steps + 1),
    )
    kf.reset(prior, np.diag([max(params.start_spread_m, 1e-6) ** 2, 1e-6]))
    return kf
