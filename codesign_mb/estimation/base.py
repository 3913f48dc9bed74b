"""The estimator interface ``pi_e`` (``eq_control_estimation``) and the no-estimator baseline."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

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
    """No estimation (kind ``none``): the stale observation is used as if it were current."""

    def reset(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        return split_networked_observation(observation)[0]

    def estimate(
        self, observation: NDArray[np.float64], action: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        return split_networked_observation(observation)[0]
