"""The conveyor's workspace braking law, compiled with numba (the plant's per-step hot path).

Near a face of the workspace box (or of the cylinder around the base) the commanded TCP
speed towards it is capped by the discrete braking law ``v <= a (sqrt(T^2 + 2 d / a) - T)``
(``d`` the distance of the inner loop's position reference to the face, ``T`` the control
period, ``a`` the braking deceleration), so the reference stops at the face; then every
component is clipped to the speed limit. With the conveyor's workspace this runs every step
(the box is narrower than the braking distance of a full-speed command). The arithmetic is
that of the Python expressions it replaced, in the same order (no fused multiply-add), and
``min``/``max`` follow Python's (``tests/test_conveyor.py`` checks it bit for bit).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["keep_in_workspace"]


@njit(cache=True)
def _pymin(a: float, b: float) -> float:
    return b if b < a else a  # builtins.min(a, b)


@njit(cache=True)
def _pymax(a: float, b: float) -> float:
    return b if b > a else a  # builtins.max(a, b)


@njit(cache=True)
def _cap(distance: float, T: float, a: float) -> float:
    return a * (math.sqrt(T * T + 2.0 * _pymax(distance, 0.0) / a) - T)


@njit(cache=True)
def keep_in_workspace(velocity, x, radius, low, high, workspace_radius, margin, T, a, limit):
    """Cap ``velocity`` (m/s, written in place) for the position reference ``x``.

    ``radius`` is ``math.hypot(x[0], x[1])`` (computed by the caller: Python's ``hypot`` is
    not libm's); ``low``, ``high`` the box, ``workspace_radius`` the cylinder; farther than
    ``margin`` from every face only the speed ``limit`` applies.
    """
    nearest = x[0] - low[0]
    for d in (x[1] - low[1], x[2] - low[2], high[0] - x[0], high[1] - x[1], high[2] - x[2]):
        nearest = _pymin(nearest, d)
    if nearest > margin and workspace_radius - radius > margin:  # only the speed limit
        for i in range(3):  # np.clip of finite values
            velocity[i] = _pymin(_pymax(velocity[i], -limit), limit)
        return
    v = np.empty(3)
    for i in range(3):
        v[i] = _pymin(_pymax(velocity[i], -_cap(x[i] - low[i], T, a)), _cap(high[i] - x[i], T, a))
    if radius > 0:
        outward = (v[0] * x[0] + v[1] * x[1]) / radius
        allowed = _cap(workspace_radius - radius, T, a)
        if outward > allowed:
            v[0] -= (outward - allowed) * x[0] / radius
            v[1] -= (outward - allowed) * x[1] / radius
    for i in range(3):
        velocity[i] = _pymin(_pymax(v[i], -limit), limit)
