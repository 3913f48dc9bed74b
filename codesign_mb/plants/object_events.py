"""What happens to the object on the belt besides the belt carrying it: its random start and
spawn time, and small disturbances (it slips or turns).

Used by :class:`~codesign_mb.plants.conveyor.ConveyorPickPlace`; every draw comes from the env's
generator and only for what the config switches on
(:class:`~codesign_mb.plants.conveyor_config.ConveyorConfig`: ``spawn_along_range_m``,
``spawn_delay_steps``, ``disturbance_*``), so the paper's plant draws nothing here.

Spawn time: until step ``k`` (drawn from ``spawn_delay_steps``) the object is parked off the
scene (upstream, beyond the belt's end, out of the arm's reach and of the camera's view); at
``k`` it appears at its start on the belt, moving with it. Disturbances: at every step the
object rests on the belt (spawned, not touched by a finger, within 5 mm of its resting height)
it gets, with probability ``disturbance_probability``, a velocity kick ``N(0, s^2)`` along x
and y and a yaw-rate kick ``N(0, w^2)``; the belt's friction then stops the slip, leaving the
object displaced and turned by a few millimetres and degrees.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from codesign_mb.robot.scene import BELT_HALF_LENGTH, BELT_X

if TYPE_CHECKING:
    from codesign_mb.plants.conveyor_config import ConveyorConfig
    from codesign_mb.robot.simulator import ConveyorSimulator

__all__ = ["PARK_Y_M", "ObjectEvents"]

PARK_Y_M = -(BELT_HALF_LENGTH + 2.0)
"""Where (along y) the object waits before it spawns: 2 m upstream of the belt's end."""

_RESTING_TOLERANCE_M = 0.005


class ObjectEvents:
    """The object's spawn and disturbances in one episode.

    Parameters
    ----------
    config:
        The env's config.
    sim:
        The env's simulator (the object is placed and pushed through it).
    rest_height:
        Height of the object's centre when it rests on the belt (m).
    """

    def __init__(self, config: ConveyorConfig, sim: ConveyorSimulator, rest_height: float) -> None:
        self.config = config
        self.sim = sim
        self.rest_height = float(rest_height)
        self.park = np.array([BELT_X, PARK_Y_M, rest_height])
        self.start = np.array([BELT_X, config.spawn_y_m, rest_height])
        self.spawn_step = 0
        self.disturbances = 0

    def reset(self, rng: np.random.Generator, lateral: float) -> NDArray[np.float64]:
        """Draw this episode's start and spawn step; return where the object is at ``t = 0``.

        ``lateral`` is the offset across the belt (drawn by the env, as in the paper's plant).
        """
        cfg = self.config
        along = 0.0
        if cfg.spawn_along_range_m > 0:
            along = float(rng.uniform(-cfg.spawn_along_range_m, cfg.spawn_along_range_m))
        self.start = np.array([BELT_X + lateral, cfg.spawn_y_m + along, self.rest_height])
        low, high = cfg.spawn_delay_steps
        self.spawn_step = int(rng.integers(low, high + 1)) if high > 0 else 0
        self.disturbances = 0
        return self.start.copy() if self.spawn_step == 0 else self.park.copy()

    def spawned(self, t: int) -> bool:
        """Whether the object is on the scene at step ``t``."""
        return t >= self.spawn_step

    def before_step(self, t: int, rng: np.random.Generator, touched: bool) -> None:
        """Disturb the object (if it rests on the belt) before the physics of step ``t``."""
        cfg = self.config
        if cfg.disturbance_probability <= 0 or not self.spawned(t) or touched:
            return
        if abs(float(self.sim.object_position()[2]) - self.rest_height) > _RESTING_TOLERANCE_M:
            return
        if rng.random() >= cfg.disturbance_probability:
            return
        slip = rng.normal(0.0, cfg.disturbance_speed_std_mps, 2)
        spin = float(rng.normal(0.0, cfg.disturbance_spin_std_radps))
        self.sim.push_object((slip[0], slip[1], 0.0), spin)
        self.disturbances += 1

    def after_step(self, t: int, belt_speed: float) -> None:
        """Keep the object parked before its spawn step; put it on the belt at ``t`` = spawn."""
        if t < self.spawn_step:
            self.sim.place_object(self.park)
        elif t == self.spawn_step and t > 0:
            self.sim.place_object(self.start, (0.0, belt_speed, 0.0))
