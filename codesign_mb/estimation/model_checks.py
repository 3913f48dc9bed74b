"""Validation of the model ``x+ = A x + w``, ``z = C x + v``; errors name the matrix.

Shared by the filter (:mod:`codesign_mb.estimation.kalman`) and the covariance theory
(:mod:`codesign_mb.estimation.riccati`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.core.config import as_matrix

FloatArray = NDArray[np.float64]
_FLOAT64 = np.dtype(np.float64)


def _matrix(name: str, value: ArrayLike, shape: tuple[int, int] | None = None) -> FloatArray:
    return as_matrix(name, value, shape)


def _vector(name: str, value: ArrayLike, size: int) -> FloatArray:
    """``value`` as a finite 1-D float array of ``size`` entries (a scalar when size is 1)."""
    if type(value) is np.ndarray and value.dtype is _FLOAT64 and value.shape == (size,):
        out = value.copy()  # the usual case (a filter's measurement), checked element-wise
        if not all(map(math.isfinite, out.tolist())):
            raise ValueError(f"{name} must be finite, got {out.tolist()}")
        return out
    try:
        out = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric vector, got {value!r}") from exc
    if out.ndim == 0 and size == 1:
        out = out.reshape(1)
    if out.shape != (size,):
        raise ValueError(f"{name} must have shape ({size},), got {out.shape}")
    if not np.isfinite(out).all():
        raise ValueError(f"{name} must be finite, got {out.tolist()}")
    return out


def _covariance(name: str, value: ArrayLike, n: int) -> FloatArray:
    """A symmetric positive semidefinite ``(n, n)`` matrix, symmetrised exactly."""
    out = _matrix(name, value, (n, n))
    scale = max(1.0, float(np.max(np.abs(out))))
    if not np.allclose(out, out.T, rtol=0.0, atol=1e-10 * scale):
        raise ValueError(f"{name} must be symmetric")
    if float(np.min(np.linalg.eigvalsh(out))) < -1e-10 * scale:
        raise ValueError(f"{name} must be positive semidefinite")
    return 0.5 * (out + out.T)


def _model(
    A: ArrayLike, C: ArrayLike, Q: ArrayLike, R: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Validate the matrices of ``x+ = A x + w``, ``z = C x + v``; errors name the matrix."""
    A = _matrix("A", A)
    n = A.shape[0]
    if A.shape != (n, n):
        raise ValueError(f"A must be square, got shape {A.shape}")
    C = _matrix("C", C)
    if C.shape[1] != n:
        raise ValueError(f"C must have {n} columns to match A, got shape {C.shape}")
    p = C.shape[0]
    return A, C, _covariance("Q", Q, n), _covariance("R", R, p)
