"""Model-based estimates of a plant's remote part: extrapolation over the age, and embedding.

:class:`ModelExtrapolation` is the simplest delay compensation: the held observation
``y_t = x_{t - zeta_t}`` (``eq_output``) is propagated over its age with the noise-free model
of the remote state, ``x_hat_t = A^zeta_t y_t`` (losses and latency alike only age it).

:class:`RemotePartEstimator` puts an estimator of the remote part alone (this one, or a
:class:`~codesign_mb.estimation.kalman.KalmanEstimator` of the remote state's
:class:`~codesign_mb.plants.linear.LinearPlantSpec`) into the plant's observation layout, so
that a plant with local, always fresh entries (proprioception) and a remote part gets an
:class:`~codesign_mb.estimation.base.Estimator` that returns its whole observation.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.core.config import as_matrix
from codesign_mb.estimation.base import Estimator, split_networked_observation

__all__ = ["ModelExtrapolation", "RemotePartEstimator"]

FloatArray = NDArray[np.float64]


class ModelExtrapolation:
    """``x_hat_t = A^zeta_t y_t``: the held observation extrapolated over its age.

    An :class:`~codesign_mb.estimation.base.Estimator` for a plant whose observation is all
    remote (e.g. under :class:`RemotePartEstimator`): the input is ``(y_t, zeta_t)``, the
    output ``A^zeta_t y_t``.

    Parameters
    ----------
    A:
        The transition of the remote state per control period, shape ``(n, n)``.

    Examples
    --------
    >>> est = ModelExtrapolation([[1.0, 0.1], [0.0, 1.0]])  # position, velocity; dt = 0.1
    >>> est.reset(np.array([0.0, 2.0, 3.0])).round(6).tolist()  # y = (0, 2) of age 3
    [0.6, 2.0]
    """

    def __init__(self, A: ArrayLike) -> None:
        A_arr = as_matrix("A", A)
        n = A_arr.shape[0]
        if A_arr.shape != (n, n):
            raise ValueError(f"A must be square, got shape {A_arr.shape}")
        self.A = A_arr
        self._powers: list[FloatArray] = [np.eye(n)]  # A^k, grown on demand

    def power(self, age: int) -> FloatArray:
        """``A^age`` (``age >= 0``), cached."""
        if age < 0:
            raise ValueError(f"age must be >= 0, got {age}")
        while len(self._powers) <= age:
            self._powers.append(self.A @ self._powers[-1])
        return self._powers[age]

    def reset(self, observation: NDArray[np.float64]) -> FloatArray:
        return self._extrapolate(observation)

    def estimate(self, observation: NDArray[np.float64], action: NDArray[np.float64]) -> FloatArray:
        return self._extrapolate(observation)

    def _extrapolate(self, observation: NDArray[np.float64]) -> FloatArray:
        y, age = split_networked_observation(observation)
        if y.shape != (self.A.shape[0],):
            raise ValueError(
                f"observation must hold {self.A.shape[0]} entries and the age, got {y.size + 1}"
            )
        return self.power(age) @ y


class RemotePartEstimator:
    """An estimator of the remote part alone, in the plant's observation layout.

    ``inner`` is given ``(y_t, zeta_t)``: the remote part of the networked observation and the
    age. The first ``len(remote)`` entries of its estimate replace ``y_t``; the local entries
    pass through as received (fresh). With a
    :class:`~codesign_mb.estimation.kalman.KalmanEstimator` inside, the remote state must
    start with the measured quantity (``C = [I 0]``), as for the plants of
    :mod:`codesign_mb.plants.linear`.

    Parameters
    ----------
    inner:
        The estimator of the remote part.
    remote:
        The plant's ``remote_slice``.

    Examples
    --------
    >>> est = RemotePartEstimator(ModelExtrapolation([[1.0, 0.1], [0.0, 1.0]]), slice(1, 3))
    >>> est.reset(np.array([5.0, 0.0, 2.0, 3.0])).round(6).tolist()  # local 5, y = (0, 2), age 3
    [5.0, 0.6, 2.0]
    """

    def __init__(self, inner: Estimator, remote: slice) -> None:
        if remote.step not in (None, 1) or remote.start is None or remote.stop is None:
            raise ValueError(f"remote must be a contiguous slice with bounds, got {remote!r}")
        self.inner = inner
        self.remote = remote

    def reset(self, observation: NDArray[np.float64]) -> FloatArray:
        return self._embed(observation, self.inner.reset(self._remote_part(observation)))

    def estimate(self, observation: NDArray[np.float64], action: NDArray[np.float64]) -> FloatArray:
        return self._embed(observation, self.inner.estimate(self._remote_part(observation), action))

    def _remote_part(self, observation: NDArray[np.float64]) -> FloatArray:
        observation = np.asarray(observation, dtype=float)
        return np.append(observation[self.remote], observation[-1])

    def _embed(self, observation: NDArray[np.float64], remote: ArrayLike) -> FloatArray:
        out = np.array(observation[:-1], dtype=float)
        size = len(out[self.remote])
        out[self.remote] = np.asarray(remote, dtype=float)[:size]
        return out
