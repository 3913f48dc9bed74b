"""Belt-aware prediction of the object: an interacting-multiple-model filter through loss and delay.

Stage B of paper.tex done model-based for belts that change speed, stop and restart: the
object's speed is a state estimated from the perceived positions (the packet carries no
velocity), under the switching model of :mod:`codesign_mb.estimation.belt_model`. The robot
holds ``y_t = x_{t - zeta_t}`` (``eq_output``): a packet measures the state at its own stamp
``t - zeta_t``; the filter keeps the last ``max_delay_steps`` steps and re-filters from a
late packet's stamp (lost packets leave it predicting; delayed and out-of-sequence ones are
filtered in where they belong). One IMM cycle per step (Blom and Bar-Shalom): mix the mode
estimates with the transition probabilities, predict each mode, weigh each by the packet's
likelihood, and report the moment-matched mixture.

**Carried mode**: once the fingers hold the object (a robot-side fact: the gripper closed and
its finger width is that of an object, steady), the object follows the gripper, whose motion
the robot knows: every mode then moves the object by the gripper's displacement, with a
small noise for a slip in the fingers. On a release or a drop the belt modes take over again.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.core.layout import entry_indices, slice_indices
from codesign_mb.estimation.base import split_networked_observation
from codesign_mb.estimation.belt_model import MODES, N_STATE, STOP, BeltModel

__all__ = ["BeltImmPredictor"]

_CARRIED_SLIP_STD_M = 0.0003
"""Per-step position noise of an object in the fingers (m)."""

_CONTACT_STD_M, _CONTACT_STD_MPS = 0.0008, 0.02
"""Per-step position and velocity noise of a free object the open or closing fingers may touch
(the gripper within :data:`_CONTACT_RADIUS_M` of it and below :data:`_CONTACT_HEIGHT_M`):
the fingers push it by millimetres, which no belt mode describes."""

_CONTACT_RADIUS_M, _CONTACT_HEIGHT_M = 0.04, 0.04


@dataclass
class _Step:
    """The filter at one step: its prior (after the time update) and posterior, per mode."""

    prior: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
    posterior: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
    gripper: NDArray[np.float64] | None
    carried: bool
    z: NDArray[np.float64] | None = None
    nis: float = math.nan
    _moments_of: Any = None
    _moments: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    def moments(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean and covariance of the posterior mixture, computed once per posterior."""
        if self._moments is None or self._moments_of is not self.posterior:
            self._moments = _moments(*self.posterior)
            self._moments_of = self.posterior
        return self._moments


class BeltImmPredictor:
    """IMM prediction of the object on a switching belt (an ``Estimator``; module docstring).

    Parameters
    ----------
    layout:
        Name -> slice of the plant observation; needs ``object_pos``; uses ``object_vel``
        (measured too), ``gripper_pos`` and ``finger_width`` (the carried mode) when present.
    model:
        The belt's :class:`~codesign_mb.estimation.belt_model.BeltModel`.
    prior_position_std_m:
        Per-axis standard deviation of the object's start around the prior (x, y, z).
    prior_stopped_probability:
        Weight of STOP at the start (the object waits at its start before it spawns).
    max_delay_steps:
        Oldest packet (steps) still filtered in.
    output_velocity:
        Append the velocity estimate (3) to the output (a layout without ``object_vel``).
    output_std:
        Append the lateral uncertainty :attr:`position_std` (1 entry, m) after everything
        else: what an uncertainty-aware controller reads.
    holding_width_m:
        Finger widths ``(low, high)`` that mean an object is in the closed fingers.
    velocity_output:
        The velocity the output carries: ``"mixture"`` (the moment-matched mean) or
        ``"likeliest"`` (the most probable mode's). A controller extrapolating the object
        with it should not aim between a stopped belt and one that may restart: the mixture
        of a likely STOP and an unlikely START moves at a speed neither has.
    """

    def __init__(
        self,
        layout: Mapping[str, slice],
        *,
        model: BeltModel,
        prior_position_std_m: ArrayLike = (0.05, 0.05, 0.005),
        prior_stopped_probability: float = 0.0,
        max_delay_steps: int = 64,
        output_velocity: bool = False,
        output_std: bool = False,
        holding_width_m: tuple[float, float] = (0.02, 0.07),
        velocity_output: str = "mixture",
    ) -> None:
        if "object_pos" not in layout:
            raise ValueError("observation layout lacks object_pos")
        if not 0.0 <= prior_stopped_probability <= 1.0:
            raise ValueError(
                f"prior_stopped_probability must be in [0, 1], got {prior_stopped_probability!r}"
            )
        if int(max_delay_steps) != max_delay_steps or max_delay_steps < 1:
            raise ValueError(f"max_delay_steps must be an integer >= 1, got {max_delay_steps!r}")
        if velocity_output not in ("mixture", "likeliest"):
            raise ValueError(
                f"velocity_output must be 'mixture' or 'likeliest', got {velocity_output!r}"
            )
        self.velocity_output = velocity_output
        self.layout = dict(layout)
        self.model = model
        self._pos = slice_indices(self.layout["object_pos"])
        self._vel = entry_indices(self.layout, "object_vel")
        self._grip = entry_indices(self.layout, "gripper_pos")
        self._width = entry_indices(self.layout, "finger_width")
        self.prior_position_std = np.broadcast_to(
            np.asarray(prior_position_std_m, dtype=float), (3,)
        ).copy()
        self.prior_stopped_probability = float(prior_stopped_probability)
        self.max_delay_steps = int(max_delay_steps)
        self.output_velocity = bool(output_velocity) and self._vel is None
        self.output_std = bool(output_std)
        self.holding_width_m = (float(holding_width_m[0]), float(holding_width_m[1]))
        self.control_period_s = model.control_period_s
        self.A, self.c, self.Q = model.dynamics()
        self.H, self.R = model.measurement(velocity=self._vel is not None)
        self.Pi = model.transitions
        self._steps: list[_Step] = []
        self._t0 = 0  # the step of self._steps[0]
        self._t = 0
        self._last_stamp: int | None = None
        self._last_width: float | None = None
        self._carried = False
        self.updates = 0

    @classmethod
    def from_env(
        cls, env: Any, *, model_options: Mapping[str, Any] | None = None, **overrides: Any
    ) -> BeltImmPredictor:
        """For a conveyor env (wrapped or not): the plant's belt model, start spread, layout.

        ``overrides`` are constructor keywords; ``model_options`` (a mapping) overrides
        fields of the :class:`BeltModel` read from the plant.
        """
        plant = env.unwrapped
        cfg = plant.config
        kwargs: dict[str, Any] = {"model": BeltModel.from_plant(plant, **(model_options or {}))}
        state_layout = getattr(plant, "state_layout", None) or {}
        if "object_vel" in state_layout and "object_vel" not in plant.observation_layout:
            kwargs["output_velocity"] = True
        uniform = 1.0 / math.sqrt(3.0)  # std of U(-h, h) is h / sqrt(3)
        kwargs["prior_position_std_m"] = (
            max(cfg.spawn_lateral_range_m * uniform, 0.002),
            max(cfg.spawn_along_range_m * uniform, 0.002),
            0.002,
        )
        low, high = cfg.spawn_delay_steps
        kwargs["prior_stopped_probability"] = 1.0 - 1.0 / (high - low + 1) if high > 0 else 0.0
        kwargs["output_std"] = True  # an uncertainty-aware controller reads it
        kwargs.update(overrides)
        return cls(plant.observation_layout, **kwargs)

    # -- Estimator protocol --------------------------------------------------------------
    def reset(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        plant_obs, age = split_networked_observation(observation)
        m = self.model
        mean = np.zeros(N_STATE)
        mean[:3] = plant_obs[self._pos]
        mean[3:6] = m.nominal_velocity_mps
        cov = np.zeros((N_STATE, N_STATE))
        cov[:3, :3] = np.diag(self.prior_position_std**2)
        cov[3:6, 3:6] = np.diag([0.01**2, m.start_speed_std_mps**2, 0.01**2])
        cov[6:, 6:] = max(m.bias_std_m, 1e-4) ** 2 * np.eye(3)
        means = np.repeat(mean[None], 4, axis=0)
        covs = np.repeat(cov[None], 4, axis=0)
        means[STOP, 3:6] = 0.0
        covs[STOP, 3:6, 3:6] = 1e-3**2 * np.eye(3)
        mu = np.array(
            [1.0 - self.prior_stopped_probability, 0.0, self.prior_stopped_probability, 0]
        )
        state = (mu, means, covs)
        self._steps = [_Step(state, state, self._gripper(plant_obs), False)]
        self._t0 = self._t = 0
        self._last_stamp = None
        self._last_width = None
        self._carried = False
        self.updates = 0
        self._incorporate(plant_obs, age)
        return self._output(plant_obs)

    def estimate(
        self, observation: NDArray[np.float64], action: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        if not self._steps:
            raise RuntimeError("call reset() before estimate()")
        plant_obs, age = split_networked_observation(observation)
        self._carried = self._holding(plant_obs, action)
        self._t += 1
        last = self._steps[-1]
        gripper = self._gripper(plant_obs)
        prior = self._time_update(last.posterior, last.gripper, gripper, self._carried)
        self._steps.append(_Step(prior, prior, gripper, self._carried))
        if len(self._steps) > self.max_delay_steps + 1:
            self._steps.pop(0)
            self._t0 += 1
        self._incorporate(plant_obs, age)
        return self._output(plant_obs)

    # -- what the controller and a QoS rule read ------------------------------------------
    @property
    def t(self) -> int:
        """The current step."""
        return self._t

    @property
    def state(self) -> NDArray[np.float64]:
        """The mixture's mean ``(o, w, b)`` at the current step, shape ``(9,)``."""
        return self._require().moments()[0].copy()

    @property
    def covariance(self) -> NDArray[np.float64]:
        """The mixture's covariance (moment-matched), shape ``(9, 9)``."""
        return self._require().moments()[1].copy()

    @property
    def mode_probabilities(self) -> dict[str, float]:
        """Posterior probability of each belt mode (:data:`MODES`) at the current step."""
        mu = self._require().posterior[0]
        return {name: float(p) for name, p in zip(MODES, mu, strict=True)}

    @property
    def carried(self) -> bool:
        """Whether the object is in the fingers (the carried mode) at the current step."""
        return self._carried

    @property
    def last_nis(self) -> float:
        """Normalised innovation squared of the last packet against the mixture's prior."""
        for step in reversed(self._steps):
            if step.z is not None:
                return step.nis
        return math.nan

    @property
    def measured_dims(self) -> int:
        """Entries of one measurement: 3 (position) or 6 (position and velocity)."""
        return int(self.H.shape[0])

    @property
    def position_std(self) -> float:
        """``sqrt(P_xx + P_yy)``: the object's lateral RMS uncertainty (m), what a grasp
        tolerates (the belt's height is known; the fingers close across the object)."""
        return _lateral_std(self.covariance)

    def position_std_ahead(self, steps: int, requests: ArrayLike = ()) -> float:
        """Lateral RMS uncertainty (:attr:`position_std`) ``steps`` steps ahead if packets are
        measured at the
        future steps ``requests`` (1-based offsets), on the averaged linear model
        (:meth:`BeltModel.average_dynamics`) from the current mixture."""
        if self._carried:
            return self.position_std
        A, Q = self.model.average_dynamics(self._require().posterior[0])
        P = self.covariance
        wanted = set(int(k) for k in np.atleast_1d(np.asarray(requests, dtype=int)))
        H, R = self.H, self.R
        for k in range(1, steps + 1):
            P = A @ P @ A.T + Q
            if k in wanted:
                S = H @ P @ H.T + R
                K = np.linalg.solve(S, H @ P).T
                P = P - K @ S @ K.T
        return _lateral_std(P)

    # -- internals ----------------------------------------------------------------------
    def _require(self) -> _Step:
        if not self._steps:
            raise RuntimeError("call reset() first")
        return self._steps[-1]

    def _gripper(self, plant_obs: NDArray[np.float64]) -> NDArray[np.float64] | None:
        return None if self._grip is None else np.array(plant_obs[self._grip], dtype=float)

    def _holding(self, plant_obs: NDArray[np.float64], action: NDArray[np.float64]) -> bool:
        """Closed fingers at an object's width, steady over a step: the object is held."""
        if self._width is None or self._grip is None:
            return False
        width = float(np.mean(plant_obs[self._width]))
        last, self._last_width = self._last_width, width
        low, high = self.holding_width_m
        closed = float(action[3]) > 0.0 if len(action) >= 4 else True  # an edge replica: no grip
        steady = last is not None and abs(width - last) < 0.002
        # Fingers that open hold nothing (an edge replica, which does not see the grip
        # command, sees a reopening after an aborted close only by this).
        opening = last is not None and width > last + 0.001
        return closed and not opening and low <= width <= high and (steady or self._carried)

    def _time_update(
        self,
        posterior: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
        gripper: NDArray[np.float64] | None,
        gripper_next: NDArray[np.float64] | None,
        carried: bool,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        mu, means, covs = posterior
        if carried and gripper is not None and gripper_next is not None:
            # Carried: every mode moves with the gripper (its displacement is known).
            moved = means.copy()
            moved[:, :3] += gripper_next - gripper
            moved[:, 3:6] = (gripper_next - gripper) / self.control_period_s
            grown = covs.copy()
            grown[:, :3, :3] += _CARRIED_SLIP_STD_M**2 * np.eye(3)
            return mu, moved, grown
        # IMM mixing (eq. of Blom and Bar-Shalom): mode j starts from the mixture of the others.
        c = self.Pi.T @ mu  # c_j = sum_i Pi_ij mu_i
        # mu_{i|j}: each column sums to 1 for every mode j of probability c_j > 0, however small
        # (a floor on c_j would shrink the mixed mean and covariance of a mode below it).
        weights = np.divide(
            self.Pi * mu[:, None], c[None, :], out=np.zeros_like(self.Pi), where=c[None, :] > 0
        )
        mixed = weights.T @ means
        spread = means[None, :, :] - mixed[:, None, :]  # [j, i, :]
        mixed_cov = np.einsum("ij,ikl->jkl", weights, covs) + np.einsum(
            "ij,jik,jil->jkl", weights, spread, spread
        )
        pred = np.einsum("jkl,jl->jk", self.A, mixed) + self.c
        pred_cov = self.A @ mixed_cov @ self.A.transpose(0, 2, 1) + self.Q
        if gripper is not None and _touching(gripper, c @ means):
            pred_cov[:, :3, :3] += _CONTACT_STD_M**2 * np.eye(3)
            pred_cov[:, 3:6, 3:6] += _CONTACT_STD_MPS**2 * np.eye(3)
        return c, pred, pred_cov

    def _incorporate(self, plant_obs: NDArray[np.float64], age: int) -> None:
        stamp = self._t - int(age)
        if stamp < 0 or (self._last_stamp is not None and stamp <= self._last_stamp):
            return  # still the prior, or the packet held before
        self._last_stamp = stamp
        k = stamp - self._t0
        if k < 0:
            return  # older than the history: the prediction carries on
        z = np.array(plant_obs[self._pos], dtype=float)
        if self._vel is not None:
            z = np.concatenate([z, plant_obs[self._vel]])
        self._steps[k].z = z
        self.updates += 1
        self._refilter(k)

    def _refilter(self, k: int) -> None:
        """Redo the measurement update at step ``k`` and the steps after it."""
        for i in range(k, len(self._steps)):
            step = self._steps[i]
            if i > k:
                before = self._steps[i - 1]
                step.prior = self._time_update(
                    before.posterior, before.gripper, step.gripper, step.carried
                )
            step.posterior = step.prior if step.z is None else self._measure(step)

    def _measure(
        self, step: _Step
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        mu, means, covs = step.prior
        H, R, z = self.H, self.R, step.z
        assert z is not None
        mean, cov = _moments(mu, means, covs)
        nu = z - H @ mean
        S = H @ cov @ H.T + R
        step.nis = float(nu @ np.linalg.solve(S, nu))
        innovations = z[None, :] - means @ H.T
        S_j = H @ covs @ H.T + R
        gains = np.linalg.solve(S_j, H @ covs).transpose(0, 2, 1)  # P H' S^-1
        solved = np.linalg.solve(S_j, innovations[..., None])[..., 0]
        quad = np.einsum("ji,ji->j", innovations, solved)
        _, logdet = np.linalg.slogdet(S_j)
        loglik = -0.5 * (quad + logdet + len(z) * math.log(2 * math.pi))
        # Modes of probability 0 stay at 0 and do not set the scale: when one of them fits the
        # packet far better than every possible mode, exp() of the others would underflow.
        possible = mu > 0
        log_post = np.where(possible, np.log(np.where(possible, mu, 1.0)) + loglik, -np.inf)
        log_post -= log_post.max()
        post = np.exp(log_post)
        post /= post.sum()
        new_means = means + np.einsum("jkl,jl->jk", gains, innovations)
        IKH = np.eye(N_STATE)[None] - gains @ H
        new_covs = IKH @ covs @ IKH.transpose(0, 2, 1) + gains @ R @ gains.transpose(0, 2, 1)
        return post, new_means, new_covs

    def _output(self, plant_obs: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.array(plant_obs, dtype=float, copy=True)
        last = self._steps[-1]
        mean, cov = last.moments()
        velocity = mean[3:6]
        if self.velocity_output == "likeliest":
            mu, means, _ = last.posterior
            velocity = means[int(np.argmax(mu)), 3:6]
        out[self._pos] = mean[:3]
        if self._vel is not None:
            out[self._vel] = velocity
        extra = [velocity] if self.output_velocity else []
        if self.output_std:
            extra.append(np.array([_lateral_std(cov)]))
        return np.concatenate([out, *extra]) if extra else out

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_steps"] = []
        return state


def _lateral_std(P: NDArray[np.float64]) -> float:
    return float(math.sqrt(max(P[0, 0] + P[1, 1], 0.0)))


def _touching(gripper: NDArray[np.float64], mean: NDArray[np.float64]) -> bool:
    """Whether the fingers may touch the object: the gripper just over its estimate."""
    lateral = math.hypot(gripper[0] - mean[0], gripper[1] - mean[1])
    return lateral <= _CONTACT_RADIUS_M and gripper[2] - mean[2] <= _CONTACT_HEIGHT_M


def _moments(
    mu: NDArray[np.float64], means: NDArray[np.float64], covs: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mean and covariance of the Gaussian mixture ``sum_j mu_j N(means_j, covs_j)``."""
    mean = mu @ means
    d = means - mean
    cov = np.einsum("j,jkl->kl", mu, covs) + np.einsum("j,jk,jl->kl", mu, d, d)
    return mean, cov
