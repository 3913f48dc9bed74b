"""Delay-compensating prediction of the object on the belt (stage B of paper.tex, model-based).

The learned QoS-aware estimator ``pi_e(y_t, zeta_t)`` of ``eq_control_estimation`` is replaced
by a Kalman filter on the object's constant-velocity model, fed with the link's output: at
step ``t`` the robot holds ``y_t = x_{t - zeta_t}`` (``eq_output``), so a new packet is a
measurement of the state at ``t - zeta_t``. The
:class:`~codesign_mb.estimation.kalman.IntermittentKalmanFilter` incorporates it at that
timestamp (re-filtering from there) and the estimate is propagated to ``t``: losses leave the
filter predicting open loop, delays are compensated by the model.

Model, per axis of the object's position ``o`` and velocity ``w`` (period ``dt``)::

    o[t+1] = o[t] + dt w[t] + dt^2 / 2 a[t]
    w[t+1] = w[t] + dt a[t],          a[t] ~ N(0, sigma_a^2)   (belt speed changes)
    z[t]   = (o[t], w[t]) + v[t],     v[t] ~ N(0, R)          (perception noise)

(``w`` is measured only if the plant perceives the object's velocity.)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.core.layout import entry_indices, slice_indices
from codesign_mb.estimation.base import split_networked_observation
from codesign_mb.estimation.kalman import IntermittentKalmanFilter

__all__ = ["DelayCompensatingPredictor", "constant_velocity_model"]


def constant_velocity_model(
    dt: float, accel_std: float, *, dims: int = 3
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(A, Q)`` of the discrete constant-velocity model, state ``(o, w)`` of size ``2 dims``.

    ``Q`` is the discrete white-noise-acceleration covariance
    ``sigma_a^2 [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]`` per axis.
    """
    eye = np.eye(dims)
    A = np.block([[eye, dt * eye], [np.zeros((dims, dims)), eye]])
    q = accel_std**2
    Q = q * np.block([[dt**4 / 4 * eye, dt**3 / 2 * eye], [dt**3 / 2 * eye, dt**2 * eye]])
    return A, Q


class DelayCompensatingPredictor:
    """Kalman prediction of the object's current position and velocity through loss and delay.

    An :class:`~codesign_mb.estimation.base.Estimator`: its input is the wrapped observation
    (plant observation with the remote part ``y_t``, then the age ``zeta_t``), its output the
    plant-layout observation with ``object_pos`` (and ``object_vel``) replaced by the filter's
    prediction for the current step. Other remote entries, if any, are passed through as held.

    Parameters
    ----------
    layout:
        Name -> slice of the plant observation; needs ``"object_pos"``, uses ``"object_vel"``
        when present (then the velocity is measured too).
    control_period_s:
        ``dt`` of the model.
    prior_velocity:
        Belt velocity assumed before any measurement (world frame, m/s).
    position_noise_std, velocity_noise_std:
        Perception noise ``R`` of the object's position (m) and velocity (m/s).
    accel_std:
        ``sigma_a`` in m/s^2: how fast the belt speed (or the object) may change.
    prior_position_std, prior_velocity_std:
        Standard deviations of the prior (the plant's ``remote_prior()``).
    max_delay_steps:
        Oldest measurement (in steps) the filter can still incorporate; older ones are ignored.
    output_velocity:
        With a layout without ``object_vel`` (the velocity is not perceived): append the
        velocity estimate (3 entries) to the output, where the plant's ``state_layout`` puts
        ``object_vel``, so a controller gets the estimated velocity rather than a nominal one.

    Examples
    --------
    >>> layout = {"object_pos": slice(0, 3)}
    >>> est = DelayCompensatingPredictor(
    ...     layout, control_period_s=0.1, position_noise_std=1e-6, accel_std=0.0
    ... )
    >>> _ = est.reset(np.array([0.0, 0.0, 0.0, 0.0]))  # x_0 = 0 received, age 0
    >>> _ = est.estimate(np.array([0.1, 0.0, 0.0, 0.0]), np.zeros(4))  # x_1 = 0.1, age 0
    >>> round(float(est.estimate(np.array([0.1, 0.0, 0.0, 1.0]), np.zeros(4))[0]), 3)
    0.2
    """

    def __init__(
        self,
        layout: Mapping[str, slice],
        *,
        control_period_s: float,
        prior_velocity: ArrayLike = (0.0, 0.0, 0.0),
        position_noise_std: float = 0.002,
        velocity_noise_std: float = 0.02,
        accel_std: float = 0.5,
        prior_position_std: float = 0.1,
        prior_velocity_std: float = 0.5,
        max_delay_steps: int = 64,
        output_velocity: bool = False,
    ) -> None:
        if "object_pos" not in layout:
            raise ValueError("observation layout lacks object_pos")
        for name, value in (
            ("control_period_s", control_period_s),
            ("position_noise_std", position_noise_std),
            ("velocity_noise_std", velocity_noise_std),
            ("prior_position_std", prior_position_std),
            ("prior_velocity_std", prior_velocity_std),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value}")
        if not (math.isfinite(accel_std) and accel_std >= 0):
            raise ValueError(f"accel_std must be >= 0, got {accel_std}")
        if int(max_delay_steps) != max_delay_steps or max_delay_steps < 1:
            raise ValueError(f"max_delay_steps must be an integer >= 1, got {max_delay_steps!r}")
        self.layout = dict(layout)
        self._pos = slice_indices(self.layout["object_pos"])
        if len(self._pos) != 3:
            raise ValueError(f"object_pos must have 3 entries, got {len(self._pos)}")
        self._vel = entry_indices(self.layout, "object_vel")
        measured = self._pos if self._vel is None else np.concatenate([self._pos, self._vel])
        step = np.diff(measured)
        self._measured: slice | None = (  # the same entries as a slice, when contiguous
            slice(int(measured[0]), int(measured[-1]) + 1) if np.all(step == 1) else None
        )
        self.control_period_s = float(control_period_s)
        self.prior_velocity = np.asarray(prior_velocity, dtype=float).reshape(3)
        self.position_noise_std = float(position_noise_std)
        self.velocity_noise_std = float(velocity_noise_std)
        self.accel_std = float(accel_std)
        self.prior_position_std = float(prior_position_std)
        self.prior_velocity_std = float(prior_velocity_std)
        self.max_delay_steps = int(max_delay_steps)
        self.output_velocity = bool(output_velocity) and self._vel is None
        self.A, self.Q = constant_velocity_model(self.control_period_s, self.accel_std)
        if self._vel is None:
            self.C = np.hstack([np.eye(3), np.zeros((3, 3))])
            self.R = self.position_noise_std**2 * np.eye(3)
        else:
            self.C = np.eye(6)
            self.R = np.diag([self.position_noise_std**2] * 3 + [self.velocity_noise_std**2] * 3)
        self._kf: Any = None
        self._kf_model: tuple[Any, ...] = ()
        self._t = 0
        self._last_stamp: int | None = None
        self.updates = 0

    @classmethod
    def from_env(cls, env: Any, **overrides: Any) -> DelayCompensatingPredictor:
        """Build for a conveyor env (wrapped or not): layout, period, belt velocity, noise.

        ``overrides`` are keyword arguments of the constructor.
        """
        plant = env.unwrapped
        cfg = getattr(plant, "config", None)
        kwargs: dict[str, Any] = {"control_period_s": float(plant.control_period_s)}
        state_layout = getattr(plant, "state_layout", None) or {}
        if "object_vel" in state_layout and "object_vel" not in plant.observation_layout:
            kwargs["output_velocity"] = True  # estimated, not perceived: the controller reads it
        belt = getattr(plant, "belt_velocity", None)
        if belt is None and cfg is not None and hasattr(cfg, "belt_speed_mps"):
            belt = (0.0, float(cfg.belt_speed_mps), 0.0)  # the belt runs along +y
        if belt is not None:
            kwargs["prior_velocity"] = tuple(np.asarray(belt, dtype=float))
        for attr, key in (
            ("perception_noise_std_m", "position_noise_std"),
            ("velocity_noise_std_mps", "velocity_noise_std"),
        ):
            value = getattr(cfg, attr, None) if cfg is not None else None
            if value is not None and float(value) > 0:
                kwargs[key] = float(value)
        kwargs.update(overrides)
        return cls(plant.observation_layout, **kwargs)

    # -- Estimator protocol --------------------------------------------------------------
    def reset(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:

        plant_obs, age = split_networked_observation(observation)
        model = (self.A, self.C, self.Q, self.R, self.max_delay_steps)
        if self._kf is None or any(a is not b for a, b in zip(model, self._kf_model, strict=True)):
            # One filter, reset per episode: its covariance memo persists across episodes.
            self._kf = IntermittentKalmanFilter(
                self.A, self.C, self.Q, self.R, max_delay_steps=self.max_delay_steps
            )
            self._kf_model = model
        x0 = np.concatenate([plant_obs[self._pos], self.prior_velocity])
        self._kf.reset(x0, self.prior_covariance)
        self._t = 0
        self._last_stamp = None
        self.updates = 0
        self._incorporate(plant_obs, age)
        return self._output(plant_obs)

    def estimate(
        self, observation: NDArray[np.float64], action: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        if self._kf is None:
            raise RuntimeError("call reset() before estimate()")
        plant_obs, age = split_networked_observation(observation)
        self._t += 1
        if age > 0:  # a packet from before t: filter it in first (no predict to redo), as
            # IntermittentKalmanFilter.update would re-filter from its stamp after predict()
            self._incorporate(plant_obs, age)
            self._kf.predict()
        else:
            self._kf.predict()
            self._incorporate(plant_obs, age)
        return self._output(plant_obs)

    # -- internals ----------------------------------------------------------------------
    def _incorporate(self, plant_obs: NDArray[np.float64], age: int) -> None:
        stamp = self._t - int(age)
        if stamp < 0:  # still the prior (timestamp -1): nothing measured yet
            return
        if self._last_stamp is not None and stamp <= self._last_stamp:
            return  # the same packet as before: no new information
        self._last_stamp = stamp
        if self._t - stamp > self.max_delay_steps:
            return  # too old to re-filter; the prediction carries on
        if self._measured is not None:  # position (and velocity) side by side
            z = plant_obs[self._measured]
        else:
            z = plant_obs[self._pos]
            if self._vel is not None:
                z = np.concatenate([z, plant_obs[self._vel]])
        self._kf.update(z, stamp)
        self.updates += 1

    def _output(self, plant_obs: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.array(plant_obs, dtype=float, copy=True)
        x = self._kf._x  # read only: the filter's current mean
        if self.output_velocity:  # position measured, velocity estimated: appended
            out[self._pos] = x[:3]
            return np.concatenate([out, x[3:]])
        if self._measured is not None:
            out[self._measured] = x if self._vel is not None else x[:3]
            return out
        out[self._pos] = x[:3]
        if self._vel is not None:
            out[self._vel] = x[3:]
        return out

    # -- what a model-based QoS rule reads --------------------------------------------------
    @property
    def t(self) -> int:
        """The current step."""
        return self._t

    @property
    def state(self) -> NDArray[np.float64]:
        """The predicted ``(o, w)`` at the current step, shape ``(6,)``."""
        self._require()
        return np.asarray(self._kf.x, dtype=float).copy()

    @property
    def prior_covariance(self) -> NDArray[np.float64]:
        """Covariance of the prior (the plant's ``remote_prior()``), before any packet."""
        return np.diag([self.prior_position_std**2] * 3 + [self.prior_velocity_std**2] * 3)

    @property
    def covariance(self) -> NDArray[np.float64]:
        """Covariance ``P`` of :attr:`state`, shape ``(6, 6)``."""
        self._require()
        return np.asarray(self._kf.P, dtype=float).copy()

    @property
    def last_nis(self) -> float:
        """Normalised innovation squared of the last packet filtered in (NaN before any).

        Chi-square with as many degrees of freedom as measured entries when the model holds;
        large when the object did what the constant-velocity model did not expect (the belt
        stopped or changed speed, the object slipped) or the perception erred.
        """
        self._require()
        return float(self._kf.last_nis)

    @property
    def measured_dims(self) -> int:
        """Entries of one measurement: 3 (position) or 6 (position and velocity)."""
        return int(self.C.shape[0])

    @property
    def position_std(self) -> float:
        """``sqrt(trace P_oo)``: the predicted object position's RMS uncertainty in m."""
        return float(math.sqrt(max(np.trace(self.covariance[:3, :3]), 0.0)))

    def _require(self) -> None:
        if self._kf is None:
            raise RuntimeError("call reset() first")

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_kf"] = None  # the filter is rebuilt by reset()
        return state
