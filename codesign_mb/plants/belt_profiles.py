"""Belt speed schedules of the conveyor: one seeded speed per control step of an episode.

Three ingredients, each off unless its config field asks for it
(:class:`~codesign_mb.plants.conveyor_config.ConveyorConfig`):

- the episode's *base* speed: ``belt_speed_mps``, or drawn from ``U(belt_speed_range_mps)``;
- the profile: ``"constant"`` (the base speed throughout) or ``"variable"`` (after seeded
  intervals drawn from ``belt_change_steps`` the speed steps to ``base * U(1 - j, 1 + j)``,
  or to 0, a stop, with probability ``belt_stop_probability``);
- with a range, every step stays inside it (a stop excepted).

The paper's plant is the constant profile without a range: ``rng`` is then not used at all,
and the variable profile without a range draws exactly what it always did.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from codesign_mb.plants.conveyor_config import ConveyorConfig

__all__ = ["base_speed", "belt_speed_schedule"]


def base_speed(config: ConveyorConfig, rng: np.random.Generator) -> float:
    """The episode's base speed (m/s): ``belt_speed_mps``, or ``U(low, high)`` with a range.

    Draws from ``rng`` only when ``belt_speed_range_mps`` is set.
    """
    if not config.belt_speed_range_mps:
        return float(config.belt_speed_mps)
    low, high = config.belt_speed_range_mps
    return float(rng.uniform(low, high))


def belt_speed_schedule(config: ConveyorConfig, rng: np.random.Generator) -> NDArray[np.float64]:
    """Belt speed at each control step ``0..horizon`` (m/s) for one episode.

    Constant profile: the base speed (:func:`base_speed`) throughout. Variable profile:
    piecewise constant, starting at the base speed, changing after seeded random intervals
    drawn from ``belt_change_steps`` (see the module docstring).
    """
    n = config.horizon + 1
    base = base_speed(config, rng)
    speeds = np.full(n, base)
    if config.belt_profile == "constant":
        return speeds
    lo, hi = config.belt_change_steps
    bounds = config.belt_speed_range_mps
    t = int(rng.integers(lo, hi + 1))
    while t < n:
        if rng.random() < config.belt_stop_probability:
            speed = 0.0
        else:
            j = config.belt_speed_jitter
            speed = base * float(rng.uniform(1.0 - j, 1.0 + j))
            if bounds:
                speed = min(max(speed, bounds[0]), bounds[1])
        speeds[t:] = speed
        t += int(rng.integers(lo, hi + 1))
    return speeds
