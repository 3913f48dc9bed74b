"""What the conveyor MPC knows of the arm: the ramp, the joint limits, the terminal cost.

Three pieces of the model of :class:`~codesign_mb.control.mpc_qp_problem.MpcQpProblem` (the
MPC's QP), kept apart from the QP's construction:

* :func:`ramp_rows`: the low level (:mod:`codesign_mb.robot.osc`) slews its velocity
  reference towards a new command at most ``a_max`` (in norm) per second. The MPC's model
  ``v[k+1] = u[k]`` holds only if that ramp ends within the step, so the change of the
  predicted velocity per step is kept inside the cuboctahedron inscribed in the ball of
  radius ``a_max dt``: ``|dv_i| <= c`` and ``|+-dv_x +- dv_y +- dv_z| <= 2c``,
  ``c = a_max dt / sqrt(2)`` (its twelve vertices ``(+-c, +-c, 0)`` lie on the sphere).
* :class:`JointLimits` and :func:`joint_linearisation`: the Panda's joint position and
  velocity limits, and the Pinocchio Jacobian that maps the gripper's predicted motion to
  the joints' at the measured configuration ``q0``: with the gripper's orientation held
  (the low level regulates it), ``qdot = J^+ [v; 0] = J_v^+ v`` (``J_v^+``: the first three
  columns of the pseudo-inverse of the 6x7 TCP Jacobian), so
  ``q[k] ~ q0 + J_v^+ (p[k] - p[0])`` and ``qdot[k] ~ J_v^+ v[k]``.
* :func:`terminal_weights`: the terminal cost, the cost-to-go of the unconstrained
  infinite-horizon problem (discrete algebraic Riccati equation of the per-axis model).
  With it the finite-horizon MPC equals the infinite-horizon LQ controller wherever no
  constraint is active, and it is the terminal cost of the standard stability argument of
  MPC (Mayne, Rawlings, Rao, Scokaert, "Constrained model predictive control: stability
  and optimality", Automatica 36, 2000, sec. 3; Rawlings, Mayne, Diehl, "Model Predictive
  Control", 2nd ed., sec. 2.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "RAMP_ROWS",
    "JointLimits",
    "joint_linearisation",
    "ramp_half_width",
    "ramp_rows",
    "terminal_weights",
]

RAMP_ROWS = np.array(
    [
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 1.0, 1.0],
        [1.0, 1.0, -1.0],
        [1.0, -1.0, 1.0],
        [-1.0, 1.0, 1.0],
    ]
)
"""Normals of the cuboctahedron's faces (one row per pair of opposite faces)."""


def ramp_half_width(max_accel_mps2: float, dt: float) -> float:
    """``c``: the per-axis bound of the cuboctahedron inscribed in the ball ``a_max dt``."""
    return max_accel_mps2 * dt / math.sqrt(2.0)


def ramp_rows(max_accel_mps2: float, dt: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(F, b)``: the velocity change ``dv`` a step may make is ``-b <= F dv <= b``.

    The cuboctahedron inscribed in the ball of radius ``max_accel_mps2 dt``: every ``dv`` in
    it reaches the command within the step on the low level's ramp.
    """
    c = ramp_half_width(max_accel_mps2, dt)
    return RAMP_ROWS.copy(), np.array([c, c, c, 2 * c, 2 * c, 2 * c, 2 * c])


@dataclass(frozen=True)
class JointLimits:
    """Position (rad) and velocity (rad/s) limits of the arm's joints, with the MPC's margins.

    ``lower``, ``upper``: the position limits, ``velocity``: the speed limits (from the
    Pinocchio model, i.e. the URDF); ``margin_rad``: how far inside the position limits the
    predicted joints must stay; ``velocity_fraction``: the share of the speed limit the MPC
    may use.
    """

    lower: tuple[float, ...]
    upper: tuple[float, ...]
    velocity: tuple[float, ...]
    margin_rad: float = 0.05
    velocity_fraction: float = 0.9

    def __post_init__(self) -> None:
        n = len(self.lower)
        if not (len(self.upper) == n == len(self.velocity) and n > 0):
            raise ValueError("lower, upper and velocity must have the same length > 0")
        for lo, hi, vel in zip(self.lower, self.upper, self.velocity, strict=True):
            if not (lo + 2 * self.margin_rad < hi and vel > 0):
                raise ValueError(
                    f"joint limits must satisfy lower + 2 margin_rad < upper and velocity > 0,"
                    f" got {lo}, {hi}, {vel} (margin_rad {self.margin_rad})"
                )
        if not (math.isfinite(self.margin_rad) and self.margin_rad >= 0):
            raise ValueError(f"margin_rad must be >= 0, got {self.margin_rad}")
        if not 0.0 < self.velocity_fraction <= 1.0:
            raise ValueError(f"velocity_fraction must be in (0, 1], got {self.velocity_fraction}")

    @classmethod
    def panda(cls, *, margin_rad: float = 0.05, velocity_fraction: float = 0.9) -> JointLimits:
        """The seven arm joints of the Panda, from its Pinocchio model."""
        from codesign_mb.robot.model import N_ARM, PandaModel

        robot = PandaModel()
        return cls(
            tuple(robot.lower[:N_ARM].tolist()),
            tuple(robot.upper[:N_ARM].tolist()),
            tuple(robot.velocity_limit[:N_ARM].tolist()),
            margin_rad,
            velocity_fraction,
        )

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.lower)

    def position_bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The interval the predicted joint positions must stay in (margins applied)."""
        lo = np.asarray(self.lower) + self.margin_rad
        return lo, np.asarray(self.upper) - self.margin_rad

    def speed_bound(self) -> NDArray[np.float64]:
        """The largest joint speed the MPC may predict (rad/s)."""
        return np.asarray(self.velocity) * self.velocity_fraction


def joint_linearisation(robot: object, q: NDArray[np.float64], n_arm: int) -> NDArray[np.float64]:
    """``J_v^+`` (``n_arm x 3``) at ``q``: the arm's joint velocity for a unit TCP velocity.

    The first three columns of the pseudo-inverse of the TCP Jacobian (6 x ``n_arm``, world
    frame; Pinocchio through :meth:`PandaModel.tcp_jacobian`): the minimum-norm joint
    velocity that moves the TCP at ``v`` without turning it.
    """
    jacobian = robot.tcp_jacobian(q)[:, :n_arm]  # type: ignore[attr-defined]
    return np.linalg.pinv(jacobian)[:, :3]


def terminal_weights(
    a: float,
    bp_v: float,
    bp_u: float,
    *,
    position: float,
    velocity: float,
    command: float,
    rate: float,
) -> NDArray[np.float64]:
    """``P`` (3 x 3): the per-axis cost-to-go ``x' P x`` of the state ``x = (e_p, e_v, e_u-)``.

    The model in error coordinates (reference moving at the reference velocity):
    ``e_p+ = e_p + bp_v e_v + bp_u e_u``, ``e_v+ = a e_v + (1 - a) e_u``, ``e_u-+ = e_u``;
    the stage cost of :class:`~codesign_mb.control.mpc_qp_problem.MpcQpProblem`,
    ``position e_p+^2 + velocity e_v+^2 + command e_u^2 + rate (e_u - e_u-)^2``, written as
    ``|C x + D u|^2_W``. ``P`` solves the DARE with ``Q = C'WC``, ``R = D'WD``, ``S = C'WD``
    (python-control's ``dare``).
    """
    import control

    A = np.array([[1.0, bp_v, 0.0], [0.0, a, 0.0], [0.0, 0.0, 0.0]])
    B = np.array([[bp_u], [1.0 - a], [1.0]])
    # Outputs weighted by W: e_p+, e_v+, e_u, e_u - e_u-.
    C = np.array([[1.0, bp_v, 0.0], [0.0, a, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    D = np.array([[bp_u], [1.0 - a], [1.0], [1.0]])
    W = np.diag([position, velocity, command, rate])
    P, _, _ = control.dare(A, B, C.T @ W @ C, D.T @ W @ D, C.T @ W @ D)
    P = np.asarray(P, dtype=float)
    return 0.5 * (P + P.T)


def joint_steps(horizon: int) -> tuple[int, ...]:
    """Horizon steps ``k`` (1-based) whose predicted joints are limited: 1, 2, 4, 8, ... and N.

    Every step would add ``14 N`` rows whose coefficients change with the configuration
    (and so the solver's matrix setup each step); the linearisation is also least accurate
    far out. The first steps, where the command applied now acts, are all checked.
    """
    steps = []
    k = 1
    while k < horizon:
        steps.append(k)
        k *= 2
    steps.append(horizon)
    return tuple(steps)


class JointRows:
    """The joint-limit rows of the MPC's QP at one configuration (module docstring).

    For each step ``k`` of :func:`joint_steps`, seven rows bound
    ``q0 + J_v^+ (p[k] - p[0])`` to the position limits and seven bound ``J_v^+ v[k]`` to the
    speed limits. ``p[k] = A_pos[k] w + c_pos[k]`` and ``v[k] = A_vel[k] w + c_vel[k]`` are
    the QP's affine predictions (decision ``w``); like the workspace box, the bounds are
    widened to the braking path from the measured state, so a state at (or past) a limit
    keeps a feasible problem whose solutions do not go further.

    Parameters
    ----------
    limits:
        :class:`JointLimits`.
    position_map, velocity_map:
        ``A_pos``, ``A_vel``, shape ``(K, 3, n_var)``.
    """

    def __init__(
        self,
        limits: JointLimits,
        position_map: NDArray[np.float64],
        velocity_map: NDArray[np.float64],
    ) -> None:
        self.limits = limits
        self.position_map = position_map
        self.velocity_map = velocity_map
        self.k = position_map.shape[0]
        self.n_rows = 2 * limits.n * self.k
        self._q_lo, self._q_hi = limits.position_bounds()
        self._qd = limits.speed_bound()

    def fill(
        self,
        pinv: NDArray[np.float64],
        q0: NDArray[np.float64],
        p0: NDArray[np.float64],
        position_offset: NDArray[np.float64],
        velocity_offset: NDArray[np.float64],
        stop_position: NDArray[np.float64],
        stop_velocity: NDArray[np.float64],
        matrix: NDArray[np.float64] | None,
        lower: NDArray[np.float64],
        upper: NDArray[np.float64],
    ) -> None:
        """Write the rows (``matrix``) and their bounds minus offsets (``lower``, ``upper``).

        ``pinv``: ``J_v^+`` (``n_joints x 3``) at (or near) ``q0``; ``p0``: the measured TCP
        position; ``*_offset``: ``c_pos``, ``c_vel`` at the steps (``K x 3``); ``stop_*``: the
        braking path's positions and velocities at the steps (``K x 3``). ``matrix=None``:
        the rows are already those of ``pinv``, only the bounds are written.
        """
        half = self.limits.n * self.k
        if matrix is not None:
            matrix[:half] = np.matmul(pinv, self.position_map).reshape(half, -1)
            matrix[half:] = np.matmul(pinv, self.velocity_map).reshape(half, -1)
        offset = (position_offset - p0) @ pinv.T + q0  # the joints at w = 0
        stop = (stop_position - p0) @ pinv.T + q0
        lower[:half] = (np.minimum(self._q_lo, stop) - offset).ravel()
        upper[:half] = (np.maximum(self._q_hi, stop) - offset).ravel()
        offset = velocity_offset @ pinv.T
        stop = stop_velocity @ pinv.T
        lower[half:] = (np.minimum(-self._qd, stop) - offset).ravel()
        upper[half:] = (np.maximum(self._qd, stop) - offset).ravel()
