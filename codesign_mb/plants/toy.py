"""A kinematic pick-and-place toy: the conveyor task without physics, for fast pipeline tests.

The object rides a belt along +x at ``belt_speed_mps``; a point gripper is velocity-controlled
in Cartesian space and closes its fingers when the grip command is positive. Closing within
``grasp_radius_m`` of the object attaches it; the task succeeds while the attached object is
held at least ``lift_height_m`` above the belt. The layout and the ``info`` keys are the ones
of :class:`codesign_mb.plants.conveyor.ConveyorPickPlace`, so every pipeline stage runs on
either env unchanged. It steps in microseconds, so the test suite can train on it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from codesign_mb.core.config import STEPS_CAP, check_range, from_mapping

__all__ = ["ToyConveyor", "ToyConveyorConfig"]


@dataclass(frozen=True)
class ToyConveyorConfig:
    """Parameters of :class:`ToyConveyor` (SI units; one step is ``control_period_s``)."""

    belt_speed_mps: float = 0.2
    control_period_s: float = 0.04
    horizon: int = 100
    max_speed_mps: float = 0.5
    grasp_radius_m: float = 0.03
    lift_height_m: float = 0.08
    spawn_x_range_m: tuple[float, float] = (-0.35, -0.25)
    spawn_y_range_m: tuple[float, float] = (-0.08, 0.08)
    gripper_start_m: tuple[float, float, float] = (0.0, 0.0, 0.15)
    terminate_on_success: bool = False

    def __post_init__(self) -> None:
        if self.belt_speed_mps < 0:
            raise ValueError(f"belt_speed_mps must be >= 0, got {self.belt_speed_mps}")
        if self.control_period_s <= 0:
            raise ValueError(f"control_period_s must be > 0, got {self.control_period_s}")
        check_range("horizon", self.horizon, ge=1, cap=STEPS_CAP)
        if self.max_speed_mps <= 0:
            raise ValueError(f"max_speed_mps must be > 0, got {self.max_speed_mps}")
        for name in ("spawn_x_range_m", "spawn_y_range_m"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name} must be (low, high) with low <= high, got {(lo, hi)}")


class ToyConveyor(gym.Env):
    """Kinematic conveyor pick-and-place; a :class:`~codesign_mb.network.NetworkedPlant`.

    Observation (13,): gripper position (3), gripper velocity (3), finger width (1), object
    position (3), object velocity (3). The object part (7:13) is the remote state. Action
    ``Box(4)`` in [-1, 1]: gripper velocity / ``max_speed_mps`` and the grip (> 0 closes).
    Reward: dense, ``-distance`` plus bonuses for holding and lifting the object.
    """

    metadata = {"render_modes": []}  # noqa: RUF012 (gymnasium convention)

    observation_layout = {  # noqa: RUF012 (read-only by convention, as in the conveyor env)
        "gripper_pos": slice(0, 3),
        "gripper_vel": slice(3, 6),
        "finger_width": slice(6, 7),
        "object_pos": slice(7, 10),
        "object_vel": slice(10, 13),
    }
    remote_slice = slice(7, 13)

    def __init__(self, config: ToyConveyorConfig | None = None, render_mode: None = None) -> None:
        self.config = config or ToyConveyorConfig()
        self.horizon = self.config.horizon
        self.control_period_s = self.config.control_period_s
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(13,), dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        self._grip = np.zeros(3)
        self._grip_vel = np.zeros(3)
        self._obj = np.zeros(3)
        self._obj_vel = np.zeros(3)
        self._width = 1.0
        self._held = False
        self._t = 0

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None = None) -> ToyConveyor:
        """The env from the fields of its :class:`ToyConveyorConfig` (unknown ones are an error)."""
        return cls(
            config=from_mapping(ToyConveyorConfig, dict(options or {}), where="plant.options")
        )

    def remote_prior(self) -> NDArray[np.float64]:
        """The nominal spawn point on the belt, moving at the belt speed."""
        c = self.config
        return np.array(
            [np.mean(c.spawn_x_range_m), np.mean(c.spawn_y_range_m), 0.0, c.belt_speed_mps, 0, 0]
        )

    def _obs(self) -> NDArray[np.float64]:
        return np.concatenate(
            [self._grip, self._grip_vel, [self._width], self._obj, self._obj_vel]
        ).astype(np.float64)

    def _info(self) -> dict[str, Any]:
        distance = float(np.linalg.norm(self._grip - self._obj))
        lifted = bool(self._held and self._obj[2] >= self.config.lift_height_m)
        return {
            "success": lifted,
            "lifted": lifted,
            "object_pos": self._obj.copy(),
            "gripper_object_distance": distance,
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float64], dict[str, Any]]:
        super().reset(seed=seed)
        c = self.config
        self._grip = np.array(c.gripper_start_m, dtype=float)
        self._grip_vel = np.zeros(3)
        self._obj = np.array(
            [
                self.np_random.uniform(*c.spawn_x_range_m),
                self.np_random.uniform(*c.spawn_y_range_m),
                0,
            ]
        )
        self._obj_vel = np.array([c.belt_speed_mps, 0.0, 0.0])
        self._width = 1.0
        self._held = False
        self._t = 0
        return self._obs(), self._info()

    def step(
        self, action: NDArray
    ) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        c = self.config
        a = np.clip(np.asarray(action, dtype=float), -1.0, 1.0)
        dt = c.control_period_s
        self._grip_vel = a[:3] * c.max_speed_mps
        self._grip = self._grip + self._grip_vel * dt
        self._grip[2] = max(self._grip[2], 0.0)
        close = a[3] > 0
        if close and not self._held and self._width > 0.5:
            self._held = bool(np.linalg.norm(self._grip - self._obj) <= c.grasp_radius_m)
        if not close:
            self._held = False
        self._width = 0.0 if close else 1.0
        if self._held:
            self._obj = self._grip.copy()
            self._obj_vel = self._grip_vel.copy()
        else:
            self._obj_vel = (
                np.array([c.belt_speed_mps, 0.0, 0.0])
                if self._obj[2] <= 1e-9
                else (self._obj_vel + np.array([0.0, 0.0, -9.81 * dt]))
            )
            self._obj = self._obj + self._obj_vel * dt
            if self._obj[2] <= 0.0:
                self._obj[2] = 0.0
                self._obj_vel = np.array([c.belt_speed_mps, 0.0, 0.0])
        self._t += 1
        info = self._info()
        reward = -info["gripper_object_distance"] + (0.5 if self._held else 0.0)
        reward += 2.0 if info["success"] else 0.0
        terminated = bool(info["success"] and c.terminate_on_success)
        truncated = self._t >= c.horizon
        return self._obs(), float(reward), terminated, truncated, info
