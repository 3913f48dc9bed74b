"""Tracking a remote object with a local actuator: the LQR of the error dynamics.

For :class:`~codesign_mb.plants.belt_tracking.BeltTracking` the tracking error ``e = g - o``
(gripper minus object) follows ``e_{t+1} = A e_t + B u_t - [0, w_t]``: a double integrator
driven by the acceleration. The infinite-horizon LQR of these dynamics for the stage cost
``e' Q e + u' R u`` gives ``u = -K (g - o_hat)``, certainty equivalent in the object's
estimate ``o_hat`` (the remote part of the estimator's output).
"""

from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.control.lqr import LqrController
from codesign_mb.plants.belt_tracking import BeltTracking
from codesign_mb.plants.linear import LinearPlantSpec

__all__ = ["TrackingLqr"]

FloatArray = NDArray[np.float64]


@functools.lru_cache(maxsize=64)
def _gain(
    model: LinearPlantSpec, state_cost: tuple[float, ...], input_cost: tuple[float, ...]
) -> FloatArray:
    """``K`` of ``model``'s LQR (python-control ``dlqr``, ~15 ms: cached per model and costs)."""
    n, m = model.n_states, model.n_inputs
    Q = np.reshape(state_cost, (n, n))
    R = np.reshape(input_cost, (m, m))
    gain = LqrController.for_plant(model, Q, R).gain
    gain.setflags(write=False)
    return gain


class TrackingLqr:
    """``u = -K (g - o_hat)``: the tracking-error LQR (a :class:`~codesign_mb.control.Controller`).

    Parameters
    ----------
    error_model:
        The error dynamics ``e_{t+1} = A e_t + B u_t + w_t`` (``A``, ``B``; the noise does
        not enter the gain).
    state_cost:
        ``Q`` on the error, shape ``(n, n)``, symmetric PSD.
    input_cost:
        ``R`` on the input, shape ``(m, m)``, symmetric positive definite.
    local, remote:
        Where the observation holds ``g`` (the actuator's state) and ``o_hat`` (the estimated
        object); both of ``n`` entries.

    Attributes
    ----------
    gain:
        ``K``, shape ``(m, n)``, from ``control.dlqr`` (read-only).

    Examples
    --------
    >>> from codesign_mb.plants.belt_tracking import BeltTracking
    >>> ctrl = TrackingLqr.for_env(BeltTracking())
    >>> obs = np.array([0.0, 0.0, 0.1, 0.2])  # gripper at rest behind the object
    >>> bool(ctrl.act(obs)[0] > 0)  # accelerate towards it
    True
    """

    def __init__(
        self,
        error_model: LinearPlantSpec,
        state_cost: ArrayLike,
        input_cost: ArrayLike,
        *,
        local: slice,
        remote: slice,
    ) -> None:
        n, m = error_model.n_states, error_model.n_inputs
        Q = np.asarray(state_cost, dtype=float)
        R = np.asarray(input_cost, dtype=float)
        if Q.shape != (n, n) or R.shape != (m, m):
            raise ValueError(
                f"state_cost and input_cost must have shapes {(n, n)} and {(m, m)}, "
                f"got {Q.shape} and {R.shape}"
            )
        for name, part in (("local", local), ("remote", remote)):
            bounded = part.start is not None and part.stop is not None
            if not bounded or part.step not in (None, 1) or part.stop - part.start != n:
                raise ValueError(f"{name} must select {n} entries, got {part!r}")
        self.error_model = error_model
        self.local, self.remote = local, remote
        self.gain: FloatArray = _gain(error_model, tuple(Q.ravel()), tuple(R.ravel()))
        self._minus_gain = -self.gain

    @classmethod
    def for_env(cls, env: gym.Env) -> TrackingLqr:
        """The controller of the :class:`BeltTracking` plant inside ``env`` (wrapped or not)."""
        plant = env.unwrapped
        if not isinstance(plant, BeltTracking):
            raise TypeError(f"env must wrap a BeltTracking plant, got {type(plant).__name__}")
        return cls(
            plant.error_model,
            plant.state_cost,
            plant.input_cost,
            local=plant.local_slice,
            remote=plant.remote_slice,
        )

    def reset(self, *, seed: int | None = None) -> None:
        return None

    def act(self, observation: NDArray[np.float64]) -> FloatArray:
        """``u = -K (g - o_hat)`` for the plant-layout (estimated) observation."""
        return self._minus_gain @ (observation[self.local] - observation[self.remote])
