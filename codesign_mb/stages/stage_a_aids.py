"""Stage A's training aids around SB3's SAC: the actor's input, shaping, belt-speed curriculum.

Plain SB3/gymnasium usage, no RL algorithm: the training env the actor acts in, the plant
behind a perfect link with the stack's estimator (:class:`EstimatedStateEnv`, the ``oracle``
link of the tables: what the robot knows with every packet delivered fresh), the shaped reward
and the early-grip penalty (:class:`Shaping`), the curriculum over belt speeds
(:func:`curriculum_schedule` + :class:`Curriculum`), and the evaluation behind that link
(:func:`evaluate_ideal`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.base import Controller
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.rollout.loop import rollout

__all__ = [
    "Curriculum",
    "EstimatedStateEnv",
    "Shaping",
    "curriculum_schedule",
    "evaluate_ideal",
    "plant_at_speed",
    "speed_at",
]


def curriculum_schedule(
    plant: PlantSpec, speeds: tuple[float, ...], total_steps: int
) -> list[tuple[int, float]]:
    """``(start step, top belt speed)`` pairs: ``speeds`` then the plant's own, equal shares.

    The plant's own is the top of its ``belt_speed_range_mps`` or its ``belt_speed_mps``.
    Empty without ``speeds``; ``ValueError`` when the plant sets neither.
    """
    if not speeds:
        return []
    speed_range = plant.options.get("belt_speed_range_mps") or ()
    final_speed = speed_range[-1] if speed_range else plant.options.get("belt_speed_mps")
    if final_speed is None:
        raise ValueError("a curriculum needs plant.options.belt_speed_mps (the final speed)")
    steps = [*speeds, float(final_speed)]
    share = total_steps // len(steps)
    return [(i * share, s) for i, s in enumerate(steps)]


def speed_at(schedule: list[tuple[int, float]], steps: int) -> float:
    """The belt speed of ``schedule`` after ``steps`` env steps."""
    speed = schedule[0][1]
    for start, value in schedule:
        if steps >= start:
            speed = value
    return speed


def plant_at_speed(plant: PlantSpec, speed: float) -> PlantSpec:
    """``plant`` with belt speeds up to ``speed`` (m/s).

    A plant that draws its speed per episode (``belt_speed_range_mps = (low, high)``) gets the
    range ``(min(low, speed), min(high, speed))`` (its nominal speed, the robot's prior, is
    kept); a plant with one speed gets ``belt_speed_mps = speed``.
    """
    speed_range = tuple(plant.options.get("belt_speed_range_mps", ()))
    if speed_range:
        low, high = float(speed_range[0]), float(speed_range[1])
        options = {**plant.options, "belt_speed_range_mps": (min(low, speed), min(high, speed))}
        return replace(plant, options=options)
    return replace(plant, options={**plant.options, "belt_speed_mps": float(speed)})


class Curriculum(BaseCallback):
    """Switch the training env's belt speed at fixed step counts (applied at the next reset)."""

    def __init__(self, schedule: list[tuple[int, float]]) -> None:
        super().__init__()
        self.schedule = schedule

    def _on_step(self) -> bool:
        self.training_env.env_method("set_top_speed", speed_at(self.schedule, self.num_timesteps))
        return True


class EstimatedStateEnv(gym.Env):
    """The plant behind a perfect link (``q = 1``, ``tau = 0``) seen through an estimator.

    The observation is the estimator's output (the plant's ``state_layout``: with the
    ``predictor`` on a plant that perceives no velocity, the estimated velocity appended), so
    the actor is trained on what it is given at evaluation under the ``oracle`` link. The
    reward, ``terminated``/``truncated`` and ``info`` are the plant's. :meth:`set_top_speed`
    rebuilds the plant with belt speeds up to a value at the next reset (the curriculum).
    """

    def __init__(self, plant: PlantSpec, estimator: ComponentSpec) -> None:
        self._plant_spec, self._estimator_spec = plant, estimator
        self._top: float | None = None
        self._pending: float | None = None
        self._build(plant)
        probe = self._estimator.reset(self._linked.reset(seed=0)[0])
        low = np.full(len(probe), -10.0, dtype=np.float32)
        self.observation_space = gym.spaces.Box(low, -low, dtype=np.float32)
        self.action_space = self._linked.action_space

    def _build(self, plant: PlantSpec) -> None:
        self.plant = make_plant(plant)
        self._linked = LinkObservationWrapper(self.plant, BernoulliLink(), StaticQos(1.0, 0))
        self._estimator = build("estimator", self._estimator_spec, self.plant)

    def set_top_speed(self, speed: float) -> None:
        """Belt speeds up to ``speed`` (m/s) from the next episode on."""
        if speed != self._top:
            self._pending = float(speed)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if self._pending is not None:
            self.plant.close()
            self._build(plant_at_speed(self._plant_spec, self._pending))
            self._top, self._pending = self._pending, None
        obs, info = self._linked.reset(seed=seed, options=options)
        return self._clip(self._estimator.reset(obs)), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self._linked.step(action)
        state = self._estimator.estimate(obs, np.asarray(action, dtype=float))
        return self._clip(state), float(reward), terminated, truncated, info

    def _clip(self, state: Any) -> np.ndarray:
        space = self.observation_space
        return np.clip(np.asarray(state, dtype=np.float32), space.low, space.high)

    def close(self) -> None:
        self.plant.close()


class Shaping(gym.Wrapper):
    """Add ``w (d_t - gamma d_{t+1})`` (potential ``-w d``; ``d`` from ``info``) to the reward,
    and ``-grip_penalty`` when the grip closes farther than ``grip_radius_m`` from the object."""

    def __init__(
        self,
        env: gym.Env,
        weight: float,
        gamma: float,
        grip_penalty: float = 0.0,
        grip_radius_m: float = 0.04,
    ) -> None:
        super().__init__(env)
        self.weight, self.gamma = float(weight), float(gamma)
        self.grip_penalty, self.grip_radius_m = float(grip_penalty), float(grip_radius_m)
        self._distance = 0.0

    def reset(self, **kwargs: Any) -> Any:
        obs, info = self.env.reset(**kwargs)
        self._distance = float(info["gripper_object_distance"])
        return obs, info

    def step(self, action: Any) -> Any:
        closing_far = float(np.asarray(action)[-1]) > 0 and self._distance > self.grip_radius_m
        obs, reward, terminated, truncated, info = self.env.step(action)
        distance = float(info["gripper_object_distance"])
        bonus = self.weight * (self._distance - (0.0 if terminated else self.gamma) * distance)
        bonus -= self.grip_penalty * closing_far
        self._distance = distance
        return obs, float(reward) + bonus, terminated, truncated, info


def evaluate_ideal(
    plant: PlantSpec,
    controller: Controller,
    *,
    seeds: Sequence[int],
    estimator: ComponentSpec | None = None,
) -> dict[str, float]:
    """Success rate and mean return of ``controller`` behind a perfect link, one episode a seed.

    Each episode is :func:`~codesign_mb.rollout.rollout` behind a perfect link (``q = 1``,
    ``tau = 0``: the tables' ``oracle``) with ``estimator`` (``None``: ideal control, the
    controller sees the plant's observation with the true remote state).
    """
    if not seeds:
        return {}
    base = make_plant(plant)
    env = LinkObservationWrapper(base, BernoulliLink(), StaticQos(1.0, 0))
    est = None if estimator is None else build("estimator", estimator, base)
    successes, returns = [], []
    for s in seeds:
        table = rollout(env, est, controller, seed=s)
        successes.append("success" in table and bool(table["success"].any()))
        total = 0.0
        for reward in table["reward"]:  # summed in step order, as SAC's episode return
            total += float(reward)
        returns.append(total)
    env.close()
    return {"success_rate": float(np.mean(successes)), "mean_return": float(np.mean(returns))}
