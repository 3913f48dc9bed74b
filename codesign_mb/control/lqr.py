"""LQR for linear plants; the Riccati cost of certainty-equivalent LQG over the link.

The LQG pair and its cost live in :mod:`codesign_mb.rollout.compose` (they combine this
controller with the Kalman filter of :mod:`codesign_mb.estimation`).

For ``x_{t+1} = A x_t + B u_t + w_t`` (``w_t ~ N(0, W)``) and the stage cost
``x' Q x + u' R u``, the LQR gain ``K`` (python-control ``dlqr``) and the Riccati solution
``S`` give, for ``u_t = -K x_hat_t`` with any estimate whose error ``e_t = x_t - x_hat_t``
is uncorrelated with ``x_hat_t`` (the Kalman conditional mean), the average cost per step::

    J = tr(S W) + tr(K' (R + B' S B) K Sigma),   Sigma = lim E[e_t e_t'] = lim E[P_{t|t}].

The identity follows from completing the square in ``x' S x``; it needs only that the input
reaches the plant (the lossy link is the sensor link). With ``q = 1`` and no delay ``Sigma``
is the stationary posterior covariance of the Kalman filter
(:func:`~codesign_mb.rollout.compose.lqg_average_cost`); under loss or delay pass the
Monte-Carlo ``E[P_{t|t}]`` of
:func:`~codesign_mb.estimation.kalman.intermittent_riccati`.
"""

from __future__ import annotations

import control
import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.plants.linear import LinearPlantEnv, LinearPlantSpec

__all__ = ["LqrController"]

FloatArray = NDArray[np.float64]


def _matrix(name: str, value: ArrayLike, shape: tuple[int, int]) -> FloatArray:
    out = np.array(value, dtype=float)
    if out.ndim == 0:
        out = out.reshape(1, 1)
    if out.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} must be finite")
    return out


class LqrController:
    """The infinite-horizon discrete LQR ``u = -K x`` (a :class:`~codesign_mb.control.Controller`).

    Parameters
    ----------
    A:
        State matrix, shape ``(n, n)``.
    B:
        Input matrix, shape ``(n, m)``.
    state_cost:
        ``Q``, shape ``(n, n)``, symmetric PSD.
    input_cost:
        ``R``, shape ``(m, m)``, symmetric positive definite.

    Attributes
    ----------
    gain:
        ``K``, shape ``(m, n)``, from ``control.dlqr``.
    riccati:
        ``S``, shape ``(n, n)``: ``x' S x`` is the optimal cost-to-go without noise.
    closed_loop_poles:
        Eigenvalues of ``A - B K``.

    Examples
    --------
    >>> ctrl = LqrController([[1.2]], [[1.0]], [[1.0]], [[1.0]])
    >>> ctrl.act([1.0]).round(4).tolist()
    [-0.7935]
    """

    def __init__(
        self, A: ArrayLike, B: ArrayLike, state_cost: ArrayLike, input_cost: ArrayLike
    ) -> None:
        A_arr = np.array(A, dtype=float)
        if A_arr.ndim == 0:
            A_arr = A_arr.reshape(1, 1)
        if A_arr.ndim != 2 or A_arr.shape[0] != A_arr.shape[1]:
            raise ValueError(f"A must be square, got shape {A_arr.shape}")
        n = A_arr.shape[0]
        A_arr = _matrix("A", A_arr, (n, n))
        B_arr = np.array(B, dtype=float)
        if B_arr.ndim == 0:
            B_arr = B_arr.reshape(1, 1)
        if B_arr.ndim != 2 or B_arr.shape[0] != n:
            raise ValueError(f"B must have shape ({n}, m) to match A, got {B_arr.shape}")
        m = B_arr.shape[1]
        B_arr = _matrix("B", B_arr, (n, m))
        Q = _matrix("state_cost", state_cost, (n, n))
        R = _matrix("input_cost", input_cost, (m, m))
        if not np.allclose(Q, Q.T) or np.min(np.linalg.eigvalsh(Q)) < -1e-12:
            raise ValueError("state_cost must be symmetric positive semidefinite")
        if not np.allclose(R, R.T) or np.min(np.linalg.eigvalsh(R)) <= 0.0:
            raise ValueError("input_cost must be symmetric positive definite")
        try:
            K, S, E = control.dlqr(A_arr, B_arr, Q, R)
        except (ValueError, np.linalg.LinAlgError, control.ControlArgument) as exc:
            raise ValueError(f"no stabilising LQR gain for (A, B, state_cost): {exc}") from exc
        self.A, self.B = A_arr, B_arr
        self.state_cost, self.input_cost = Q, R
        self.gain: FloatArray = np.asarray(K, dtype=float)
        self.riccati: FloatArray = np.asarray(S, dtype=float)
        self.closed_loop_poles: NDArray[np.complex128] = np.asarray(E)

    @classmethod
    def for_plant(
        cls, plant: LinearPlantSpec, state_cost: ArrayLike, input_cost: ArrayLike
    ) -> LqrController:
        """The LQR of ``plant`` for the stage cost ``x' Q x + u' R u``."""
        return cls(plant.A, plant.B, state_cost, input_cost)

    @classmethod
    def for_env(cls, env: gym.Env) -> LqrController:
        """The LQR of the :class:`LinearPlantEnv` inside ``env`` for its own stage cost."""
        plant_env = env.unwrapped
        if not isinstance(plant_env, LinearPlantEnv):
            raise TypeError(f"env must wrap a LinearPlantEnv, got {type(plant_env).__name__}")
        return cls.for_plant(plant_env.plant, plant_env.state_cost, plant_env.input_cost)

    def reset(self, *, seed: int | None = None) -> None:
        return None

    def act(self, observation: NDArray[np.float64]) -> FloatArray:
        """``u = -K x`` for the state (estimate) ``observation``, shape ``(n,)``."""
        x = np.asarray(observation, dtype=float).reshape(-1)
        if x.shape != (self.A.shape[0],):
            raise ValueError(f"observation must have {self.A.shape[0]} entries, got {x.size}")
        return -self.gain @ x
