"""The covariance theory of Kalman filtering with intermittent observations.

Sinopoli et al. (2004), "Kalman filtering with intermittent observations", IEEE TAC 49(9):
with arrivals ``gamma_t ~ Bernoulli(q)`` (``eq_d``) the expected error covariance stays
bounded iff ``q > q_c``, with ``1 - 1/max|lambda(A)|^2 <= q_c``, equal when ``C`` is
invertible (:func:`critical_arrival_bounds`); :func:`intermittent_riccati` runs the
covariance recursion for a batch of arrival sequences (Monte-Carlo of ``E[P_t]``),
:func:`expected_covariance_bounds` gives the lower and upper bounds of ``lim E[P_t]`` and
:func:`steady_state_covariance` the stationary covariances with every measurement delivered.
The filter itself is :class:`~codesign_mb.estimation.kalman.IntermittentKalmanFilter`.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike

from codesign_mb.estimation.model_checks import FloatArray, _covariance, _matrix, _model

__all__ = [
    "critical_arrival_bounds",
    "critical_arrival_lower_bound",
    "expected_covariance_bounds",
    "intermittent_riccati",
    "steady_state_covariance",
]


def steady_state_covariance(
    A: ArrayLike, C: ArrayLike, Q: ArrayLike, R: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Stationary prior and posterior error covariances of the Kalman filter (``q = 1``).

    The prior ``P = A P A' + Q - A P C' (C P C' + R)^{-1} C P A'`` (the filter DARE, as in
    ``control.dlqe``) and the posterior ``P - P C' (C P C' + R)^{-1} C P``.

    Returns
    -------
    tuple of ndarray
        ``(prior, posterior)``, each of shape ``(n, n)``.
    """
    A, C, Q, R = _model(A, C, Q, R)
    prior = scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)
    prior = 0.5 * (prior + prior.T)
    PCt = prior @ C.T
    posterior = prior - PCt @ np.linalg.solve(C @ PCt + R, PCt.T)
    return prior, 0.5 * (posterior + posterior.T)


def intermittent_riccati(
    A: ArrayLike,
    C: ArrayLike,
    Q: ArrayLike,
    R: ArrayLike,
    P0: ArrayLike,
    arrivals: ArrayLike,
    *,
    average: bool = False,
) -> tuple[FloatArray, FloatArray]:
    """Error covariances of the filter for a batch of arrival sequences (no delay).

    The random Riccati recursion of Sinopoli et al. (2004) with ``gamma_t`` from ``arrivals``:
    ``P_{t|t} = P_{t|t-1} - gamma_t K_t C P_{t|t-1}`` and ``P_{t+1|t} = A P_{t|t} A' + Q``,
    vectorised over the batch; the same arithmetic as :class:`IntermittentKalmanFilter` fed
    ``z_t`` at ``t`` when ``gamma_t = 1``.

    Parameters
    ----------
    A, C, Q, R:
        The model, as in :class:`IntermittentKalmanFilter`.
    P0:
        Prior covariance of ``x_0``, shape ``(n, n)``.
    arrivals:
        ``gamma``, boolean, shape ``(T,)`` or ``(N, T)`` (``N`` sequences of ``T`` steps).
    average:
        Return the mean over the ``N`` sequences (a Monte-Carlo estimate of ``E[P_t]``)
        instead of every sequence; memory is then independent of ``N``.

    Returns
    -------
    priors : ndarray
        ``P_{t|t-1}`` for ``t = 0..T``, shape ``(N, T + 1, n, n)``; without the leading
        axis when ``arrivals`` is 1-D or ``average`` is set.
    posteriors : ndarray
        ``P_{t|t}`` for ``t = 0..T-1``, shape ``(N, T, n, n)``, likewise.
    """
    A, C, Q, R = _model(A, C, Q, R)
    n = A.shape[0]
    P_init = _covariance("P0", P0, n)
    gamma = np.asarray(arrivals)
    if gamma.dtype != bool:
        if not np.all((gamma == 0) | (gamma == 1)):
            raise ValueError("arrivals must hold booleans (or 0/1)")
        gamma = gamma.astype(bool)
    single = gamma.ndim == 1
    if single:
        gamma = gamma[None, :]
    if gamma.ndim != 2:
        raise ValueError(f"arrivals must have shape (T,) or (N, T), got {gamma.shape}")
    N, T = gamma.shape
    P = np.broadcast_to(P_init, (N, n, n)).copy()
    eye = np.eye(n)
    if average:
        priors = np.empty((T + 1, n, n))
        posteriors = np.empty((T, n, n))
        priors[0] = P_init
    else:
        priors = np.empty((N, T + 1, n, n))
        posteriors = np.empty((N, T, n, n))
        priors[:, 0] = P
    for t in range(T):
        rows = gamma[:, t]
        if rows.any():
            Pg = P[rows]
            PCt = Pg @ C.T
            S = C @ PCt + R
            K = np.swapaxes(np.linalg.solve(S, np.swapaxes(PCt, 1, 2)), 1, 2)
            IKC = eye - K @ C
            Pg = IKC @ Pg @ np.swapaxes(IKC, 1, 2) + K @ R @ np.swapaxes(K, 1, 2)
            P[rows] = 0.5 * (Pg + np.swapaxes(Pg, 1, 2))
        if average:
            posteriors[t] = P.mean(axis=0)
        else:
            posteriors[:, t] = P
        P = A @ P @ A.T + Q
        P = 0.5 * (P + np.swapaxes(P, 1, 2))
        if average:
            priors[t + 1] = P.mean(axis=0)
        else:
            priors[:, t + 1] = P
    if single and not average:
        return priors[0], posteriors[0]
    return priors, posteriors


def critical_arrival_lower_bound(A: ArrayLike) -> float:
    """Sinopoli et al.'s lower bound ``1 - 1/max|lambda_i(A)|^2`` on the critical probability.

    Below it ``E[P_t]`` diverges for some initial condition; 0 for a stable ``A``. Exact (the
    critical value itself) when ``C`` is invertible.
    """
    A = _matrix("A", A)
    rho = float(np.max(np.abs(np.linalg.eigvals(A))))
    return max(0.0, 1.0 - 1.0 / rho**2)


def critical_arrival_bounds(
    A: ArrayLike, C: ArrayLike, *, tol: float = 1e-4, margin: float = 1e-7
) -> tuple[float, float]:
    """Lower and upper bounds on the critical arrival probability ``q_c`` (Sinopoli 2004).

    ``E[P_t]`` is bounded for every initial condition iff ``q > q_c`` (Theorem 2). The lower
    bound is :func:`critical_arrival_lower_bound`; the upper bound is the smallest ``q`` for
    which the LMI of Theorem 5 is feasible::

        Psi_q(Y, Z) = [[Y,              sqrt(q) (Y A + Z C), sqrt(1 - q) Y A],
                       [sqrt(q) (.)',   Y,                   0              ],
                       [sqrt(1 - q) (.)', 0,                 Y              ]] > 0,
        0 <= Y <= I,

    found by bisection to ``tol`` with ``Psi >= margin * I`` standing for the strict
    inequality (cvxpy, Clarabel). Both bounds coincide when ``C`` is invertible.

    Returns
    -------
    tuple of float
        ``(lower, upper)``; ``upper`` is ``inf`` when ``(A, C)`` is not detectable.
    """
    import cvxpy as cp

    A = _matrix("A", A)
    n = A.shape[0]
    if A.shape != (n, n):
        raise ValueError(f"A must be square, got shape {A.shape}")
    C = _matrix("C", C)
    if C.shape[1] != n:
        raise ValueError(f"C must have {n} columns to match A, got shape {C.shape}")
    if not (math.isfinite(tol) and tol > 0.0):
        raise ValueError(f"tol must be > 0, got {tol!r}")
    lower = critical_arrival_lower_bound(A)
    if lower == 0.0:
        return 0.0, 0.0
    p = C.shape[0]
    Y = cp.Variable((n, n), symmetric=True)
    Z = cp.Variable((n, p))
    sq = cp.Parameter(nonneg=True)
    sr = cp.Parameter(nonneg=True)
    zero = np.zeros((n, n))
    gain = Y @ A + Z @ C
    psi = cp.bmat(
        [
            [Y, sq * gain, sr * (Y @ A)],
            [sq * gain.T, Y, zero],
            [sr * (Y @ A).T, zero, Y],
        ]
    )
    psi = 0.5 * (psi + psi.T)
    problem = cp.Problem(
        cp.Minimize(0),
        [psi >> margin * np.eye(3 * n), Y >> 0, np.eye(n) - Y >> 0],
    )

    def feasible(q: float) -> bool:
        sq.value, sr.value = math.sqrt(q), math.sqrt(1.0 - q)
        try:
            problem.solve(solver=cp.CLARABEL)
        except cp.error.SolverError:
            return False
        return problem.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)

    if not feasible(1.0):
        return lower, math.inf
    lo, hi = lower, 1.0
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if feasible(mid):
            hi = mid
        else:
            lo = mid
    return lower, hi


def expected_covariance_bounds(
    A: ArrayLike,
    C: ArrayLike,
    Q: ArrayLike,
    R: ArrayLike,
    q: float,
    *,
    max_iter: int = 100_000,
    rtol: float = 1e-12,
) -> tuple[FloatArray, FloatArray]:
    """Bounds ``S <= lim E[P_{t|t-1}] <= V`` for arrivals ``~ Bernoulli(q)`` (Sinopoli Thm 3-4).

    ``S`` solves ``S = (1 - q) A S A' + Q`` (exists iff ``(1 - q) max|lambda(A)|^2 < 1``);
    ``V`` is the fixed point of the modified algebraic Riccati equation
    ``V = A V A' + Q - q A V C' (C V C' + R)^{-1} C V A'`` reached by iteration from ``Q``.
    A bound that does not exist (the iteration diverges or fails to converge in ``max_iter``
    steps) is returned filled with ``inf``.

    Returns
    -------
    tuple of ndarray
        ``(lower, upper)``, each of shape ``(n, n)``.
    """
    A, C, Q, R = _model(A, C, Q, R)
    q = float(q)
    if not (math.isfinite(q) and 0.0 <= q <= 1.0):
        raise ValueError(f"q must be in [0, 1], got {q!r}")
    n = A.shape[0]
    infinite = np.full((n, n), np.inf)
    rho = float(np.max(np.abs(np.linalg.eigvals(A))))
    if (1.0 - q) * rho**2 < 1.0:
        lower = scipy.linalg.solve_discrete_lyapunov(math.sqrt(1.0 - q) * A, Q)
        lower = 0.5 * (lower + lower.T)
    else:
        lower = infinite.copy()
    V = Q.copy()
    upper = infinite.copy()
    for _ in range(max_iter):
        AV = A @ V
        S = C @ V @ C.T + R
        V_next = AV @ A.T + Q - q * AV @ C.T @ np.linalg.solve(S, C @ AV.T)
        V_next = 0.5 * (V_next + V_next.T)
        size = float(np.max(np.abs(V_next)))
        if not math.isfinite(size) or size > 1e15:
            break
        if np.max(np.abs(V_next - V)) <= rtol * max(1.0, size):
            upper = V_next
            break
        V = V_next
    return lower, upper
