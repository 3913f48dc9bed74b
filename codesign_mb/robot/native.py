"""The operational-space law and the physics substeps, compiled (numba + MuJoCo's C API).

The plant's hot path is 20 physics substeps per control step with the affine law
``tau = G s + h`` (:mod:`codesign_mb.robot.osc`) between MuJoCo's ``mj_step1`` and
``mj_step2``. Written in Python, each substep costs about ten numpy and binding calls, as
much as the physics itself. Here numba compiles the law and the substep loop; the loop calls
``mj_step1`` / ``mj_step2`` of the ``libmujoco`` the Python bindings loaded (by symbol, on
the ``MjModel`` / ``MjData`` addresses), so a block of substeps is one call from Python; all
of it is cached on disk by numba (the first call in a process still costs about 0.5 s).

:func:`affine_torque` is the single implementation of the law: the Python reference path
(:meth:`~codesign_mb.robot.osc.OperationalSpaceController.torque`) calls it too, so both
paths compute bit-identical torques from identical inputs. :data:`run_substeps` is ``None``
where the C library cannot be located (then the controller loops in Python).
"""

from __future__ import annotations

import ctypes
import glob
import math
import os

import mujoco
import numpy as np
from numba import njit, types

__all__ = [
    "affine_torque",
    "leash_reference",
    "map_workspace",
    "operational_space_map",
    "plan_reference",
    "run_substeps",
]


@njit(cache=True)
def affine_torque(G, rot, pos, ref, q, v, bias, limit, clip, out):
    """``out = G [vec(R), x, 1, x_r, r, q, qdot] + h``, optionally clipped to ``+-limit``.

    ``G`` is the controller's (n_arm, 19 + 2 nv) map (osc module doc); ``rot`` the TCP
    rotation (9, row-major), ``pos`` its position, ``ref`` the reference ``(x_r, r)`` (6),
    ``q`` and ``v`` the joint positions and velocities (nv), ``bias`` ``h`` (>= n_arm).
    """
    nv = q.shape[0]
    iq, iv = 19, 19 + nv
    for j in range(out.shape[0]):
        acc = G[j, 12]
        for c in range(9):
            acc += G[j, c] * rot[c]
        for c in range(3):
            acc += G[j, 9 + c] * pos[c]
        for c in range(6):
            acc += G[j, 13 + c] * ref[c]
        for c in range(nv):
            acc += G[j, iq + c] * q[c]
        for c in range(nv):
            acc += G[j, iv + c] * v[c]
        acc += bias[j]
        if clip:
            acc = min(max(acc, -limit[j]), limit[j])
        out[j] = acc


@njit(cache=True)
def leash_reference(refs, start, pos, max_lag):
    """Keep the position reference within ``max_lag`` (m) of the TCP ``pos``, in place.

    If ``e = x_r - x`` of ``refs[start]`` is longer than ``max_lag``, the positions
    ``refs[start:, :3]`` all move by ``-e (1 - max_lag / |e|)``: the reference of this substep
    then lies on the sphere of radius ``max_lag`` around the TCP. ``|e|^2`` is ``np.dot``
    (BLAS, the rounding of numpy's ``e @ e``), so the Python and the compiled paths agree bit
    for bit.
    """
    error = np.empty(3)
    for c in range(3):
        error[c] = refs[start, c] - pos[c]
    dist = math.sqrt(np.dot(error, error))
    if dist > max_lag:
        scale = 1.0 - max_lag / dist
        for r in range(start, refs.shape[0]):
            for c in range(3):
                refs[r, c] -= error[c] * scale


@njit(cache=True)
def plan_reference(x0, v0, v_cmd, dt, kd, a_max, low, high, radius, bounded, refs, v_end):
    """The reference of the next ``n = len(refs)`` substeps (osc module doc).

    The reference velocity moves from ``v0`` towards ``v_cmd`` with acceleration
    ``a_max`` (a straight line in velocity space); the position integrates it from ``x0``.
    ``refs[k] = (x_r, r)`` after substep ``k``, with ``r = K_d xdot_r + xddot_r``. With
    ``bounded``, positions are projected into the box ``[low, high]`` and the cylinder of
    ``radius`` around the z axis; where that moved any, the velocity is the projected
    positions' and the acceleration feed-forward is dropped. ``v_end`` receives the
    velocity reference after the last substep.
    """
    n = refs.shape[0]
    d0, d1, d2 = v_cmd[0] - v0[0], v_cmd[1] - v0[1], v_cmd[2] - v0[2]
    dist = (d0 * d0 + d1 * d1 + d2 * d2) ** 0.5
    u = (d0 / dist, d1 / dist, d2 / dist) if dist > 0.0 else (0.0, 0.0, 0.0)
    reached_before = 0.0
    travelled = 0.0  # sum of the speeds gained so far, times dt
    moved = False
    for k in range(n):
        reached = min((k + 1) * a_max * dt, dist)
        travelled += reached * dt
        accel = (reached - reached_before) / dt
        reached_before = reached
        for c in range(3):
            x = x0[c] + (k + 1) * dt * v0[c] + travelled * u[c]
            refs[k, c] = x
            refs[k, 3 + c] = kd * (v0[c] + reached * u[c]) + accel * u[c]
        if bounded:
            for c in range(3):
                x = min(max(refs[k, c], low[c]), high[c])
                if x != refs[k, c]:
                    refs[k, c] = x
                    moved = True
            rxy = (refs[k, 0] ** 2 + refs[k, 1] ** 2) ** 0.5
            if rxy > radius:
                refs[k, 0] *= radius / rxy
                refs[k, 1] *= radius / rxy
                moved = True
    if moved:  # stopped or sliding at the boundary
        for k in range(n):
            for c in range(3):
                before = x0[c] if k == 0 else refs[k - 1, c]
                v_end[c] = (refs[k, c] - before) / dt
            for c in range(3):
                refs[k, 3 + c] = kd * v_end[c]
    else:
        for c in range(3):
            v_end[c] = v0[c] + reached_before * u[c]


@njit(cache=True)
def _cholesky(A, L):
    # L L^T = A (lower L); False if A is not positive definite.
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if acc <= 0.0:
                    return False
                L[i, i] = acc**0.5
            else:
                L[i, j] = acc / L[j, j]
    return True


@njit(cache=True)
def _cholesky_solve(L, B, X):
    # X = (L L^T)^-1 B, column by column.
    n = L.shape[0]
    for c in range(B.shape[1]):
        for i in range(n):
            acc = B[i, c]
            for k in range(i):
                acc -= L[i, k] * X[k, c]
            X[i, c] = acc / L[i, i]
        for i in range(n - 1, -1, -1):
            acc = X[i, c]
            for k in range(i + 1, n):
                acc -= L[k, i] * X[k, c]
            X[i, c] = acc / L[i, i]


def map_workspace(G: np.ndarray) -> np.ndarray:
    """The ``work`` buffer of :func:`operational_space_map` for the map ``G`` (n, ns)."""
    n, ns = G.shape
    return np.empty(3 * n * n + 5 * 6 * n + 2 * 36 + 2 * n * ns)


@njit(cache=True)
def _view(work, start, rows, cols):
    # A (rows, cols) C-contiguous view of work[start:], and where the next one starts.
    stop = start + rows * cols
    return work[start:stop].reshape((rows, cols)), stop


@njit(cache=True)
def operational_space_map(J, M, P, Q, kd, iv, damping, G, work):
    """``G = J^T Lambda P + N^T M Q`` of the affine law (osc module doc), in place.

    ``J`` (6, >= n) and ``M`` (>= n, >= n) are the TCP Jacobian and the inertia, of which
    the first ``n = G.shape[0]`` (arm) joints are used; ``Lambda = (J M^-1 J^T)^-1`` (damped
    by ``damping`` at a singularity), ``N^T M = M - J^T Lambda J``. ``P``'s ``qdot`` block
    (columns ``iv..iv+n``) is set to ``-K_d J`` (``kd``: the six task-space dampings) first.
    ``work`` (:func:`map_workspace`) holds the intermediates, so a call allocates nothing;
    the products are BLAS's, as with ``@``.
    """
    n, ns = G.shape
    Ja, o = _view(work, 0, 6, n)
    Ma, o = _view(work, o, n, n)
    JaT, o = _view(work, o, n, 6)
    L, o = _view(work, o, n, n)
    MinvJt, o = _view(work, o, n, 6)
    A, o = _view(work, o, 6, 6)
    La, o = _view(work, o, 6, 6)
    LamJ, o = _view(work, o, 6, n)
    JtL, o = _view(work, o, n, 6)
    NtM, o = _view(work, o, n, n)
    T1, o = _view(work, o, n, ns)
    T2, o = _view(work, o, n, ns)
    for r in range(6):
        for c in range(n):
            Ja[r, c] = J[r, c]
            JaT[c, r] = J[r, c]
            P[r, iv + c] = -kd[r] * J[r, c]
    for r in range(n):
        for c in range(n):
            Ma[r, c] = M[r, c]
    L[:, :] = 0.0
    _cholesky(Ma, L)  # the inertia (armature included) is positive definite
    _cholesky_solve(L, JaT, MinvJt)
    np.dot(Ja, MinvJt, A)
    La[:, :] = 0.0
    if not _cholesky(A, La):  # at a singularity: damped least squares
        for r in range(6):
            A[r, r] += damping
        _cholesky(A, La)
    _cholesky_solve(La, Ja, LamJ)
    for r in range(6):  # J^T Lambda (Lambda is symmetric)
        for c in range(n):
            JtL[c, r] = LamJ[r, c]
    np.dot(JtL, Ja, NtM)
    for r in range(n):
        for c in range(n):
            NtM[r, c] = Ma[r, c] - NtM[r, c]
    np.dot(JtL, P, T1)
    np.dot(NtM, Q, T2)
    for r in range(n):
        for c in range(ns):
            G[r, c] = T1[r, c] + T2[r, c]


def _load_mujoco_library() -> bool:
    """Make the bindings' own ``libmujoco`` symbols visible to compiled code."""
    import llvmlite.binding as llvm

    folder = os.path.dirname(mujoco.__file__)
    candidates = sorted(
        glob.glob(os.path.join(folder, "libmujoco.so*"))
        + glob.glob(os.path.join(folder, "libmujoco*.dylib"))
        + glob.glob(os.path.join(folder, "mujoco.dll"))
    )
    for path in candidates:
        try:
            if ctypes.CDLL(path).mj_version() != mujoco.mj_version():
                continue
            llvm.load_library_permanently(path)
        except (OSError, RuntimeError):
            continue
        return True
    return False


if _load_mujoco_library():
    # mj_step1(const mjModel*, mjData*), mj_step2(...): resolved by name, so cacheable.
    _mj_step1 = types.ExternalFunction("mj_step1", types.void(types.uintp, types.uintp))
    _mj_step2 = types.ExternalFunction("mj_step2", types.void(types.uintp, types.uintp))

    @njit(cache=True)
    def _run_substeps(
        model, data, G, refs, start, stop, leash, max_lag, rot, pos, q, v, bias, limit, clip, ctrl
    ):
        for i in range(start, stop):
            _mj_step1(model, data)
            if leash and i == start:
                leash_reference(refs, i, pos, max_lag)
            affine_torque(G, rot, pos, refs[i], q, v, bias, limit, clip, ctrl)
            _mj_step2(model, data)

    run_substeps = _run_substeps
    """``run_substeps(model_address, data_address, G, refs, start, stop, leash, max_lag, rot,
    pos, q, v, bias, limit, clip, ctrl)``: substeps ``start..stop-1`` of one control step,
    each ``mj_step1``; at the first, with ``leash``, :func:`leash_reference` (``max_lag``)
    on the TCP position it computed; ``ctrl[:] = tau`` (:func:`affine_torque` with
    ``refs[i]``); ``mj_step2``. The arrays are live views into ``MjData``."""
else:  # pragma: no cover - the wheels ship libmujoco next to the bindings
    run_substeps = None
