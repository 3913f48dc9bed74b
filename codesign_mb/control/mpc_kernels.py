"""The MPC's per-step arithmetic around the QP solver, compiled with numba.

Written with numpy, building the parameter vector, widening the workspace bounds to the
stopping path and checking the solution take about fifty small array operations a step,
more than the solver. These kernels do the same arithmetic elementwise, in the same order
(no fused multiply-add, NaN propagated like ``np.minimum``/``np.maximum``), so their results
equal the numpy expressions of :class:`~codesign_mb.control.mpc.MpcQp` (``qp_data``,
``stopping_path``) and :meth:`MpcQp.pack` bit for bit (``tests/test_mpc_hot_path.py``).
The matrix-vector products stay with numpy. Cached on disk by numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["fill_parameters", "stopping_bounds", "worst_violation"]

APPROACH, DESCEND, GRASP, LIFT = 0, 1, 2, 3  # codesign_mb.control.mpc.Phase


@njit(cache=True)
def _min(a: float, b: float) -> float:
    return a if a <= b else b  # np.minimum: b when b is NaN


@njit(cache=True)
def _max(a: float, b: float) -> float:
    return a if a >= b else b  # np.maximum: b when b is NaN


@njit(cache=True)
def fill_parameters(
    theta, p, v, u_prev, obj, offset, obj_vel, kdt, phase, hover, clearance, depth, lift, origin,
    low, high, off_value,
):  # fmt: skip
    """Write ``theta`` (the layout of ``MpcQp.pack``) for ``phase``; see ``MpcController``.

    The grasp path is ``obj + offset + k dt w``; ``hover`` and ``lift`` are the 3-vectors
    added to it (APPROACH) or to ``origin`` (LIFT); ``off_value`` switches a constraint off.
    """
    n = kdt.shape[0]
    i_ref, i_vref, i_apex, i_plane = 9, 9 + 3 * n, 9 + 6 * n, 9 + 9 * n
    for j in range(3):
        theta[j] = p[j]
        theta[3 + j] = v[j]
        theta[6 + j] = u_prev[j]
    for k in range(n):
        for j in range(3):
            path = (obj[j] + offset[j]) + kdt[k, 0] * obj_vel[j]
            if phase == APPROACH:
                ref = path + hover[j]
                vref = obj_vel[j]
                apex = -off_value if j == 2 else path
            elif phase in (DESCEND, GRASP):
                ref = path
                vref = obj_vel[j]
                apex = path - depth if j == 2 else path
            else:
                ref = origin[j] + lift[j]
                vref = 0.0
                apex = -off_value if j == 2 else path
            r = low[j] if ref < low[j] else ref  # np.clip: max with low, then min with high
            theta[i_ref + 3 * k + j] = high[j] if r > high[j] else r
            theta[i_vref + 3 * k + j] = vref
            theta[i_apex + 3 * k + j] = apex
            if j == 2:
                theta[i_plane + k] = path + clearance if phase == APPROACH else -off_value


@njit(cache=True)
def stopping_bounds(p, v, k_step, v_max, bp_v, bp_u, con_low, con_high, row0, offset, lba, uba):
    """``lba = low - offset``, ``uba = high - offset`` with the workspace rows (from ``row0``)
    widened to the stopping path; the closed form of ``MpcQp.stopping_path`` (``a = 0``)."""
    for i in range(con_low.shape[0]):
        lba[i] = con_low[i] - offset[i]
        uba[i] = con_high[i] - offset[i]
    n = k_step.shape[0] - 1
    for j in range(3):
        speed = abs(v[j])
        sign = np.sign(v[j])
        s = speed - k_step[0, 0]
        prev = sign * (0.0 if s < 0.0 else s)  # v[0]
        position = 0.0
        for k in range(n):
            s = speed - k_step[k + 1, 0]
            s = 0.0 if s < 0.0 else s
            s = v_max if s > v_max else s  # np.minimum(s, v_max), NaN kept
            vk = sign * s
            step = bp_v * prev + bp_u * vk
            position = step if k == 0 else position + step  # np.cumsum
            prev = vk
            r = row0 + 3 * k + j
            stop = p[j] + position
            lba[r] = _min(con_low[r], stop) - offset[r]
            uba[r] = _max(con_high[r], stop) - offset[r]


@njit(cache=True)
def worst_violation(x, ax, lbx, ubx, lba, uba):
    """The largest bound violation of ``x`` (``ax = A x``); ``inf`` when ``x`` is not finite."""
    worst = -np.inf
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return np.inf
        worst = max(worst, lbx[i] - x[i], x[i] - ubx[i])
    for i in range(ax.shape[0]):
        worst = max(worst, lba[i] - ax[i], ax[i] - uba[i])
    return worst
