"""Stage A's training aids around SB3's SAC: reward shaping, belt-speed curriculum, actor pacing.

Plain SB3 usage (gymnasium wrappers and callbacks), no RL algorithm: the shaped reward and
the early-grip penalty (:class:`Shaping`), the curriculum over belt speeds
(:class:`SpeedSwitch` + :class:`Curriculum`), critic-only updates for a while
(:class:`FreezeActor`) and a smaller actor learning rate (:func:`scale_actor_learning_rate`).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from codesign_mb.core.registry import PlantSpec, make_plant

__all__ = [
    "Curriculum",
    "FreezeActor",
    "Shaping",
    "SpeedSwitch",
    "curriculum_schedule",
    "plant_at_speed",
    "scale_actor_learning_rate",
    "speed_at",
]


def curriculum_schedule(
    plant: PlantSpec, speeds: tuple[float, ...], total_steps: int
) -> list[tuple[int, float]]:
    """``(start step, belt speed)`` pairs: ``speeds`` then the plant's own, equal shares.

    Empty without ``speeds``; ``ValueError`` when the plant sets no ``belt_speed_mps``.
    """
    if not speeds:
        return []
    final_speed = plant.options.get("belt_speed_mps")
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
    """``plant`` with its ``belt_speed_mps`` option set to ``speed`` (m/s)."""
    return replace(plant, options={**plant.options, "belt_speed_mps": float(speed)})


class Curriculum(BaseCallback):
    """Switch the training env's belt speed at fixed step counts (applied at the next reset)."""

    def __init__(self, schedule: list[tuple[int, float]]) -> None:
        super().__init__()
        self.schedule = schedule

    def _on_step(self) -> bool:
        self.training_env.env_method("set_belt_speed", speed_at(self.schedule, self.num_timesteps))
        return True


class FreezeActor(BaseCallback):
    """Keep SAC's actor frozen (critic-only updates) until ``until`` env steps."""

    def __init__(self, until: int) -> None:
        super().__init__()
        self.until = int(until)
        self._frozen: bool | None = None

    def _set(self, frozen: bool) -> None:
        if frozen != self._frozen:
            for p in self.model.actor.parameters():
                p.requires_grad_(not frozen)
            self._frozen = frozen

    def _on_training_start(self) -> None:
        self._set(self.num_timesteps < self.until)

    def _on_step(self) -> bool:
        self._set(self.num_timesteps < self.until)
        return True

    def _on_training_end(self) -> None:
        self._set(False)


def scale_actor_learning_rate(model: Any, scale: float) -> None:
    """Make SB3's per-update learning-rate setting give the actor ``scale`` times the rate."""
    import types

    from stable_baselines3.common.utils import update_learning_rate

    if scale == 1.0:
        return
    base = model._update_learning_rate

    def _update(self: Any, optimizers: Any) -> None:
        base(optimizers)
        rate = self.lr_schedule(self._current_progress_remaining) * scale
        update_learning_rate(self.actor.optimizer, rate)

    model._update_learning_rate = types.MethodType(_update, model)


class SpeedSwitch(gym.Wrapper):
    """Rebuild the plant with another belt speed at the next reset (for the curriculum)."""

    def __init__(self, plant: PlantSpec) -> None:
        super().__init__(make_plant(plant))
        self._plant = plant
        self._speed = plant.options.get("belt_speed_mps")
        self._pending: float | None = None

    def set_belt_speed(self, speed: float) -> None:
        if speed != self._speed:
            self._pending = speed

    def reset(self, **kwargs: Any) -> Any:
        if self._pending is not None:
            self.env.close()
            self.env = make_plant(plant_at_speed(self._plant, self._pending))
            self._speed, self._pending = self._pending, None
        return self.env.reset(**kwargs)


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
