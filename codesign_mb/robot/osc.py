r"""Operational-space control of the Panda's gripper: Cartesian velocity -> joint torques.

The low level of DESIGN.md step 7, part of the plant and the same for every policy. At each
physics substep (2 ms) it turns the commanded gripper velocity ``v_cmd`` (held over the 40 ms
control period) into arm torques with the classic operational-space law (Khatib 1987):

.. math::

    \dot x_r &\leftarrow \dot x_r + \mathrm{sat}_{a_{max} dt}(v_{cmd} - \dot x_r), \qquad
    x_r \leftarrow x_r + \dot x_r\, dt \quad (|x_r - x| \le \ell_{max}) \\
    a &= \begin{bmatrix} \ddot x_r + K_p (x_r - x) + K_d (\dot x_r - J_v \dot q) \\
          K_R\, e_R - K_\omega J_\omega \dot q \end{bmatrix}, \quad
          e_R = \tfrac12 (R_r R^T - R R_r^T)^\vee = \sin\theta\, k \\
    \tau &= J^T \Lambda a + N^T M \big(k_n (q_0 - q) - d_n \dot q\big) + h(q, \dot q),
    \qquad \Lambda = (J M^{-1} J^T)^{-1}, \; N = I - M^{-1} J^T \Lambda J

with ``J`` the 6x7 TCP Jacobian, ``M`` the arm's inertia (armature included), ``h`` the
Coriolis and gravity torques, all from the Pinocchio model; ``e_R`` is the usual
orientation error (``R_r R^T = exp(theta k)``; equal to ``log(R_r R^T)`` to second order,
and linear in ``R``); the null-space term holds the
elbow near the posture ``q_0``; the torques are clipped to the URDF limits. The reference
``x_r`` integrates the velocity command with a bounded acceleration (a step in the command
would otherwise saturate the motors) and is kept within ``max_lag_m`` of the TCP, so a
blocked gripper (pressed on the belt) pushes with a bounded force instead of winding up.
The orientation reference is fixed (gripper pointing down, fingers closing across the belt):
the command is a 3-D translational velocity, the orientation is regulated.

Implementation (the plant's hot path). With the configuration-dependent matrices fixed,
the law is affine in the reference error, the rotation matrix, ``q``, ``qdot`` and the
reference terms:

.. math::

    \tau = G\, [\mathrm{vec}(R),\ x,\ 1,\ x_r,\ K_d \dot x_r + \ddot x_r,\ q,\ \dot q]
        + h(q, \dot q)

with ``R`` and ``x`` the TCP's rotation and position (the 1 carries the constant term).

``G`` (from ``J``, ``M``, ``Lambda``, ``N`` at the current ``q``) is recomputed from
Pinocchio every ``model_period`` substeps, when the reference leash is also checked; the TCP
pose and ``h`` are recomputed at every substep from the current state, so the feedback runs
at 500 Hz. Inside the simulator they are read from MuJoCo's forward pass of the substep
(:class:`SensedTcp`), which computes the same quantities of the same arm anyway, and the
substeps between two refreshes of ``G`` run compiled (:mod:`codesign_mb.robot.native`).
``model_period=1`` is the exact law at every substep; the default refreshes ``G`` every
20 ms (10 substeps): on a 0.4 m/s circle the worst tracking error goes from 1.13 mm
(exact) to 1.38 mm (``tests/test_robot.py`` bounds the difference), and most of the
per-substep linear algebra is gone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from codesign_mb.robot.model import GRIPPER_DOWN, N_ARM, PandaModel
from codesign_mb.robot.native import (
    affine_torque,
    leash_reference,
    map_workspace,
    operational_space_map,
    plan_reference,
    run_substeps,
)

__all__ = ["OperationalSpaceController", "OscGains", "SensedTcp"]

_SINGULAR_DAMPING = 1e-6


@dataclass(frozen=True)
class OscGains:
    """Gains and limits of :class:`OperationalSpaceController`.

    Parameters
    ----------
    kp_pos, kd_pos:
        Translational stiffness (1/s^2) and damping (1/s) per unit task-space mass.
    kp_rot, kd_rot:
        Rotational stiffness (1/s^2) and damping (1/s).
    kp_null, kd_null:
        Null-space posture stiffness (1/s^2) and damping (1/s).
    max_accel_mps2:
        Bound on the reference acceleration (m/s^2).
    max_lag_m:
        Bound on the distance between the reference and the TCP (m).
    """

    kp_pos: float = 900.0
    kd_pos: float = 60.0
    kp_rot: float = 600.0
    kd_rot: float = 50.0
    kp_null: float = 25.0
    kd_null: float = 10.0
    max_accel_mps2: float = 8.0
    max_lag_m: float = 0.05

    def __post_init__(self) -> None:
        for name in ("kp_pos", "kd_pos", "kp_rot", "kd_rot", "kp_null", "kd_null"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        for name in ("max_accel_mps2", "max_lag_m"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be finite and > 0, got {value}")


@dataclass(frozen=True)
class SensedTcp:
    """What a simulator's forward pass already computed at the current state.

    ``forward()`` computes it (MuJoCo: ``mj_step1``); ``rotation`` (9, row-major),
    ``position`` (3) and ``bias`` (``h(q, qdot)``, at least the 7 arm entries) are live
    views that it updates. ``addresses``: the ``MjModel`` and ``MjData`` addresses, for the
    compiled substep loop (``None``: loop in Python). Given to
    :meth:`OperationalSpaceController.run`.
    """

    forward: Callable[[], object]
    rotation: NDArray[np.float64]
    position: NDArray[np.float64]
    bias: NDArray[np.float64]
    addresses: tuple[int, int] | None = None


class OperationalSpaceController:
    """Cartesian gripper velocity tracking by operational-space torques (see module doc).

    Parameters
    ----------
    robot:
        The Pinocchio model; its ``data`` workspace is used (one controller per robot).
    gains:
        :class:`OscGains`.
    dt:
        The substep (s) at which torques are computed.
    model_period:
        Substeps between recomputations of ``J``, ``Lambda``, ``N^T M`` (1 = every substep).

    Examples
    --------
    >>> robot = PandaModel()
    >>> osc = OperationalSpaceController(robot)
    >>> q = robot.neutral()
    >>> osc.reset(q)
    >>> osc.set_velocity_command([0.1, 0.0, 0.0])
    >>> tau = osc.torque(q, np.zeros(9))  # (7,) arm torques for the next 2 ms
    """

    def __init__(
        self,
        robot: PandaModel,
        gains: OscGains | None = None,
        *,
        dt: float = 0.002,
        model_period: int = 10,
    ) -> None:
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        if int(model_period) < 1:
            raise ValueError(f"model_period must be >= 1, got {model_period}")
        self.robot = robot
        self.gains = gains or OscGains()
        self.dt = float(dt)
        self.model_period = int(model_period)
        self.rotation_ref: NDArray[np.float64] = GRIPPER_DOWN.copy()
        self.posture: NDArray[np.float64] = robot.neutral()[:N_ARM]
        self.workspace: tuple[NDArray[np.float64], NDArray[np.float64], float] | None = None
        g = self.gains
        nv = robot.model.nv
        self.torque_limit: NDArray[np.float64] = robot.arm_effort_limit
        self._kd6 = np.array([g.kd_pos] * 3 + [g.kd_rot] * 3)
        self._x_ref = np.zeros(3)
        self._v_ref = np.zeros(3)
        self._v_cmd = np.zeros(3)
        self._k = 0
        self._no_workspace = np.zeros(3)
        # Columns of G for the stacked input s = [vec(R) (9), x (3), 1, x_r (3), r (3),
        # q (nv), qdot (nv)] of the affine law tau = G s + h(q, qdot): the TCP's rotation
        # (row-major) and position, a constant 1 that carries the constant term, the
        # position reference x_r and the reference term r = K_d xdot_r + xddot_r
        # (native.affine_torque evaluates it without stacking s).
        self._iR = slice(0, 9)
        self._ix = slice(9, 12)
        self._iq = slice(19, 19 + nv)
        self._iv = slice(19 + nv, 19 + 2 * nv)
        self._G = np.zeros((N_ARM, 19 + 2 * nv))
        self._tau = np.zeros(N_ARM)
        self._work = map_workspace(self._G)
        self._set_input_maps()

    @property
    def position_reference(self) -> NDArray[np.float64]:
        """The TCP position reference ``x_r`` (m)."""
        return self._x_ref.copy()

    @property
    def velocity_reference(self) -> NDArray[np.float64]:
        """The TCP velocity reference (m/s)."""
        return self._v_ref.copy()

    def reset(
        self,
        q: ArrayLike,
        *,
        posture: ArrayLike | None = None,
        rotation: ArrayLike | None = None,
    ) -> None:
        """Start holding the current TCP position; optionally set the posture and rotation."""
        q = np.asarray(q, dtype=float)
        position, _ = self.robot.tcp_pose(q)
        self._x_ref[:] = position
        self._v_ref[:] = 0.0
        self._v_cmd[:] = 0.0
        if posture is not None:
            self.posture = np.asarray(posture, dtype=float)[:N_ARM].copy()
        if rotation is not None:
            self.rotation_ref = np.asarray(rotation, dtype=float).copy()
        self._set_input_maps()
        self._k = 0

    def set_workspace(self, low: ArrayLike, high: ArrayLike, radius: float = np.inf) -> None:
        """Keep the position reference in the box ``[low, high]`` (m) and within ``radius``
        of the base's z axis: the gripper then stops at the boundary (up to its lag).
        """
        low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
        if not (np.all(low < high) and radius > 0):
            raise ValueError(f"empty workspace: low {low}, high {high}, radius {radius}")
        self.workspace = (low, high, float(radius))

    def set_velocity_command(self, velocity: ArrayLike) -> None:
        """The TCP velocity (m/s, base frame) to track until the next command."""
        self._v_cmd[:] = velocity

    def torque(self, q: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        """Arm torques (7,) for the state ``(q, v)`` (9,), clipped to the limits.

        Advances the reference by one substep ``dt``; :meth:`run` is the same law over
        several substeps with the physics stepped in between.
        """
        self.run(q, v, self._tau, None, 1, clip=True)
        return self._tau.copy()

    def run(
        self,
        q: NDArray[np.float64],
        v: NDArray[np.float64],
        ctrl: NDArray[np.float64],
        step: Callable[[], object] | None,
        n: int,
        *,
        clip: bool = True,
        sensed: SensedTcp | None = None,
    ) -> None:
        """Run ``n`` substeps: ``ctrl[:] = tau(q, v)``, then ``step()`` advances the physics.

        ``q`` and ``v`` are live views of the simulator's state (read after every step).
        ``clip=False`` leaves the torque limits to the actuators (MuJoCo's ``ctrlrange`` is
        set to the same limits). With ``sensed``, the TCP pose and ``h`` of each substep are
        read from the simulator's own forward pass (``sensed.forward``, e.g. ``mj_step1``;
        ``step`` then finishes the step, ``mj_step2``) instead of being recomputed by
        Pinocchio: the same numbers (``tests/test_robot.py``) without computing them twice;
        with ``sensed.addresses`` too, the substeps between two refreshes of ``G`` run
        compiled (:mod:`codesign_mb.robot.native`; ``step`` is then not called). ``J``,
        ``M`` and ``Lambda`` always come from the Pinocchio model.
        """
        refs = self._plan_reference(n)
        if sensed is not None and sensed.addresses is not None and run_substeps is not None:
            self._run_native(q, v, ctrl, n, refs, clip, sensed)
        else:
            self._run_python(q, v, ctrl, step, n, refs, clip, sensed)
        self._x_ref[:] = refs[-1, :3]

    def _run_native(
        self,
        q: NDArray[np.float64],
        v: NDArray[np.float64],
        ctrl: NDArray[np.float64],
        n: int,
        refs: NDArray[np.float64],
        clip: bool,
        sensed: SensedTcp,
    ) -> None:
        # Python refreshes G (Pinocchio) before the first substep of each block; the compiled
        # loop runs the block, the leash after the block's first mj_step1. The refresh reads
        # q only, which mj_step1 leaves as is: the order of the Python loop's arithmetic.
        model, data = sensed.addresses
        rot, pos, bias = sensed.rotation, sensed.position, sensed.bias
        G, limit, period, k = self._G, self.torque_limit, self.model_period, self._k
        max_lag = self.gains.max_lag_m
        i = 0
        while i < n:
            refresh = k % period == 0
            if refresh:
                self._update_model(q)
            stop = min(n, i + period - k % period)
            run_substeps(
                model, data, G, refs, i, stop, refresh, max_lag, rot, pos, q, v, bias, limit,
                clip, ctrl,
            )  # fmt: skip
            k += stop - i
            i = stop
        self._k = k

    def _run_python(
        self,
        q: NDArray[np.float64],
        v: NDArray[np.float64],
        ctrl: NDArray[np.float64],
        step: Callable[[], object] | None,
        n: int,
        refs: NDArray[np.float64],
        clip: bool,
        sensed: SensedTcp | None,
    ) -> None:
        model, data, fid = self.robot.model, self.robot.data, self.robot.tcp_id
        G, limit, period, k = self._G, self.torque_limit, self.model_period, self._k
        forward, place, nle = pin.forwardKinematics, pin.updateFramePlacement, pin.nonLinearEffects
        for i in range(n):
            refresh = k % period == 0
            if sensed is not None:
                sensed.forward()
                rot, pos, bias = sensed.rotation, sensed.position, sensed.bias
                if refresh:
                    self._update_model(q)
            else:
                if refresh:
                    self._update_model(q)  # forward kinematics included
                else:
                    forward(model, data, q)
                placement = place(model, data, fid)
                rot, pos = placement.rotation.ravel(), placement.translation
                bias = nle(model, data, q, v)
            if refresh:  # keep the reference within max_lag of the TCP
                leash_reference(refs, i, pos, self.gains.max_lag_m)
            k += 1
            affine_torque(G, rot, pos, refs[i], q, v, bias, limit, clip, ctrl)
            if step is not None:
                step()
        self._k = k

    def _plan_reference(self, n: int) -> NDArray[np.float64]:
        # The reference of the next n substeps (native.plan_reference): per substep, the
        # position reference after it and the term r = K_d xdot_r + xddot_r.
        g = self.gains
        refs = np.empty((n, 6))
        if self.workspace is None:
            low, high, radius, bounded = self._no_workspace, self._no_workspace, np.inf, False
        else:
            (low, high, radius), bounded = self.workspace, True
        plan_reference(
            self._x_ref, self._v_ref, self._v_cmd, self.dt, g.kd_pos, g.max_accel_mps2,
            low, high, radius, bounded, refs, self._v_ref,
        )  # fmt: skip
        return refs

    def _set_input_maps(self) -> None:
        # G = J^T Lambda P + N^T M Q: P (6 x ns) maps s to the task-space acceleration a
        # (its qdot block, -K_d J, is refreshed with J), Q (7 x ns) to the posture term.
        g, ns = self.gains, self._G.shape[1]
        iq, iv = self._iq.start, self._iv.start
        P = np.zeros((6, ns))
        # + K_R e_R with e_R = L vec(R)
        P[3:, self._iR] = g.kp_rot * _orientation_error_map(self.rotation_ref)
        P[:3, self._ix] = -g.kp_pos * np.eye(3)  # - K_p x
        P[:3, 13:16] = g.kp_pos * np.eye(3)  # + K_p x_r
        P[:3, 16:19] = np.eye(3)  # + K_d xdot_r + xddot_r
        Q = np.zeros((N_ARM, ns))
        Q[:, 12] = g.kp_null * self.posture  # s[12] = 1 carries the constant
        Q[:, iq : iq + N_ARM] = -g.kp_null * np.eye(N_ARM)
        Q[:, iv : iv + N_ARM] = -g.kd_null * np.eye(N_ARM)
        self._P, self._Q = P, Q  # P's qdot block, -K_d J, is set with each new J

    def _update_model(self, q: NDArray[np.float64]) -> None:
        model, data = self.robot.model, self.robot.data
        J = pin.computeFrameJacobian(model, data, q, self.robot.tcp_id, pin.LOCAL_WORLD_ALIGNED)
        M = pin.crba(model, data, q)  # symmetric (both triangles filled)
        operational_space_map(
            J, M, self._P, self._Q, self._kd6, self._iv.start, _SINGULAR_DAMPING, self._G,
            self._work,
        )  # fmt: skip


def _orientation_error_map(rotation_ref: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 3x9 matrix ``L`` with ``L vec(R) = vee(R_r R^T - R R_r^T) / 2``.

    That is ``sin(theta) k`` for the rotation ``R_r R^T = exp(theta k)`` from the current to
    the reference orientation (world frame): the usual orientation error of operational-space
    controllers (equal to ``log(R_r R^T)`` to second order), and linear in ``R``.
    """
    L = np.zeros((3, 9))
    for j in range(9):
        R = np.zeros(9)
        R[j] = 1.0
        E = rotation_ref @ R.reshape(3, 3).T
        S = 0.5 * (E - E.T)
        L[:, j] = (S[2, 1], S[0, 2], S[1, 0])
    return L
