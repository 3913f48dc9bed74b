"""A scripted pick policy for the conveyor: proof the task is solvable, and a test fixture.

:class:`ScriptedPickController` reads the plant-layout observation of
:class:`~codesign_mb.plants.conveyor.ConveyorPickPlace` (the estimator's output under a
link) and runs four phases, each a proportional law on the TCP velocity with the object's
velocity as feedforward, so the gripper moves with the belt:

1. **approach**: go to ``hover_m`` above the object's predicted position;
2. **descend**: go down to the object's centre height while tracking it;
3. **grip**: keep tracking, close the gripper until the fingers stop on the object;
4. **lift**: go up to ``lift_to_m`` above the belt (horizontal velocity zero), gripper closed.

If the object drops (far from the gripper while lifting) it opens and starts again. Without
perceived velocity (``perceive_velocity=False``) it differences consecutive positions.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from codesign_mb.plants.conveyor import ConveyorConfig, observation_layout
from codesign_mb.plants.toy import ToyConveyor
from codesign_mb.robot.scene import BELT_SURFACE_Z, OBJECTS

__all__ = ["ScriptedPickController", "ToyPickController"]

_APPROACH, _DESCEND, _GRIP, _LIFT = "approach", "descend", "grip", "lift"


class ScriptedPickController:
    """Move above the object, match the belt, descend, grip, lift (a ``Controller``).

    Parameters
    ----------
    config:
        The env's configuration (observation layout, speed scale, object size).
    gain:
        Proportional gain of the position loops (1/s).
    hover_m:
        Approach height above the object's centre (m).
    lift_to_m:
        Final TCP height above the belt surface (m).
    lead_s:
        How far ahead (s) the object's position is predicted with its velocity.

    Examples
    --------
    >>> from codesign_mb.plants.conveyor import ConveyorPickPlace
    >>> env = ConveyorPickPlace()
    >>> policy = ScriptedPickController(env.config)
    >>> obs, info = env.reset(seed=1)
    >>> policy.reset(seed=1)
    >>> action = policy.act(obs)
    """

    def __init__(
        self,
        config: ConveyorConfig | None = None,
        *,
        gain: float = 8.0,
        hover_m: float = 0.06,
        lift_to_m: float = 0.2,
        lead_s: float = 0.0,
    ) -> None:
        self.config = config or ConveyorConfig()
        self.layout = observation_layout(self.config)
        self.gain = float(gain)
        self.hover = float(hover_m)
        self.lift_to = BELT_SURFACE_Z + float(lift_to_m)
        self.lead = float(lead_s)
        self.half_width = OBJECTS[self.config.object].size[0]
        self.phase = _APPROACH
        self._prev_obj: NDArray[np.float64] | None = None
        self._prev_width = np.inf
        self._grip_steps = 0

    @classmethod
    def from_env(cls, env: Any, **kwargs: Any) -> ScriptedPickController:
        """Build for a conveyor env (wrapped or not): its :class:`ConveyorConfig`."""
        config = getattr(getattr(env, "unwrapped", env), "config", None)
        if not isinstance(config, ConveyorConfig):
            raise TypeError(f"from_env needs a ConveyorPickPlace env, got {type(env).__name__}")
        return cls(config, **kwargs)

    def reset(self, *, seed: int | None = None) -> None:
        self.phase = _APPROACH
        self._prev_obj = None
        self._prev_width = np.inf
        self._grip_steps = 0

    def act(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        obs = np.asarray(observation, dtype=float)
        lay = self.layout
        grip = obs[lay["gripper_pos"]]
        width = float(obs[lay["finger_width"]][0])
        obj = obs[lay["object_pos"]]
        if "object_vel" in lay:
            obj_vel = obs[lay["object_vel"]].copy()
        elif self._prev_obj is not None:
            obj_vel = (obj - self._prev_obj) / self.config.control_period_s
        else:
            obj_vel = np.zeros(3)
        self._prev_obj = obj.copy()
        target = obj + obj_vel * self.lead
        error = target - grip
        horizontal = float(np.linalg.norm(error[:2]))
        close = False

        if self.phase == _LIFT and float(np.linalg.norm(obj - grip)) > 0.05:
            self.phase, self._grip_steps = _APPROACH, 0  # dropped: start again
        if self.phase == _APPROACH:
            error[2] += self.hover
            if horizontal < 0.015 and abs(error[2]) < 0.03:
                self.phase = _DESCEND
        if self.phase == _DESCEND:
            if horizontal > 0.04:
                self.phase = _APPROACH
            elif horizontal < 0.008 and abs(error[2]) < 0.006:
                self.phase = _GRIP
        if self.phase == _GRIP:
            close = True
            self._grip_steps += 1
            closed_on_object = width < 2 * self.half_width + 0.004
            stalled = self._prev_width - width < 5e-4
            if (closed_on_object and stalled) or self._grip_steps > 12:
                self.phase = _LIFT
        self._prev_width = width

        if self.phase == _LIFT:
            close = True
            velocity = np.array([0.0, 0.0, self.gain * (self.lift_to - grip[2])])
        else:
            velocity = obj_vel + self.gain * error
            velocity[2] = self.gain * error[2]  # no vertical feedforward (the belt is flat)
        scale = self.config.max_gripper_speed_mps
        action = np.empty(4)
        action[:3] = np.clip(velocity / scale, -1.0, 1.0)
        action[3] = 1.0 if close else -1.0
        return action


class ToyPickController:
    """A scripted pick for :class:`ToyConveyor` (a :class:`~codesign_mb.control.Controller`).

    Moves above the object, descends onto it, closes, lifts. Used as the demonstration
    controller of stage A on the toy and as a reference in tests.
    """

    def __init__(self, max_speed_mps: float = 0.5, control_period_s: float = 0.04) -> None:
        self.max_speed_mps = max_speed_mps
        self.control_period_s = control_period_s
        self._closed = False

    @classmethod
    def from_env(cls, env: gym.Env) -> ToyPickController:
        c = env.unwrapped.config
        return cls(c.max_speed_mps, c.control_period_s)

    def reset(self, *, seed: int | None = None) -> None:
        self._closed = False

    def act(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        lay = ToyConveyor.observation_layout
        grip, obj = observation[lay["gripper_pos"]], observation[lay["object_pos"]]
        vel = observation[lay["object_vel"]]
        target = obj + vel * self.control_period_s
        error = target - grip
        horizontal = float(np.linalg.norm(error[:2]))
        if self._closed:
            if horizontal > 0.05 and grip[2] < 0.02:
                self._closed = False  # missed: open and retry
            command = np.array([0.0, 0.0, 1.0])
        else:
            if horizontal > 0.02:
                error[2] = max(error[2], 0.04 - grip[2])  # stay above until aligned
            command = error / (self.max_speed_mps * self.control_period_s)
            if horizontal < 0.015 and abs(error[2]) < 0.01:
                self._closed = True
            command[:2] += vel[:2] / self.max_speed_mps
        action = np.append(np.clip(command, -1.0, 1.0), 1.0 if self._closed else -1.0)
        return action
