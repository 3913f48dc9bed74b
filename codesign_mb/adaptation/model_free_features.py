"""Model-free extra inputs of the learned QoS policy: what ``(y, zeta)``'s history gives.

The QoS policy of ``eq_q_t_pol2`` sees ``(y_{t-1}, zeta_{t-1})``. :class:`HeldHistoryFeature`
adds what can be computed from the history of that stream alone, without a model of the
object or of the robot's estimator (unlike the hybrid ``predictor_std`` features, which run a
replica of the robot's Kalman predictor at the edge):

* the elapsed time ``t / T`` of the packet (the phase of the pick in time);
* the held object's displacement per second between the last two distinct packets (a finite
  difference of held positions over their stamps ``t - zeta``), over ``speed_scale_mps``;
* the held object's height above its first held height, over ``lift_scale_m`` (the lift,
  seen in ``y``).

The module imports no estimator (a test and the import contracts check it).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["HeldHistoryFeature", "object_position_in_y"]


def object_position_in_y(env: Any, features: str) -> slice:
    """Where the object's position lies in ``y`` (the plant's remote part), for QoS features
    of kind ``features``, which need a plant with an ``object_pos`` and a horizon."""
    plant = env.unwrapped
    layout = getattr(plant, "observation_layout", None) or {}
    if "object_pos" not in layout or getattr(plant, "horizon", None) is None:
        raise ValueError(f"{features} features need a plant with object_pos and a horizon")
    start = layout["object_pos"].start - plant.remote_slice.start
    return slice(start, start + 3)


class HeldHistoryFeature:
    """The model-free QoS features (see the module docstring); ``dim = 1 + 3 + 1``.

    Parameters
    ----------
    position:
        Indices of the object position inside ``y`` (the plant's remote part).
    control_period_s:
        Seconds per step (turns a difference over stamps into a displacement per second).
    horizon:
        Episode length ``T``.
    speed_scale_mps, lift_scale_m:
        Scales of the displacement rate and of the lift.

    Examples
    --------
    >>> f = HeldHistoryFeature(slice(0, 3), control_period_s=0.1, horizon=10)
    >>> f.reset()
    >>> _ = f(np.array([0.0, 0.0, 0.1]), 0)  # the packet of step 0
    >>> f(np.array([0.0, 0.0, 0.1]), 1).round(3).tolist()  # step 1: the same packet, age 1
    [0.1, 0.0, 0.0, 0.0, 0.0]
    >>> f(np.array([0.0, 0.1, 0.1]), 0).round(3).tolist()  # step 2's packet: 0.1 m in 0.2 s
    [0.2, 0.0, 1.0, 0.0, 0.0]
    """

    dim = 5

    def __init__(
        self,
        position: slice,
        *,
        control_period_s: float,
        horizon: int,
        speed_scale_mps: float = 0.5,
        lift_scale_m: float = 0.05,
    ) -> None:
        if not control_period_s > 0:
            raise ValueError(f"control_period_s must be > 0, got {control_period_s!r}")
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        if not (speed_scale_mps > 0 and lift_scale_m > 0):
            raise ValueError("speed_scale_mps and lift_scale_m must be > 0")
        if position.stop - position.start != 3:
            raise ValueError(f"position must have 3 entries, got {position}")
        self.position = position
        self.control_period_s = float(control_period_s)
        self.horizon = int(horizon)
        self.speed_scale_mps = float(speed_scale_mps)
        self.lift_scale_m = float(lift_scale_m)
        self.reset()

    @classmethod
    def from_env(cls, env: Any, **options: Any) -> HeldHistoryFeature:
        """For a plant with an ``object_pos`` in its remote part, a period and a horizon."""
        plant = env.unwrapped
        return cls(
            object_position_in_y(env, "held_history"),
            control_period_s=float(plant.control_period_s),
            horizon=int(plant.horizon),
            **options,
        )

    def reset(self) -> None:
        self._t = 0
        self._stamps: list[int] = []
        self._held: list[NDArray[np.float64]] = []

    def __call__(self, observation: NDArray[np.float64], age: int) -> NDArray[np.float64]:
        t = self._t
        self._t += 1
        stamp = t - int(age)
        position = np.asarray(observation, dtype=float)[self.position]
        if not self._stamps or stamp > self._stamps[-1]:  # a new packet
            self._stamps = [*self._stamps[-1:], stamp]
            self._held = [*self._held[-1:], position.copy()]
            if len(self._stamps) == 1:
                self._first_height = float(position[2])
        rate = np.zeros(3)
        if len(self._stamps) == 2:
            gap_s = (self._stamps[1] - self._stamps[0]) * self.control_period_s
            rate = (self._held[1] - self._held[0]) / gap_s / self.speed_scale_mps
        lift = (float(self._held[-1][2]) - self._first_height) / self.lift_scale_m
        return np.array([t / self.horizon, *rate, lift])
