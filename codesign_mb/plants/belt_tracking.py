"""A gripper tracking an object on a belt: the linear stand-in for the pick-and-place task.

The plant of the ``linear`` sweep scenario (:mod:`codesign_mb.studies.sweep_linear`),
milliseconds per episode, no MuJoCo. Per control period ``dt``:

- **Object** (the remote state, perceived at the edge): ``o = [p, v]`` with
  ``p_{t+1} = p_t + dt v_t``, ``v_{t+1} = v_t + w_t``, ``w_t ~ N(0, velocity_noise_mps^2)``,
  ``p_0 = start_offset_m + N(0, start_spread_m^2)``, ``v_0`` = the belt speed. The edge
  measures ``x_t = o_t + n_t``, ``n_t ~ N(0, diag(measurement_noise_m^2,
  measurement_noise_mps^2))``.
- **Gripper** (local, always fresh): a double integrator ``g = [pos, vel]``, ``g_0 = 0``,
  driven by the acceleration ``u`` (clipped to ``max_accel_mps2``) with a zero-order hold:
  ``g_{t+1} = A g_t + [dt^2 / 2, dt] u_t``.

The observation is ``[g, x]`` (``remote_slice`` selects ``x``, the part a
:class:`~codesign_mb.network.LinkObservationWrapper` sends over the link). The reward is
``-(e' Q e + r u^2)`` with the tracking error ``e = g - o`` before the transition,
``Q = diag(1, velocity_weight)``, ``r = control_weight``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.plants.linear import (
    CONTROL_PERIOD_S,
    LinearPlantSpec,
    _non_negative,
    _positive,
)

__all__ = ["BeltTracking"]

FloatArray = NDArray[np.float64]


@dataclass(eq=False, slots=True)
class _Workspace:
    """The mutable part of an episode: gripper ``g = [pos, vel]``, object ``o = [p, v]``, step.

    Python floats: the dynamics are a handful of scalar operations per step, which numpy
    would spend most of its time dispatching.
    """

    pos: float
    vel: float
    p: float
    v: float
    t: int = 0


class BeltTracking(gym.Env[NDArray[np.float64], NDArray[np.float64]]):
    """A double-integrator gripper tracking an object on a belt (see the module docstring).

    Observation ``[g_pos, g_vel, x_p, x_v]`` (m, m/s; shape ``(4,)``), the last two remote.
    Action: the gripper's acceleration ``u`` in m/s^2 (shape ``(1,)``), clipped to
    ``[-max_accel_mps2, max_accel_mps2]``. The episode is truncated after ``horizon`` steps
    and never terminates.

    Parameters
    ----------
    belt_speed_mps:
        ``v_0``, the belt speed (m/s, finite).
    horizon:
        Episode length in control periods (>= 1).
    control_period_s:
        ``dt`` in seconds (> 0).
    start_offset_m, start_spread_m:
        Mean and standard deviation of the object's start ahead of the gripper (m).
    velocity_noise_mps:
        Per-step standard deviation of the belt velocity random walk (m/s).
    measurement_noise_m, measurement_noise_mps:
        Edge perception noise on position (m) and velocity (m/s).
    velocity_weight, control_weight:
        Stage-cost weights on the velocity error (1/s^2 units) and the acceleration (> 0).
    max_accel_mps2:
        Acceleration limit of the gripper (> 0).
    success_radius_m:
        Radius of the per-step ``within_radius`` indicator (m).
    render_mode:
        Unused (no rendering); accepted for the Gymnasium constructor convention.

    Notes
    -----
    Randomness only through ``reset(seed=...)``: the env's own generator ``np_random`` draws
    ``p_0`` and ``n_0``, then per step ``w_t`` followed by ``n_{t+1}``. ``info`` carries the
    true object ``"object"`` (``o_t`` at reset, ``o_{t+1}`` after a step) and, after a step,
    the ``"stage_cost"`` of the step, the position error ``"tracking_error_m"``
    (``pos - p`` before the transition, the one the stage cost charges) and
    ``"within_radius"`` (``|pos - p| <= success_radius_m``).

    Examples
    --------
    >>> env = BeltTracking(belt_speed_mps=0.6, horizon=3)
    >>> obs, info = env.reset(seed=0)
    >>> obs.shape, env.remote_slice, env.remote_prior().tolist()
    ((4,), slice(2, 4, None), [0.1, 0.6])
    >>> obs, reward, terminated, truncated, info = env.step(np.array([1.0]))
    >>> bool(info["stage_cost"] == -reward), sorted(info)
    (True, ['object', 'stage_cost', 'tracking_error_m', 'within_radius'])
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 (Gymnasium convention)

    local_slice = slice(0, 2)
    """The gripper's part of the observation (local, always fresh)."""
    remote_slice = slice(2, 4)
    """The object's part of the observation (perceived at the edge, sent over the link)."""

    def __init__(
        self,
        *,
        belt_speed_mps: float = 0.2,
        horizon: int = 100,
        control_period_s: float = CONTROL_PERIOD_S,
        start_offset_m: float = 0.1,
        start_spread_m: float = 0.02,
        velocity_noise_mps: float = 0.02,
        measurement_noise_m: float = 0.002,
        measurement_noise_mps: float = 0.01,
        velocity_weight: float = 0.1,
        control_weight: float = 1e-3,
        max_accel_mps2: float = 20.0,
        success_radius_m: float = 0.01,
        render_mode: str | None = None,
    ) -> None:
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        if render_mode is not None:
            raise ValueError(f"render_mode must be None (no rendering), got {render_mode!r}")
        if not math.isfinite(belt_speed_mps) or not math.isfinite(start_offset_m):
            raise ValueError(
                f"belt_speed_mps and start_offset_m must be finite, "
                f"got {belt_speed_mps!r} and {start_offset_m!r}"
            )
        dt = _positive("control_period_s", control_period_s)
        self.belt_speed_mps = float(belt_speed_mps)
        self.horizon = horizon
        self.control_period_s = dt
        self.start_offset_m = float(start_offset_m)
        self.start_spread_m = _non_negative("start_spread_m", start_spread_m)
        self.velocity_noise_mps = _non_negative("velocity_noise_mps", velocity_noise_mps)
        self.measurement_noise_m = _non_negative("measurement_noise_m", measurement_noise_m)
        self.measurement_noise_mps = _non_negative("measurement_noise_mps", measurement_noise_mps)
        self.velocity_weight = _non_negative("velocity_weight", velocity_weight)
        self.control_weight = _positive("control_weight", control_weight)
        self.max_accel_mps2 = _positive("max_accel_mps2", max_accel_mps2)
        self.success_radius_m = _non_negative("success_radius_m", success_radius_m)
        self.render_mode = render_mode

        self.state_cost: FloatArray = np.diag([1.0, self.velocity_weight])
        """``Q`` of the stage cost, on the tracking error ``e = g - o``."""
        self.input_cost: FloatArray = np.array([[self.control_weight]])
        """``R`` of the stage cost, on the acceleration."""
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(4,), dtype=np.float64)
        bound = self.max_accel_mps2
        self.action_space = gym.spaces.Box(-bound, bound, shape=(1,), dtype=np.float64)
        self._ws: _Workspace | None = None

    @functools.cached_property
    def remote_model(self) -> LinearPlantSpec:
        """The object ``o`` and its measurement ``x`` (the action does not move it: ``B = 0``)."""
        return self._model("belt_object", np.zeros((2, 1)))

    @functools.cached_property
    def error_model(self) -> LinearPlantSpec:
        """The error ``e = g - o``: ``e+ = A e + B u - [0, w]``, measured as ``g - x``."""
        dt = self.control_period_s
        return self._model("belt_tracking_error", np.array([[0.5 * dt * dt], [dt]]))

    def _model(self, name: str, B: FloatArray) -> LinearPlantSpec:
        dt = self.control_period_s
        W = np.diag([0.0, self.velocity_noise_mps**2])
        V = np.diag([self.measurement_noise_m**2, self.measurement_noise_mps**2])
        return LinearPlantSpec(name, np.array([[1.0, dt], [0.0, 1.0]]), B, np.eye(2), W, V, dt)

    @property
    def t(self) -> int:
        """The current step (0 after reset)."""
        return 0 if self._ws is None else self._ws.t

    def remote_prior(self) -> FloatArray:
        """``E[o_0] = [start_offset_m, belt_speed_mps]``: what the robot holds before a delivery."""
        return np.array([self.start_offset_m, self.belt_speed_mps])

    def remote_prior_cov(self) -> FloatArray:
        """Covariance of ``o_0``: ``diag(start_spread_m^2, 0)``."""
        return np.diag([self.start_spread_m**2, 0.0])

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[FloatArray, dict[str, Any]]:
        super().reset(seed=seed)
        if options:
            raise ValueError(f"unknown reset option(s) {sorted(options)}; expected none")
        spread, n_p, n_v = self.np_random.standard_normal(3).tolist()
        p0 = self.start_offset_m + self.start_spread_m * spread
        ws = self._ws = _Workspace(0.0, 0.0, p0, self.belt_speed_mps)
        return self._observe(ws, n_p, n_v), {"object": np.array([ws.p, ws.v])}

    def step(self, action: ArrayLike) -> tuple[FloatArray, float, bool, bool, dict[str, Any]]:
        ws = self._ws
        if ws is None:
            raise RuntimeError("call reset() before step()")
        u_arr = np.asarray(action, dtype=float)
        if u_arr.size != 1 or u_arr.ndim > 1:
            raise ValueError(f"action must have 1 entry, got shape {np.shape(action)}")
        bound = self.max_accel_mps2
        u = min(max(float(u_arr.flat[0]), -bound), bound)  # NaN propagates, as with np.clip
        error_p, error_v = ws.pos - ws.p, ws.vel - ws.v
        stage_cost = error_p * error_p + self.velocity_weight * error_v * error_v
        stage_cost += self.control_weight * u * u
        # g+ = A g + [dt^2 / 2, dt] u;  o+ = A o + [0, w];  then x+ = o+ + n.
        dt = self.control_period_s
        w, n_p, n_v = self.np_random.standard_normal(3).tolist()
        ws.pos += dt * ws.vel + 0.5 * dt * dt * u
        ws.vel += dt * u
        ws.p += dt * ws.v
        ws.v += self.velocity_noise_mps * w
        ws.t += 1
        info = {
            "object": np.array([ws.p, ws.v]),
            "stage_cost": stage_cost,
            "tracking_error_m": error_p,
            "within_radius": abs(error_p) <= self.success_radius_m,
        }
        return self._observe(ws, n_p, n_v), -stage_cost, False, ws.t >= self.horizon, info

    def _observe(self, ws: _Workspace, n_p: float, n_v: float) -> FloatArray:
        """``[g, x]`` with the edge's measurement ``x = o + n`` (``n_p``, ``n_v`` standard)."""
        return np.array(
            [
                ws.pos,
                ws.vel,
                ws.p + self.measurement_noise_m * n_p,
                ws.v + self.measurement_noise_mps * n_v,
            ]
        )
