"""The conveyor MPC's parametric QP (:class:`MpcQpProblem`): the model, built once in CasADi.

What is solved, kept apart from how: :class:`~codesign_mb.control.mpc_qp.MpcQp` adds the
solvers that re-solve it each step.

Model (per Cartesian axis, control period ``dt``)
-------------------------------------------------
The arm's low-level operational-space loop (:mod:`codesign_mb.robot.osc`) makes the gripper
velocity ``v`` follow the commanded Cartesian velocity ``u``: its velocity reference slews
towards the command at 8 m/s^2 (in norm), and the TCP tracks the reference. As long as the
change of the command stays within that slew (the *ramp* constraint below), the TCP
velocity reaches the command within one 40 ms step, on a ramp, so the model is::

    v[k+1] = u[k]
    p[k+1] = p[k] + dt (beta v[k] + (1 - beta) u[k])        (beta = 0.31)

``beta`` is identified by least squares on closed-loop steps against MuJoCo
(:func:`codesign_mb.bench.mpc.one_step_model_error`, which also prints the one-step
prediction error: p99 below 2 mm, where the same model without the ramp constraint, whose
commands outran the slew, had 10 mm).

and, more generally (:func:`lag_discretisation`), the exact discretisation of a first-order lag
of time constant ``T`` (:attr:`MpcConfig.lag_time_constant_s`), ``a = exp(-dt / T)``::

    v[k+1] = a v[k] + (1 - a) u[k]
    p[k+1] = p[k] + T (1 - a) v[k] + (dt - T (1 - a)) u[k]

The object moves with the belt at a constant velocity ``w``: ``o[k] = o[0] + k dt w``.
Everything is linear, so the finite-horizon problem is a convex QP; the object's predicted
path only enters the QP's linear term and constraint bounds.

QP over the horizon ``N`` (decision ``U = (u[0], ..., u[N-1])`` and one slack ``s >= 0``)::

    min  sum_k |p[k] - r[k]|^2_Q + |v[k] - vr[k]|^2_Qv + |u[k] - vr[k]|^2_R
         + |u[k] - u[k-1]|^2_S + rho1 s + rho2 s^2 + x[N]' P x[N]
    s.t. |u[k]| <= v_max                                   (velocity, hard, per axis)
         v[k+1] - v[k] in the ramp's cuboctahedron         (acceleration, hard, 7 rows)
         lo[k] <= p[k] <= hi[k], k = 1..N                  (workspace box, hard)
         z[k] + s >= c[k]                                  (clearance plane, soft)
         z[k] - c |x[k] - ox[k]| + s >= h[k]  (same in y)  (approach funnel, soft)
         q_lo <= q0 + J_v^+ (p[k] - p[0]) <= q_hi          (joint positions, hard)
         |J_v^+ v[k]| <= qd_max                            (joint speeds, hard)

The terminal cost ``x[N]' P x[N]`` (per axis, ``x = (e_p, e_v, e_u-)``) is the LQ cost-to-go
of the unconstrained problem, and the ramp, the joint rows and ``J_v^+`` (the Pinocchio
Jacobian at the measured joints ``q0``, limited at the steps ``k = 1, 2, 4, 8, .., N``) are
built in :mod:`~codesign_mb.control.mpc_model`, which says why each is what it is.

The workspace box ``[lo, hi]`` is widened, where needed, to the path of a maximal braking from
the measured state, so a gripper outside it or too fast to stop inside it (pushed by a contact,
or at the end of its reach) still has a feasible problem that brings it back; only a measured
speed beyond ``v_max + a_max dt`` makes the QP infeasible, and then the controller falls back to
a safe command (stop, or a bounded push back into the box) and counts the failure.

Approach from above: until the gripper is aligned with the object, the *clearance plane*
``c[k]`` (the grasp point plus a clearance) keeps it above the object; once aligned, the
*approach funnel* (the pyramid of slope ``c`` with its apex ``h[k]`` at the grasp point)
lets it come down only as long as it stays laterally on the object. Each is linear (four
faces per step for the funnel), so the problem stays a QP; a bound of ``-inf``-like value
switches one off. The Hessian and the constraint matrix are constant (the weights do not
depend on the phase): only the linear term and the bounds change from step to step, and
the joint rows, whose coefficients follow the configuration: they are rewritten when the
controller relinearises (:attr:`MpcConfig.joint_relinearise_rad`), and the solver then redoes
its matrix setup (DAQP: ``Model.update`` with the new ``A``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.control.mpc_config import MpcConfig
from codesign_mb.control.mpc_model import (
    JointLimits,
    JointRows,
    joint_steps,
    ramp_half_width,
    ramp_rows,
    terminal_weights,
)

__all__ = ["OFF", "MpcQpProblem", "lag_discretisation"]

OFF = 1e3
"""A constraint whose lower bound is ``-OFF`` metres is inactive."""

Joints = tuple[NDArray[np.float64], NDArray[np.float64]]
"""The arm's measured joint positions ``q0`` and ``J_v^+`` at them (:mod:`.mpc_model`)."""


def lag_discretisation(
    dt: float, lag_time_constant_s: float, position_blend: float = 0.0
) -> tuple[float, float, float]:
    """``(a, bp_v, bp_u)`` of the model ``v+ = a v + (1 - a) u``, ``p+ = p + bp_v v + bp_u u``.

    With ``T > 0`` it is the exact discretisation of a first-order lag of time constant ``T``.
    With ``T = 0`` the velocity reaches the command within the step, and ``position_blend``
    ``beta`` is the share of the step travelled at the old velocity:
    ``p+ = p + dt (beta v + (1 - beta) u)`` (a ramp between them gives ``beta`` near 1/2 for a
    ramp lasting the whole step, 0 for an instant change).
    """
    if lag_time_constant_s <= 0.0:
        return 0.0, position_blend * dt, (1.0 - position_blend) * dt
    a = math.exp(-dt / lag_time_constant_s)
    bp_v = lag_time_constant_s * (1.0 - a)
    return a, bp_v, dt - bp_v


class MpcQpProblem:
    """The MPC's parametric QP, built once with CasADi.

    What :class:`~codesign_mb.control.mpc_qp.MpcQp`, its subclass, solves each step.
    The parameter vector ``theta`` (:meth:`pack`) holds the measured gripper position and
    velocity, the previous command, and per horizon step the position reference, the velocity
    reference (also the command's feed-forward), the funnel apex ``(ox, oy, h)`` and the
    clearance plane's height. The QP data
    are affine in ``theta``: ``g = G theta + g0``, bounds ``= const - (B theta + b0)``; the
    Hessian ``H`` and the constraint matrix ``A`` are constant. :meth:`qp_data` is the data at
    ``theta`` as a dict.

    Parameters
    ----------
    config:
        Horizon, weights, limits, solver.
    dt:
        Control period in s.
    max_speed_mps:
        The plant's Cartesian speed that ``|action| = 1`` commands; bounds ``|u|`` with
        :attr:`MpcConfig.speed_fraction`.
    """

    def __init__(
        self,
        config: MpcConfig,
        *,
        dt: float,
        max_speed_mps: float,
        joint_limits: JointLimits | None = None,
    ) -> None:
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be > 0, got {dt}")
        if not (math.isfinite(max_speed_mps) and max_speed_mps > 0):
            raise ValueError(f"max_speed_mps must be > 0, got {max_speed_mps}")
        if config.workspace_low is None:
            raise ValueError(
                "workspace_low/workspace_high are not set: give them in MpcConfig or build "
                "the controller with MpcController.from_env"
            )
        self.config = config
        self.joint_limits = joint_limits
        self.dt = float(dt)
        self.v_max = float(max_speed_mps) * config.speed_fraction
        self.n = config.horizon
        self.n_theta = 9 + 10 * self.n
        self.n_var = 3 * self.n + 1
        self._build()

    # -- construction -------------------------------------------------------------------
    def _symbolic(self, ca: Any, theta: Any, w: Any) -> tuple[Any, Any, Any, Any]:
        """The cost, the constraints and the predicted positions and velocities, in CasADi."""
        cfg, n = self.config, self.n
        ramp = ca.DM(ramp_rows(cfg.max_accel_mps2, self.dt)[0])
        a, bp_v, bp_u = lag_discretisation(self.dt, cfg.lag_time_constant_s, cfg.position_blend)
        p, v, u_prev = theta[0:3], theta[3:6], theta[6:9]
        ref = ca.reshape(theta[9 : 9 + 3 * n], 3, n)
        vref = ca.reshape(theta[9 + 3 * n : 9 + 6 * n], 3, n)
        apex = ca.reshape(theta[9 + 6 * n : 9 + 9 * n], 3, n)
        plane = theta[9 + 9 * n : 9 + 10 * n]
        U = ca.reshape(w[: 3 * n], 3, n)
        s = w[3 * n]
        q_pos = ca.diag(ca.DM([cfg.weight_position, cfg.weight_position, cfg.weight_height]))
        cost = cfg.slack_linear * s + cfg.slack_quadratic * s**2
        acc, pos, vel, funnel, clearance = [], [], [], [], []
        u_last = u_prev
        c = cfg.funnel_slope
        c_y = c if cfg.funnel_slope_y is None else cfg.funnel_slope_y
        for k in range(n):
            uk = U[:, k]
            v_next = a * v + (1 - a) * uk
            p = p + bp_v * v + bp_u * uk
            acc.append(ca.mtimes(ramp, v_next - v))
            v = v_next
            pos.append(p)
            vel.append(v)
            e = p - ref[:, k]
            cost += ca.bilin(q_pos, e, e)
            cost += cfg.weight_velocity * ca.sumsqr(v - vref[:, k])
            cost += cfg.weight_command * ca.sumsqr(uk - vref[:, k])
            cost += cfg.weight_rate * ca.sumsqr(uk - u_last)
            u_last = uk
            dx = p[0] - apex[0, k]
            dy = p[1] - apex[1, k]
            rel = p[2] - apex[2, k] + s
            funnel.extend([rel - c * dx, rel + c * dx, rel - c_y * dy, rel + c_y * dy])
            clearance.append(p[2] + s - plane[k])
        # Terminal cost: the per-axis LQ cost-to-go of (e_p, e_v, e_u-) at step N (DARE).
        for i, weight in enumerate((cfg.weight_position, cfg.weight_position, cfg.weight_height)):
            P = terminal_weights(
                a, bp_v, bp_u, position=weight, velocity=cfg.weight_velocity,
                command=cfg.weight_command, rate=cfg.weight_rate,
            )  # fmt: skip
            x = ca.vertcat(p[i] - ref[i, n - 1], v[i] - vref[i, n - 1], u_last[i] - vref[i, n - 1])
            cost += cfg.weight_terminal * ca.bilin(ca.DM(P), x, x)
        return cost, ca.vertcat(*acc, *pos, *funnel, *clearance), ca.vertcat(*pos), ca.vertcat(*vel)

    def _build(self) -> None:
        import casadi as ca

        cfg, n, dt = self.config, self.n, self.dt
        a, bp_v, bp_u = lag_discretisation(dt, cfg.lag_time_constant_s, cfg.position_blend)
        theta = ca.SX.sym("theta", self.n_theta)
        w = ca.SX.sym("w", self.n_var)
        cost, g, pos, vel = self._symbolic(ca, theta, w)
        steps = [k - 1 for k in joint_steps(n)] if self.joint_limits is not None else []
        # The predicted positions and velocities at the joint-limited steps, affine in w.
        pos_k = ca.vertcat(*[pos[3 * k : 3 * k + 3] for k in steps]) if steps else ca.DM()
        vel_k = ca.vertcat(*[vel[3 * k : 3 * k + 3] for k in steps]) if steps else ca.DM()
        # Split everything into its constant and theta-affine parts, numerically, once.
        H = ca.hessian(cost, w)[0]
        grad0 = ca.substitute(ca.gradient(cost, w), w, ca.DM.zeros(self.n_var))
        A = ca.jacobian(g, w)
        g_off = ca.substitute(g, w, ca.DM.zeros(self.n_var))
        maps = ca.Function(
            "maps",
            [theta],
            [H, A, ca.jacobian(grad0, theta), ca.jacobian(g_off, theta)],
        )
        zero = ca.DM.zeros(self.n_theta)
        H_num, A_num, G_num, B_num = (np.array(ca.DM(m)) for m in maps(zero))
        offsets = ca.Function("offsets", [theta], [grad0, g_off])
        g0, b0 = (np.array(m).ravel() for m in offsets(zero))
        self.joints: JointRows | None = None
        if self.joint_limits is not None:
            pv = ca.vertcat(pos_k, vel_k)
            pv_map = ca.Function("pv", [theta], [ca.jacobian(pv, w), ca.jacobian(pv, theta)])
            pv_off = ca.Function("pv0", [theta], [ca.substitute(pv, w, ca.DM.zeros(self.n_var))])
            A_pv, B_pv = (np.array(ca.DM(m)) for m in pv_map(zero))
            half = 3 * len(steps)
            self.joints = JointRows(
                self.joint_limits,
                A_pv[:half].reshape(len(steps), 3, self.n_var),
                A_pv[half:].reshape(len(steps), 3, self.n_var),
            )
            self._pv_map = (B_pv, np.array(pv_off(zero)).ravel())
            A_num = np.vstack([A_num, np.zeros((self.joints.n_rows, self.n_var))])
            B_num = np.vstack([B_num, np.zeros((self.joints.n_rows, self.n_theta))])
            b0 = np.concatenate([b0, np.zeros(self.joints.n_rows)])
        self.joint_steps = tuple(k + 1 for k in steps)
        self.n_con = A_num.shape[0]
        self.H = H_num
        self.A = A_num
        self.G, self.g0 = G_num, g0
        self.B, self.b0 = B_num, b0
        self._H_dm = ca.DM(H_num)
        self._A_dm = ca.DM(A_num)
        ramp_bound = np.tile(ramp_rows(cfg.max_accel_mps2, dt)[1], n)
        # Braking: every axis slows by the same step, (s, s, s) inside the cuboctahedron.
        acc_bound = 2.0 * ramp_half_width(cfg.max_accel_mps2, dt) / 3.0
        self._model = (a, bp_v, bp_u)
        self._acc_bound = acc_bound
        self._ws_low, self._ws_high = np.asarray(cfg.workspace_low), np.asarray(cfg.workspace_high)
        lo = np.array(cfg.workspace_low)
        hi = np.array(cfg.workspace_high)
        n_joint = self.n_con - 15 * n
        self.con_low = np.concatenate(
            [-ramp_bound, np.tile(lo, n), np.zeros(5 * n), np.full(n_joint, -OFF)]
        )
        self.con_high = np.concatenate(
            [ramp_bound, np.tile(hi, n), np.full(5 * n, np.inf), np.full(n_joint, OFF)]
        )
        self.var_low = np.concatenate([np.full(3 * n, -self.v_max), [0.0]])
        self.var_high = np.concatenate([np.full(3 * n, self.v_max), [np.inf]])
        # Constraint row blocks, for tests and diagnostics.
        self.rows = {
            "acceleration": slice(0, 7 * n),
            "workspace": slice(7 * n, 10 * n),
            "funnel": slice(10 * n, 14 * n),
            "clearance": slice(14 * n, 15 * n),
            "joint_position": slice(15 * n, 15 * n + n_joint // 2),
            "joint_velocity": slice(15 * n + n_joint // 2, 15 * n + n_joint),
        }
        self._ca = ca
        self._k_step = np.arange(n + 1)[:, None] * (acc_bound / (1.0 - a))  # k * step, k = 0..N
        if self.joints is not None:
            self._joint_rows = slice(self.rows["joint_position"].start, self.n_con)
            self._joint_index = np.asarray(steps)

    # -- the QP at theta ----------------------------------------------------------------
    def pack(
        self,
        position: NDArray[np.float64],
        velocity: NDArray[np.float64],
        previous_command: NDArray[np.float64],
        reference: NDArray[np.float64],
        velocity_reference: NDArray[np.float64],
        apex: NDArray[np.float64],
        plane: NDArray[np.float64] | float = -OFF,
    ) -> NDArray[np.float64]:
        """The parameter vector ``theta``.

        ``reference``, ``velocity_reference`` and ``apex`` have shape ``(N, 3)``; ``plane`` has
        shape ``(N,)`` or is a scalar. An apex height or plane of ``-OFF`` switches it off.
        """
        n = self.n
        parts = [
            np.asarray(position, dtype=float).reshape(3),
            np.asarray(velocity, dtype=float).reshape(3),
            np.asarray(previous_command, dtype=float).reshape(3),
            np.asarray(reference, dtype=float).reshape(n, 3).ravel(),
            np.asarray(velocity_reference, dtype=float).reshape(n, 3).ravel(),
            np.asarray(apex, dtype=float).reshape(n, 3).ravel(),
            np.broadcast_to(np.asarray(plane, dtype=float), (n,)),
        ]
        return np.concatenate(parts)

    def qp_data(
        self, theta: NDArray[np.float64], joints: Joints | None = None
    ) -> dict[str, NDArray[np.float64]]:
        """The QP ``min 1/2 w'Hw + g'w, lba <= A w <= uba, lbx <= w <= ubx`` at ``theta``.

        With ``joints`` (and :attr:`joint_limits`), the joint-limit rows are those of the
        configuration (:class:`~codesign_mb.control.mpc_model.JointRows`); without, they are
        zero and unbounded.

        The workspace bounds are widened, where needed, to the path of a maximal braking
        from the measured state (:meth:`stopping_path`): a gripper outside the box, or too
        fast towards its wall to stop inside, keeps a feasible problem and is brought back
        by the cost. Only a velocity beyond ``v_max + a_max dt`` makes the QP infeasible.
        """
        offset = self.B @ theta + self.b0
        low, high = self.con_low.copy(), self.con_high.copy()
        stop = self.stopping_path(theta[0:3], theta[3:6])
        rows = self.rows["workspace"]
        low[rows] = np.minimum(low[rows], stop.ravel())
        high[rows] = np.maximum(high[rows], stop.ravel())
        A, lba, uba = self.A.copy(), low - offset, high - offset
        if self.joints is not None:
            rows = self._joint_rows
            A[rows] = 0.0
            if joints is not None:
                self._joint_data(theta, joints, A[rows], lba[rows], uba[rows])
        return {
            "h": self.H,
            "g": self.G @ theta + self.g0,
            "a": A,
            "lba": lba,
            "uba": uba,
            "lbx": self.var_low,
            "ubx": self.var_high,
        }

    def _joint_data(
        self,
        theta: NDArray[np.float64],
        joints: Joints,
        matrix: NDArray[np.float64] | None,
        lower: NDArray[np.float64],
        upper: NDArray[np.float64],
    ) -> None:
        """The joint-limit rows (unless ``matrix`` is None) and their bounds at ``theta``."""
        assert self.joints is not None
        q0, pinv = joints
        B_pv, b_pv = self._pv_map
        pv = B_pv @ theta + b_pv
        half = 3 * self._joint_index.size
        stop_p, stop_v = self.braking_path(theta[0:3], theta[3:6])
        k = self._joint_index
        self.joints.fill(
            pinv, q0, theta[0:3], pv[:half].reshape(-1, 3), pv[half:].reshape(-1, 3),
            stop_p[k], stop_v[k], matrix, lower, upper,
        )  # fmt: skip

    def stopping_path(
        self, position: NDArray[np.float64], velocity: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Positions ``p[1..N]`` (shape ``(N, 3)``) when braking as hard as the constraints allow.

        Per axis, the command steps the velocity towards zero by the same step each step
        (``(s, s, s)`` inside the ramp's cuboctahedron: it satisfies the velocity and
        acceleration constraints whenever the measured speed is within ``v_max + s``).
        """
        return self.braking_path(position, velocity)[0]

    def braking_path(
        self, position: NDArray[np.float64], velocity: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Positions and velocities ``p[1..N]``, ``v[1..N]`` of :meth:`stopping_path`."""
        a, bp_v, bp_u = self._model
        step = self._acc_bound / (1.0 - a)
        if a == 0.0:  # the velocity is the command: closed form
            v = np.asarray(velocity, dtype=float)
            speeds = np.maximum(np.abs(v) - self._k_step, 0.0)
            np.minimum(speeds[1:], self.v_max, out=speeds[1:])
            vs = np.sign(v) * speeds  # v[0..N]; u[k] = v[k+1]
            return position + np.cumsum(bp_v * vs[:-1] + bp_u * vs[1:], axis=0), vs[1:]
        p = np.asarray(position, dtype=float).copy()
        v = np.asarray(velocity, dtype=float).copy()
        out, vel = np.empty((self.n, 3)), np.empty((self.n, 3))
        for k in range(self.n):
            u = np.clip(np.sign(v) * np.maximum(np.abs(v) - step, 0.0), -self.v_max, self.v_max)
            p = p + bp_v * v + bp_u * u
            v = a * v + (1.0 - a) * u
            out[k], vel[k] = p, v
        return out, vel

    def __getstate__(self) -> dict[str, Any]:
        # The CasADi objects are rebuilt on unpickling (worker processes).
        return {
            "config": self.config,
            "dt": self.dt,
            "max_speed_mps": self.v_max / self.config.speed_fraction,
            "joint_limits": self.joint_limits,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state.pop("config"), **state)  # type: ignore[misc]
