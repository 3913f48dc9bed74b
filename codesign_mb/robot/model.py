"""The Pinocchio model of the Panda arm and gripper: kinematics and rigid-body dynamics.

It is built from the same URDF that MuJoCo imports (``models/panda/panda.urdf``) with the
same joint armature, so the two simulators describe one robot: the test suite checks that the
gripper pose and the joint-space mass matrix agree to 1e-6 at random configurations.

The configuration is ``q = (q_1..q_7, f_1, f_2)``: the seven arm joints (rad) and the two
finger joints (m, opening from 0 to 0.04 each). All quantities are in the robot base frame,
which is the world frame of the conveyor scene (base at the origin, z up).
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from codesign_mb.robot.assets import PANDA_URDF, asset_path

__all__ = [
    "ARM_ARMATURE",
    "ARM_JOINTS",
    "FINGER_ARMATURE",
    "FINGER_JOINTS",
    "GRIPPER_DOWN",
    "N_ARM",
    "N_DOF",
    "TCP_FRAME",
    "PandaModel",
]

ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
N_ARM = len(ARM_JOINTS)
N_DOF = N_ARM + len(FINGER_JOINTS)

TCP_FRAME = "panda_hand_tcp"
"""The tool centre point: between the finger pads, 0.1034 m below the flange."""

ARM_ARMATURE = 0.1
"""Reflected rotor inertia of each arm joint (kg m^2), as in MuJoCo Menagerie's Panda."""

FINGER_ARMATURE = 0.01
"""Reflected inertia of each finger drive (kg); the Panda hand is not backdrivable."""

GRIPPER_DOWN = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""TCP orientation used for picking: approach axis pointing down, fingers closing along x."""


class PandaModel:
    """Pinocchio model and workspace of the Panda (description apart from state).

    ``model`` is the :class:`pinocchio.Model` (armature included, so ``crba`` gives the same
    mass matrix as MuJoCo); ``data`` is a workspace reused by every call, so one instance is
    not thread-safe (make one per simulator).

    Examples
    --------
    >>> robot = PandaModel()
    >>> q = robot.neutral()
    >>> p, R = robot.tcp_pose(q)
    >>> robot.mass_matrix(q).shape
    (9, 9)
    """

    def __init__(self) -> None:
        path = asset_path(PANDA_URDF)
        model = pin.buildModelFromUrdf(str(path))
        names = tuple(model.names[1:])
        if names != ARM_JOINTS + FINGER_JOINTS:
            raise ValueError(f"unexpected joint order in {path}: {names}")
        model.armature = np.array([ARM_ARMATURE] * N_ARM + [FINGER_ARMATURE] * 2)
        self.model: pin.Model = model
        self.data: pin.Data = model.createData()
        self.tcp_id: int = model.getFrameId(TCP_FRAME)
        self.lower: NDArray[np.float64] = model.lowerPositionLimit.copy()
        self.upper: NDArray[np.float64] = model.upperPositionLimit.copy()
        self.effort_limit: NDArray[np.float64] = model.effortLimit.copy()
        self.velocity_limit: NDArray[np.float64] = model.velocityLimit.copy()

    @property
    def armature(self) -> NDArray[np.float64]:
        """Joint armature (kg m^2 or kg), the same in MuJoCo."""
        return np.asarray(self.model.armature).copy()

    def neutral(self) -> NDArray[np.float64]:
        """The "ready" pose of the Franka documentation, fingers open."""
        return np.array(
            [0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4, 0.04, 0.04]
        )

    def tcp_pose(self, q: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """TCP position (3,) in m and rotation matrix (3, 3) in the base frame."""
        q = np.asarray(q, dtype=float)
        pin.framesForwardKinematics(self.model, self.data, q)
        placement = self.data.oMf[self.tcp_id]
        return placement.translation.copy(), placement.rotation.copy()

    def tcp_jacobian(self, q: ArrayLike) -> NDArray[np.float64]:
        """TCP Jacobian (6, 9): ``[v; omega] = J qdot`` in the base frame at the TCP."""
        q = np.asarray(q, dtype=float)
        return pin.computeFrameJacobian(
            self.model, self.data, q, self.tcp_id, pin.LOCAL_WORLD_ALIGNED
        ).copy()

    def mass_matrix(self, q: ArrayLike) -> NDArray[np.float64]:
        """Joint-space inertia ``M(q)`` (9, 9), armature included, symmetric."""
        q = np.asarray(q, dtype=float)
        M = pin.crba(self.model, self.data, q)
        return np.triu(M) + np.triu(M, 1).T

    def nonlinear_effects(self, q: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
        """Coriolis, centrifugal and gravity torques ``C(q, v) v + g(q)`` (9,)."""
        return pin.nonLinearEffects(
            self.model, self.data, np.asarray(q, dtype=float), np.asarray(v, dtype=float)
        ).copy()

    def gravity(self, q: ArrayLike) -> NDArray[np.float64]:
        """Gravity torques ``g(q)`` (9,)."""
        q = np.asarray(q, dtype=float)
        return pin.computeGeneralizedGravity(self.model, self.data, q).copy()

    def inverse_kinematics(
        self,
        position: ArrayLike,
        rotation: ArrayLike = GRIPPER_DOWN,
        q0: ArrayLike | None = None,
        *,
        tol: float = 1e-10,
        max_iter: int = 400,
        posture_gain: float = 0.3,
    ) -> NDArray[np.float64]:
        """Arm configuration placing the TCP at ``position`` with ``rotation`` (fingers kept).

        Newton iterations on the SE(3) log error; during the first half a null-space
        descent of ``||q - q0||^2`` (the Panda is redundant) selects the solution near ``q0``.

        Raises
        ------
        ValueError
            If the target is not reached (out of reach or joint limits).
        """
        target = pin.SE3(np.asarray(rotation, dtype=float), np.asarray(position, dtype=float))
        q_ref = self.neutral() if q0 is None else np.asarray(q0, dtype=float).copy()
        q = q_ref.copy()
        lo, hi = self.lower[:N_ARM], self.upper[:N_ARM]
        for it in range(max_iter):
            pin.framesForwardKinematics(self.model, self.data, q)
            err = pin.log6(self.data.oMf[self.tcp_id].actInv(target)).vector  # TCP frame
            J = pin.computeFrameJacobian(self.model, self.data, q, self.tcp_id, pin.LOCAL)
            J = J[:, :N_ARM]
            J_pinv = np.linalg.pinv(J, rcond=1e-8)
            dq = J_pinv @ err
            # First half: also descend ||q - q0||^2 in the null space; then pure Newton.
            if it < max_iter // 2:
                null_step = (np.eye(N_ARM) - J_pinv @ J) @ (posture_gain * (q_ref - q)[:N_ARM])
                if np.linalg.norm(err) < tol and np.linalg.norm(null_step) < 1e-9:
                    return q
                dq += null_step
            elif np.linalg.norm(err) < tol:
                return q
            q[:N_ARM] = np.clip(q[:N_ARM] + dq, lo, hi)
        raise ValueError(
            f"inverse kinematics did not converge to position {np.asarray(position).tolist()}"
        )

    @cached_property
    def arm_effort_limit(self) -> NDArray[np.float64]:
        """Torque limits of the seven arm joints (N m), from the URDF: 87 or 12."""
        return self.effort_limit[:N_ARM].copy()
