"""Consistency of a Gaussian estimator: the normalised estimation error squared (NEES).

A filter that reports the estimate ``x_hat`` with covariance ``P`` is *consistent* when its
error ``e = x_hat - x`` is distributed as ``N(0, P)``; then ``e' P^-1 e`` is chi-square with
``n = dim(e)`` degrees of freedom (Bar-Shalom, Li and Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, 2001, sec. 5.4). An average NEES above ``n`` means
the filter is overconfident (its errors exceed what ``P`` admits), below ``n`` that it is
underconfident.

:func:`nees` computes it for a batch of errors; :func:`nees_band` is the two-sided interval
in which the average of ``N`` independent NEES samples of a consistent filter lies with the
given probability; :func:`has_covariance` tells an estimator that exposes its Gaussian (like
:class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor`: ``state`` and
``covariance`` over the object's position then velocity) from one that does not.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

__all__ = ["has_covariance", "nees", "nees_band"]


def has_covariance(estimator: Any) -> bool:
    """Whether a reset ``estimator`` exposes ``state`` and ``covariance`` (directly or through
    a proxy forwarding attributes; a filter not yet reset may raise on access)."""
    return all(getattr(estimator, name, None) is not None for name in ("state", "covariance"))


def nees(errors: ArrayLike, covariances: ArrayLike) -> NDArray[np.float64]:
    """``e_k' P_k^-1 e_k`` for each row ``e_k`` of ``errors`` (shape ``(N, n)``) and
    ``P_k = covariances[k]`` (shape ``(N, n, n)``, positive definite); shape ``(N,)``."""
    e = np.asarray(errors, dtype=float)
    P = np.asarray(covariances, dtype=float)
    if e.ndim != 2 or P.shape != (*e.shape, e.shape[1]):
        raise ValueError(
            f"errors must have shape (N, n) and covariances (N, n, n), got {e.shape} and {P.shape}"
        )
    if len(e) == 0:
        return np.empty(0)
    return np.einsum("ki,ki->k", e, np.linalg.solve(P, e[..., None])[..., 0])


def nees_band(samples: int, dof: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided ``confidence`` interval of the average of ``samples`` independent NEES
    values of a consistent filter with ``dof`` degrees of freedom.

    Their sum is chi-square with ``dof * samples`` degrees of freedom, so the average lies in
    ``chi2.ppf((a / 2, 1 - a / 2), dof * samples) / samples`` with probability ``1 - a``
    (Bar-Shalom et al., sec. 5.4.2). NaN for no samples.
    """
    if samples < 0 or dof < 1 or not 0.0 < confidence < 1.0:
        raise ValueError(
            f"need samples >= 0, dof >= 1 and confidence in (0, 1), got {samples}, {dof}, "
            f"{confidence}"
        )
    if samples == 0:
        return math.nan, math.nan
    tail = (1.0 - confidence) / 2.0
    low, high = chi2.ppf([tail, 1.0 - tail], dof * samples) / samples
    return float(low), float(high)
