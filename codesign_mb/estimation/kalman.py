"""Kalman filtering with lost and delayed observations: the delay-compensating predictor.

The robot receives ``y_t = z_{t - zeta_t}`` (``eq_output``), the freshest measurement that has
arrived over the link, with its age ``zeta_t`` (``eq_time``). For the linear-Gaussian model::

    x_{t+1} = A x_t + B u_t + w_t,   w_t ~ N(0, Q)
    z_t     = C x_t + v_t,           v_t ~ N(0, R)

the conditional mean given everything that has arrived is computed by
:class:`IntermittentKalmanFilter`: a step without a new measurement is a prediction only; a
measurement stamped ``s = t - zeta`` corrects the estimate of ``x_s`` and is propagated to
``t`` by re-filtering the stored inputs; one older than a measurement already used (out of
sequence) is handled the same way, so the result equals filtering all data in time order.
(``Q``, ``R`` are the noise covariances here, as in Sinopoli et al. (2004); the plants and
the LQR use ``W``, ``V`` for the noises and ``Q``, ``R`` for the costs.)

The theory of Sinopoli et al. (2004), "Kalman filtering with intermittent observations",
IEEE TAC 49(9), is in :mod:`codesign_mb.estimation.riccati` (re-exported here): with arrivals
``gamma_t ~ Bernoulli(q)`` (``eq_d``) the expected error covariance stays bounded iff
``q > q_c``, with ``1 - 1/max|lambda(A)|^2 <= q_c``, equal when ``C`` is invertible
(:func:`critical_arrival_bounds`); :func:`intermittent_riccati` runs the covariance recursion
for a batch of arrival sequences (Monte-Carlo of ``E[P_t]``), and
:func:`expected_covariance_bounds` gives the lower and upper bounds of ``lim E[P_t]``.

:class:`KalmanEstimator` is the filter behind the :class:`~codesign_mb.estimation.Estimator`
protocol, for a :class:`~codesign_mb.plants.linear.LinearPlantEnv` seen through a
:class:`~codesign_mb.network.LinkObservationWrapper`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.estimation.base import split_networked_observation
from codesign_mb.estimation.model_checks import _covariance, _matrix, _model, _vector
from codesign_mb.estimation.riccati import (
    critical_arrival_bounds,
    critical_arrival_lower_bound,
    expected_covariance_bounds,
    intermittent_riccati,
    steady_state_covariance,
)
from codesign_mb.network.link import PRIOR_TIMESTAMP
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.linear import LinearPlantEnv, LinearPlantSpec

__all__ = [
    "IntermittentKalmanFilter",
    "KalmanEstimator",
    "critical_arrival_bounds",
    "critical_arrival_lower_bound",
    "expected_covariance_bounds",
    "intermittent_riccati",
    "steady_state_covariance",
]

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------- filter maths


def _predict(
    x: FloatArray,
    P: FloatArray,
    A: FloatArray,
    Q: FloatArray,
    B: FloatArray | None,
    u: FloatArray | None,
) -> tuple[FloatArray, FloatArray]:
    """Time update ``x+ = A x + B u``, ``P+ = A P A' + Q``."""
    x = A @ x
    if B is not None and u is not None:
        x = x + B @ u
    P = A @ P @ A.T + Q
    return x, 0.5 * (P + P.T)


def _correct(
    x: FloatArray, P: FloatArray, z: FloatArray, C: FloatArray, R: FloatArray, eye: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Measurement update with the Joseph form (symmetric, PSD under rounding)."""
    K, P = _gain_and_covariance(P, C, R, eye)
    return x + K @ (z - C @ x), P


def _gain_and_covariance(
    P: FloatArray, C: FloatArray, R: FloatArray, eye: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The gain ``K`` and the covariance of :func:`_correct` (they depend on ``P`` only)."""
    PCt = P @ C.T
    S = C @ PCt + R
    K = np.asarray(np.linalg.solve(S, PCt.T).T, dtype=np.float64)  # P C' S^{-1}, S symmetric
    IKC = eye - K @ C
    P = IKC @ P @ IKC.T + K @ R @ K.T
    return K, 0.5 * (P + P.T)


@dataclass(slots=True)
class _Step:
    """What the filter keeps of one step to re-filter from it."""

    t: int
    x_prior: FloatArray
    P_prior: FloatArray
    measurements: list[FloatArray] = field(default_factory=list)
    A: FloatArray | None = None  # transition used to leave this step (set by predict)
    Q: FloatArray | None = None
    u: FloatArray | None = None


class IntermittentKalmanFilter:
    """A Kalman filter for lost, delayed and out-of-sequence measurements.

    Model ``x_{t+1} = A x_t + B u_t + w_t``, ``w_t ~ N(0, Q)``; measurement
    ``z_s = C x_s + v_s``, ``v_s ~ N(0, R)``, which may arrive at any ``t >= s`` or never.

    Parameters
    ----------
    A:
        State matrix, shape ``(n, n)``; :meth:`predict` may override it per step.
    C:
        Measurement matrix, shape ``(p, n)``.
    Q:
        Process-noise covariance, shape ``(n, n)``, symmetric PSD.
    R:
        Measurement-noise covariance, shape ``(p, p)``, symmetric PSD (``C P C' + R`` must be
        invertible at every update).
    B:
        Input matrix, shape ``(n, m)`` (a 1-D array is a column), or ``None`` without inputs.
    max_delay_steps:
        How far back a measurement can still be incorporated exactly: the filter keeps the
        priors, inputs and measurements of the last ``max_delay_steps + 1`` steps.

    Raises
    ------
    ValueError
        When a matrix has the wrong shape, is not finite or a covariance is not symmetric
        PSD; the message names the matrix.

    Notes
    -----
    Timeline: :meth:`reset` sets the prior of ``x_0`` (``t = 0``); :meth:`update` with
    ``timestamp = t`` is the usual correction; :meth:`predict` moves to ``t + 1``. A lost
    measurement is simply never given (prediction only). :attr:`x`, :attr:`P` are the mean and
    covariance of ``x_t`` given every measurement incorporated so far. An update with
    ``timestamp = s < t`` inserts the measurement at step ``s`` (after those already there)
    and re-runs the filter from the stored prior of ``s`` with the stored inputs, so the
    result equals filtering all measurements in time order. Cost: ``O(t - s)`` steps.

    Examples
    --------
    >>> kf = IntermittentKalmanFilter(A=1.2, C=1.0, Q=1.0, R=1.0)
    >>> kf.reset([0.0], [[1.0]])
    >>> kf.update([0.5], timestamp=0)
    True
    >>> kf.predict()
    >>> kf.t, kf.x.round(3).tolist(), kf.P.round(3).tolist()
    (1, [0.3], [[1.72]])
    """

    def __init__(
        self,
        A: ArrayLike,
        C: ArrayLike,
        Q: ArrayLike,
        R: ArrayLike,
        B: ArrayLike | None = None,
        *,
        max_delay_steps: int = 64,
    ) -> None:
        self.A, self.C, self.Q, self.R = _model(A, C, Q, R)
        n = self.A.shape[0]
        if B is None:
            self.B: FloatArray | None = None
        else:
            B_arr = np.asarray(B, dtype=float)
            if B_arr.ndim == 1:
                B_arr = B_arr.reshape(-1, 1)
            self.B = _matrix("B", B_arr)
            if self.B.shape[0] != n:
                raise ValueError(f"B must have {n} rows to match A, got shape {self.B.shape}")
        if (
            isinstance(max_delay_steps, bool)
            or int(max_delay_steps) != max_delay_steps
            or max_delay_steps < 0
        ):
            raise ValueError(f"max_delay_steps must be an integer >= 0, got {max_delay_steps!r}")
        self.max_delay_steps = int(max_delay_steps)
        self._eye = np.eye(n)
        self._memo_predict: dict[tuple[bool, bytes], FloatArray] = {}
        self._memo_correct: dict[tuple[bool, bytes], tuple[FloatArray, FloatArray]] = {}
        self._history: deque[_Step] = deque(maxlen=self.max_delay_steps + 1)
        self._x: FloatArray | None = None
        self._P: FloatArray | None = None
        self._t = 0
        self._n_dropped = 0
        self._innovation: tuple[FloatArray, FloatArray, FloatArray] | None = None

    @property
    def n_states(self) -> int:
        """State dimension ``n``."""
        return self.A.shape[0]

    @property
    def n_outputs(self) -> int:
        """Measurement dimension ``p``."""
        return self.C.shape[0]

    @property
    def n_inputs(self) -> int:
        """Input dimension ``m`` (0 without ``B``)."""
        return 0 if self.B is None else self.B.shape[1]

    @property
    def t(self) -> int:
        """The current step: :attr:`x` estimates ``x_t``."""
        return self._t

    @property
    def x(self) -> FloatArray:
        """Conditional mean of ``x_t``, shape ``(n,)`` (a copy)."""
        self._require_reset()
        assert self._x is not None
        return self._x.copy()

    @property
    def P(self) -> FloatArray:
        """Error covariance of :attr:`x`, shape ``(n, n)`` (a copy)."""
        self._require_reset()
        assert self._P is not None
        return self._P.copy()

    @property
    def oldest_timestamp(self) -> int:
        """The oldest measurement timestamp :meth:`update` can still incorporate."""
        return self._history[0].t if self._history else 0

    @property
    def n_dropped(self) -> int:
        """Measurements refused since :meth:`reset` because they were older than the window."""
        return self._n_dropped

    @property
    def last_nis(self) -> float:
        """Normalised innovation squared of the last incorporated measurement (NaN before any).

        ``nu' S^{-1} nu`` with ``nu = z - C x_s^-`` and ``S = C P_s^- C' + R``, against the prior
        at the measurement's own step ``s`` (so a delayed packet is judged by what the filter
        expected of that step). For a consistent filter it is chi-square with ``p`` degrees of
        freedom. Computed on demand: the filter's hot path only keeps references.
        """
        if self._innovation is None:
            return math.nan
        z, x, P = self._innovation
        nu = z - self.C @ x
        S = self.C @ P @ self.C.T + self.R
        return float(nu @ np.linalg.solve(S, nu))

    def reset(self, x0: ArrayLike, P0: ArrayLike) -> None:
        """Start at ``t = 0`` from the prior ``x_0 ~ N(x0, P0)``.

        Parameters
        ----------
        x0:
            Prior mean, shape ``(n,)``.
        P0:
            Prior covariance, shape ``(n, n)``, symmetric PSD.
        """
        n = self.n_states
        x = _vector("x0", x0, n)
        P = _covariance("P0", P0, n)
        self._history.clear()
        self._history.append(_Step(0, x, P))
        self._x, self._P = x, P
        self._t = 0
        self._n_dropped = 0
        self._innovation = None

    def predict(
        self,
        u: ArrayLike | None = None,
        *,
        A: ArrayLike | None = None,
        Q: ArrayLike | None = None,
    ) -> None:
        """Move from ``t`` to ``t + 1`` with the input ``u_t`` (zero when ``None``).

        Parameters
        ----------
        u:
            The input applied during ``[t, t + 1)``, shape ``(m,)``; needs ``B``.
        A, Q:
            Time-varying model: the transition and process-noise covariance of this step only
            (default: the constructor's). They are stored, so re-filtering uses them again.
        """
        self._require_reset()
        n = self.n_states
        u_t = None
        if u is not None:
            if self.B is None:
                raise ValueError("u was given but the filter has no input matrix B")
            u_t = _vector("u", u, self.B.shape[1])
        A_t = self.A if A is None else _matrix("A", A, (n, n))
        Q_t = self.Q if Q is None else _covariance("Q", Q, n)
        step = self._history[-1]
        step.A, step.Q, step.u = A_t, Q_t, u_t
        assert self._x is not None and self._P is not None
        self._x, self._P = self._time_update(self._x, self._P, A_t, Q_t, u_t)
        self._t += 1
        self._history.append(_Step(self._t, self._x, self._P))

    def update(self, z: ArrayLike, timestamp: int) -> bool:
        """Incorporate the measurement ``z = C x_timestamp + v``.

        Parameters
        ----------
        z:
            The measurement, shape ``(p,)``.
        timestamp:
            Its capture step ``s`` with ``0 <= s <= t``; ``t - s`` is its age ``zeta``.

        Returns
        -------
        bool
            ``True`` when incorporated; ``False`` when ``s`` is older than
            :attr:`oldest_timestamp` (outside the ``max_delay_steps`` window): the
            measurement is dropped and counted in :attr:`n_dropped`.

        Raises
        ------
        ValueError
            When ``timestamp`` is not an integer in ``[0, t]`` or ``z`` has the wrong shape.
        """
        self._require_reset()
        z_arr = _vector("z", z, self.n_outputs)
        if isinstance(timestamp, bool) or int(timestamp) != timestamp:
            raise ValueError(f"timestamp must be an integer, got {timestamp!r}")
        s = int(timestamp)
        if s > self._t:
            raise ValueError(f"timestamp must be <= t = {self._t} (no future data), got {s}")
        if s < 0:
            raise ValueError(f"timestamp must be >= 0, got {s}")
        first = self._history[0].t
        if s < first:
            self._n_dropped += 1
            return False
        k = s - first
        step = self._history[k]
        self._innovation = (z_arr, step.x_prior, step.P_prior)
        step.measurements.append(z_arr)
        if s == self._t:
            assert self._x is not None and self._P is not None
            self._x, self._P = self._measurement_update(self._x, self._P, z_arr)
        else:
            self._refilter(k)
        return True

    def _refilter(self, k: int) -> None:
        """Re-run the filter from the stored prior of history entry ``k`` to the present."""
        steps = self._history
        x, P = steps[k].x_prior, steps[k].P_prior
        last = len(steps) - 1
        for j in range(k, last + 1):
            step = steps[j]
            if j > k:
                step.x_prior, step.P_prior = x, P
            for z in step.measurements:
                x, P = self._measurement_update(x, P, z)
            if j < last:
                assert step.A is not None and step.Q is not None
                x, P = self._time_update(x, P, step.A, step.Q, step.u)
        self._x, self._P = x, P

    # The covariance recursion depends on P only (for the constructor's A, Q and the fixed C,
    # R), and the same P recurs: across episodes with the same prior and deliveries, and at
    # the floating-point fixed point of the Riccati map. Its results are memoised by the
    # exact bytes of P, so a hit returns what the computation would (the mean is always
    # computed).
    _MEMO_SIZE = 4096

    def _memo_key(self, P: FloatArray) -> tuple[bool, bytes]:
        return bool(P.flags.c_contiguous), P.tobytes()

    def _time_update(
        self, x: FloatArray, P: FloatArray, A: FloatArray, Q: FloatArray, u: FloatArray | None
    ) -> tuple[FloatArray, FloatArray]:
        """:func:`_predict`, with ``P+`` memoised for the constructor's ``A`` and ``Q``."""
        if A is not self.A or Q is not self.Q:
            return _predict(x, P, A, Q, self.B, u)
        key = self._memo_key(P)
        P_next = self._memo_predict.get(key)
        if P_next is None:
            x, P_next = _predict(x, P, A, Q, self.B, u)
            if len(self._memo_predict) >= self._MEMO_SIZE:
                self._memo_predict.clear()
            self._memo_predict[key] = P_next
            return x, P_next
        x = A @ x
        if self.B is not None and u is not None:
            x = x + self.B @ u
        return x, P_next

    def _measurement_update(
        self, x: FloatArray, P: FloatArray, z: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """:func:`_correct`, with the gain and ``P+`` memoised."""
        key = self._memo_key(P)
        hit = self._memo_correct.get(key)
        if hit is None:
            hit = _gain_and_covariance(P, self.C, self.R, self._eye)
            if len(self._memo_correct) >= self._MEMO_SIZE:
                self._memo_correct.clear()
            self._memo_correct[key] = hit
        K, P_next = hit
        return x + K @ (z - self.C @ x), P_next

    def _require_reset(self) -> None:
        if self._x is None:
            raise RuntimeError("call reset(x0, P0) first")


# --------------------------------------------------------------------------- estimator


class KalmanEstimator:
    """The :class:`IntermittentKalmanFilter` as an :class:`~codesign_mb.estimation.Estimator`.

    For a :class:`~codesign_mb.plants.linear.LinearPlantEnv` behind a
    :class:`~codesign_mb.network.LinkObservationWrapper`: the networked observation is
    ``(y_t, zeta_t)`` with ``y_t = z_{t - zeta_t}`` (``eq_output``). A timestamp
    ``t - zeta_t`` newer than the last one used means a new measurement, which updates the
    filter at that step (``eq_time``); the applied action drives the prediction.

    Parameters
    ----------
    plant:
        The plant model (``A``, ``B``, ``C``, ``W``, ``V``).
    x0_mean, x0_cov:
        Prior of ``x_0``, shapes ``(n,)`` and ``(n, n)``.
    max_delay_steps:
        The filter's re-filtering window.
    link_wrapper:
        When given, every packet that arrived at a step (``Reception.arrivals`` of
        ``link_wrapper.last_reception``) is incorporated, including out-of-sequence ones
        that the observation hides because a fresher packet arrived first.

    Notes
    -----
    The returned estimate is the state estimate ``x_hat_{t|t}`` (shape ``(n,)``): for a
    linear plant the ideal controller (LQR) acts on the state, and the remote quantity the
    measurement carries is the state. With the factories' ``C = [I_p 0]`` its first ``p``
    entries estimate the noise-free measurement, which the rollout compares with ``z_t``.
    """

    def __init__(
        self,
        plant: LinearPlantSpec,
        *,
        x0_mean: ArrayLike,
        x0_cov: ArrayLike,
        max_delay_steps: int = 64,
        link_wrapper: LinkObservationWrapper | None = None,
    ) -> None:
        self.plant = plant
        self.filter = IntermittentKalmanFilter(
            plant.A, plant.C, plant.W, plant.V, plant.B, max_delay_steps=max_delay_steps
        )
        self.x0_mean = _vector("x0_mean", x0_mean, plant.n_states)
        self.x0_cov = _covariance("x0_cov", x0_cov, plant.n_states)
        self.link_wrapper = link_wrapper
        self._t = 0
        self._last_timestamp = PRIOR_TIMESTAMP

    @classmethod
    def for_env(
        cls, env: gym.Env, *, max_delay_steps: int = 64, use_arrivals: bool = True
    ) -> KalmanEstimator:
        """The estimator matched to ``env``: its plant and initial-state distribution.

        ``env`` is a :class:`LinearPlantEnv` or a wrapper chain around one; with
        ``use_arrivals`` and a :class:`LinkObservationWrapper` in the chain, every arrived
        packet is used (see ``link_wrapper``).
        """
        plant_env = env.unwrapped
        if not isinstance(plant_env, LinearPlantEnv):
            raise TypeError(f"env must wrap a LinearPlantEnv, got {type(plant_env).__name__}")
        wrapper = None
        if use_arrivals:
            layer: gym.Env = env
            while isinstance(layer, gym.Wrapper):
                if isinstance(layer, LinkObservationWrapper):
                    wrapper = layer
                    break
                layer = layer.env
        return cls(
            plant_env.plant,
            x0_mean=plant_env.x0_mean,
            x0_cov=plant_env.x0_cov,
            max_delay_steps=max_delay_steps,
            link_wrapper=wrapper,
        )

    def reset(self, observation: NDArray[np.float64]) -> FloatArray:
        self.filter.reset(self.x0_mean, self.x0_cov)
        self._t = 0
        self._last_timestamp = PRIOR_TIMESTAMP
        self._ingest(observation)
        return self.filter.x

    def estimate(self, observation: NDArray[np.float64], action: NDArray[np.float64]) -> FloatArray:
        self.filter.predict(action)
        self._t += 1
        self._ingest(observation)
        return self.filter.x

    def _ingest(self, observation: NDArray[np.float64]) -> None:
        y, age = split_networked_observation(observation)
        if self.link_wrapper is not None:
            rx = self.link_wrapper.last_reception
            if rx is None or rx.t != self._t:
                raise RuntimeError(
                    "link_wrapper's last reception is not the current step; pass the wrapper "
                    "the rollout steps, or none"
                )
            for packet in rx.arrivals:
                if packet.timestamp >= 0:
                    self.filter.update(packet.value, packet.timestamp)
            return
        timestamp = self._t - age  # eq_time
        if timestamp > self._last_timestamp:
            self.filter.update(y, timestamp)
            self._last_timestamp = timestamp
