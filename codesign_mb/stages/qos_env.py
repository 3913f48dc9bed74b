"""The QoS policy's MDP (``eq_q_t_pol2``): the plant behind a link, run by a fixed robot side.

:class:`QosAdaptationEnv` turns "the plant behind a link, run by a fixed controller and
estimator" into a Gymnasium env whose agent is the QoS policy. One agent step is one packet:

* observation: ``(y_{t-1}, zeta_{t-1})`` as the link held it (``eq_q_pol``), plus optional
  extra features (:class:`~codesign_mb.adaptation.learned.QosFeatures`);
* action: the reliability ``q_t`` (and, optionally, the latency; fixed at one step by
  default, like the paper);
* the packet ``x_t`` is sent with it, the robot runs ``u_t = controller(estimator(y_t,
  zeta_t))`` (``eq_c_pol2``) and the plant steps: one step of THE closed loop
  (:class:`~codesign_mb.rollout.ClosedLoop`);
* reward ``-(C(q_t) + lambda (L(x_t) - J_max / T))`` (``eq_q_t_pol2``);
* the plant's horizon ``T`` *terminates* the agent's episode (``terminal_horizon``): ``J``
  is scored at ``T`` and nothing follows, so the critic must not bootstrap past it as it
  would after a time limit (the failure loss is paid exactly on that step).

The task loss ``L`` (:attr:`QosEnvConfig.loss`) is one of

* ``"failure"``: ``1`` at the last step of an episode that never succeeded, else ``0``; the
  constraint ``E[sum_t L] <= J_max`` then bounds the failure rate by ``J_max``;
* ``"distance"``: the gripper-object distance in m at every step (a dense proxy);
* ``"estimation_error"``: the error of the estimator's remote estimate (norm) at every step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from codesign_mb.adaptation.learned import QosFeatures, QosInterface
from codesign_mb.control.base import Controller
from codesign_mb.core.config import LATENCY_STEPS_CAP, check_range
from codesign_mb.estimation.base import Estimator
from codesign_mb.network.link import BernoulliLink, Link
from codesign_mb.network.qos import QosCost, QosRequest, reliability_cost
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.rollout.loop import ClosedLoop

__all__ = ["LOSSES", "QosAdaptationEnv", "QosEnvConfig", "evaluate_qos_agent"]

LOSSES = ("failure", "distance", "estimation_error")


@dataclass(frozen=True)
class QosEnvConfig:
    """The QoS agent's problem (``eq_q_t_pol2``).

    Parameters
    ----------
    latency_steps:
        Fixed latency ``tau`` when not learned (the paper: 1).
    learn_latency, max_latency_steps:
        Learn ``tau`` in ``[0, max_latency_steps]`` too.
    min_reliability:
        Lowest reliability the agent may request.
    age_scale:
        The age enters the observation as ``zeta / age_scale``.
    loss:
        The task loss ``L`` (see the module docstring).
    j_max:
        ``J_max``: the bound on the expected episode sum of ``L`` (for ``"failure"``, the
        tolerated failure rate).
    lam:
        ``lambda``: fixed, or the initial value under dual ascent.
    terminal_horizon:
        The plant's horizon ends the agent's episode as a termination (``J`` is scored at
        ``T``; the critic does not bootstrap past it); ``False`` reports it as a time limit
        (truncation), as the trainer did before (``checkpoints/stage_c_mpc`` was trained so).
    """

    latency_steps: int = 1
    learn_latency: bool = False
    max_latency_steps: int = 4
    min_reliability: float = 0.0
    age_scale: float = 10.0
    loss: str = "failure"
    j_max: float = 0.02
    lam: float = 50.0
    terminal_horizon: bool = True

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        if self.j_max < 0:
            raise ValueError(f"j_max must be >= 0, got {self.j_max}")
        if self.lam < 0:
            raise ValueError(f"lam must be >= 0, got {self.lam}")
        check_range("max_latency_steps", self.max_latency_steps, cap=LATENCY_STEPS_CAP)
        check_range("latency_steps", self.latency_steps, cap=LATENCY_STEPS_CAP)
        QosInterface(  # validates the shared fields
            remote_dim=1,
            latency_steps=self.latency_steps,
            learn_latency=self.learn_latency,
            max_latency_steps=self.max_latency_steps,
            min_reliability=self.min_reliability,
            age_scale=self.age_scale,
        )


class _ActionQos:
    """The wrapper's QoS policy inside :class:`QosAdaptationEnv`: whatever the agent chose."""

    def __init__(self) -> None:
        self.next = QosRequest(1.0, 0)

    def reset(self, *, seed: int | None = None) -> None:
        return None

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        return self.next


class QosAdaptationEnv(gym.Env):
    """The QoS policy's MDP (``eq_q_t_pol2``) around a fixed controller and estimator.

    Parameters
    ----------
    env_factory:
        Builds the plant env (a :class:`~codesign_mb.network.NetworkedPlant` with a
        ``horizon``); called once.
    estimator, controller:
        The robot side (``eq_c_pol2``); any implementations of the protocols.
    config:
        :class:`QosEnvConfig`.
    features:
        Extra observation features, or ``None``.
    link:
        The link (default :class:`~codesign_mb.network.BernoulliLink`).
    qos_cost:
        ``C(q, tau)`` (default ``C(q) = q``, ``eq_robot``).

    Each agent step after the first steps the :class:`~codesign_mb.rollout.ClosedLoop` of
    the robot once; the first resets it (the packet sent at the reset gets the agent's QoS).
    ``info`` of the last step of an episode holds ``"qos_episode"``: the episode's
    ``success``, ``constraint`` (sum of ``L``), ``mean_reliability`` and ``steps``.
    """

    metadata = {"render_modes": []}  # noqa: RUF012

    def __init__(
        self,
        env_factory: Callable[[], gym.Env],
        estimator: Estimator,
        controller: Controller,
        *,
        config: QosEnvConfig | None = None,
        features: QosFeatures | None = None,
        link: Link | None = None,
        qos_cost: QosCost = reliability_cost,
    ) -> None:
        self.config = config or QosEnvConfig()
        plant = env_factory()
        self._qos = _ActionQos()
        self.wrapped = LinkObservationWrapper(plant, link or BernoulliLink(), self._qos, qos_cost)
        self.estimator = estimator
        self.controller = controller
        self.loop = ClosedLoop(self.wrapped, estimator, controller, record=False)
        self.features = features
        bind = getattr(features, "bind_belief", None)
        if bind is not None:  # features reading the robot's belief read this estimator
            bind(estimator)
        unwrapped = plant.unwrapped
        horizon = getattr(unwrapped, "horizon", None)
        if horizon is None:
            raise ValueError("QosAdaptationEnv needs a plant with a horizon (J_max / T)")
        self.horizon = int(horizon)
        self._prior = np.asarray(unwrapped.remote_prior(), dtype=float)
        c = self.config
        self.interface = QosInterface(
            remote_dim=int(self._prior.size),
            feature_dim=0 if features is None else int(features.dim),
            latency_steps=c.latency_steps,
            learn_latency=c.learn_latency,
            max_latency_steps=c.max_latency_steps,
            min_reliability=c.min_reliability,
            age_scale=c.age_scale,
        )
        self.observation_space = gym.spaces.Box(
            -np.inf, np.inf, shape=(self.interface.observation_dim,), dtype=np.float32
        )
        self.action_space = gym.spaces.Box(
            -1.0, 1.0, shape=(self.interface.action_dim,), dtype=np.float32
        )
        self.lam = float(c.lam)
        self._started = False
        self._done = True
        self._episode_seed = 0
        self._stats: dict[str, float] = {}

    def set_lambda(self, lam: float) -> None:
        """Set the multiplier ``lambda`` (dual ascent does this between episodes)."""
        if lam < 0:
            raise ValueError(f"lambda must be >= 0, got {lam}")
        self.lam = float(lam)

    def _observe(self, held: NDArray[np.float64], age: int) -> NDArray[np.float32]:
        extra = None if self.features is None else self.features(held, age)
        return self.interface.observation(held, age, extra)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        super().reset(seed=seed)
        self._episode_seed = int(self.np_random.integers(2**31 - 1)) if seed is None else seed
        self._started = False
        self._done = False
        self._stats = {"constraint": 0.0, "reliability": 0.0, "steps": 0, "success": False}
        if self.features is not None:
            self.features.reset()
        # The first request sees the prior, of age 0 (the wrapper's convention).
        return self._observe(self._prior, 0), {}

    def step(
        self, action: NDArray
    ) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        if self._done:
            raise RuntimeError("call reset() before step()")
        qos = self.interface.request(action)
        self._qos.next = qos  # eq_q_pol: the packet sent now gets the agent's QoS
        if not self._started:  # the first packet goes out with the reset
            info = self.loop.reset(seed=self._episode_seed)
            terminated = truncated = False
            self._started = True
        else:
            terminated, truncated, info = self.loop.step()
        done = bool(terminated or truncated)
        s = self._stats
        s["success"] = bool(s["success"] or info.get("success", False))
        loss = self._loss(info, done)
        s["constraint"] += loss
        s["reliability"] += qos.reliability
        s["steps"] += 1
        c = self.config
        reward = -(float(info["qos_cost"]) + self.lam * (loss - c.j_max / self.horizon))
        rx = self.wrapped.last_reception
        assert rx is not None
        next_obs = self._observe(rx.observation, rx.age)
        info = dict(info)
        info["lambda"] = self.lam
        info["task_loss"] = loss
        if done:
            self._done = True
            info["qos_episode"] = {
                "success": s["success"],
                "constraint": s["constraint"],
                "mean_reliability": s["reliability"] / s["steps"],
                "steps": s["steps"],
            }
        if c.terminal_horizon:  # the horizon ends the finite-horizon problem (J is scored at T)
            return next_obs, reward, done, False, info
        return next_obs, reward, bool(terminated), bool(truncated), info

    def _loss(self, info: dict[str, Any], done: bool) -> float:
        kind = self.config.loss
        if kind == "failure":
            return float(done and not self._stats["success"])
        if kind == "distance":
            return float(info.get("gripper_object_distance", 0.0))
        estimate = np.asarray(self.loop.state)[self.wrapped.remote_slice]
        return float(np.linalg.norm(estimate - np.asarray(info["remote_true"])))

    def close(self) -> None:
        self.wrapped.close()


def evaluate_qos_agent(
    env: QosAdaptationEnv, model: Any, *, seeds: Sequence[int]
) -> dict[str, float]:
    """Deterministic episodes of ``model`` in ``env``, one a seed: success, mean reliability."""
    results = []
    for s in seeds:
        obs, _ = env.reset(seed=s)
        done = False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        results.append(info["qos_episode"])
    if not results:
        return {}
    return {
        "eval_success_rate": float(np.mean([r["success"] for r in results])),
        "eval_mean_reliability": float(np.mean([r["mean_reliability"] for r in results])),
        "eval_constraint": float(np.mean([r["constraint"] for r in results])),
    }
