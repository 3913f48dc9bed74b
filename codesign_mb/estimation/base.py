"""The estimator interface ``pi_e`` (``eq_control_estimation``) and the no-estimator baseline."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

__all__ = ["Estimator", "PassThroughEstimator", "split_networked_observation"]


def split_networked_observation(
    observation: NDArray[np.float64],
) -> tuple[NDArray[np.float64], int]:
    """Split a :class:`~codesign_mb.network.LinkObservationWrapper` observation.

    Returns the plant-layout observation (remote part = ``y_t``) and the age ``zeta_t``.
    """
    observation = np.asarray(observation, dtype=float)
    return observation[:-1], round(float(observation[-1]))  # np.rint: half to even


@runtime_checkable
class Estimator(Protocol):
    """Turns a networked observation into the ideal controller's observation.

    Input: the :class:`~codesign_mb.network.LinkObservationWrapper` observation, i.e. the plant's
    observation whose remote part is ``y_t = x_{t - zeta_t}``, followed by the age ``zeta_t``.
    Output: the plant's observation layout with the remote part replaced by the estimate
    ``x_hat_t``, so that ``controller.act(estimator.estimate(...))`` is ``eq_c_pol2``.
    """

    def reset(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        """Start an episode from its first networked observation; return the first estimate."""
        ...

    def estimate(
        self, observation: NDArray[np.float64], action: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Estimate after ``action`` was applied and ``observation`` received."""
        ...


class PassThroughEstimator:
    """No estimation (kind ``none``): the stale observation is used as if it were current.

    With ``nominal_velocity`` (3 numbers) that is appended to it: for a plant whose packet
    carries no velocity, where its ``state_layout`` puts ``object_vel``, so a controller that
    reads the state layout (a learned one) gets what the robot assumes without estimation, the
    nominal belt velocity (:meth:`from_env`); the MPC assumes the same when the slot is absent.
    """

    def __init__(self, nominal_velocity: Any = None) -> None:
        self.nominal_velocity = (
            None if nominal_velocity is None else np.asarray(nominal_velocity, float).reshape(3)
        )

    @classmethod
    def from_env(cls, env: Any, *, nominal_velocity: bool = False) -> PassThroughEstimator:
        """For a plant: with ``nominal_velocity``, its nominal belt velocity is appended when
        its ``state_layout`` has an ``object_vel`` its observation lacks (else nothing is)."""
        if not nominal_velocity:
            return cls()
        plant = env.unwrapped
        state = getattr(plant, "state_layout", None) or {}
        observed = getattr(plant, "observation_layout", None) or {}
        lacks = "object_vel" in state and "object_vel" not in observed
        if lacks:
            return cls(np.asarray(plant.belt_velocity, dtype=float))
        return cls()

    def reset(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        return self._output(observation)

    def estimate(
        self, observation: NDArray[np.float64], action: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        return self._output(observation)

    def _output(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        held = split_networked_observation(observation)[0]
        if self.nominal_velocity is None:
            return held
        return np.concatenate([held, self.nominal_velocity])
