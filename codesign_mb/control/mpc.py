"""Model predictive control of the conveyor pick: a QP built once in CasADi, re-solved each step.

The ideal controller ``pi_c`` of paper.tex sec. 4.A (``eq_control_ideal``), done model-based.

Model (per Cartesian axis, control period ``dt``)
-------------------------------------------------
The arm's low-level operational-space loop (:mod:`codesign_mb.robot.osc`) makes the gripper
velocity ``v`` follow the commanded Cartesian velocity ``u``. Identified on the plant with
step commands: the TCP velocity reaches the command within one 40 ms step (the reference
slews at 12 m/s^2), on a ramp, so the model is::

    v[k+1] = u[k]
    p[k+1] = p[k] + dt (beta v[k] + (1 - beta) u[k])        (beta = 0.25)

and, more generally (:func:`lag_discretisation`), the exact discretisation of a first-order lag
of time constant ``T`` (:attr:`MpcConfig.lag_time_constant_s`), ``a = exp(-dt / T)``::

    v[k+1] = a v[k] + (1 - a) u[k]
    p[k+1] = p[k] + T (1 - a) v[k] + (dt - T (1 - a)) u[k]

The object moves with the belt at a constant velocity ``w``: ``o[k] = o[0] + k dt w``.
Everything is linear, so the finite-horizon problem is a convex QP; the object's predicted
path only enters the QP's linear term and constraint bounds.

QP over the horizon ``N`` (decision ``U = (u[0], ..., u[N-1])`` and one slack ``s >= 0``)::

    min  sum_k |p[k] - r[k]|^2_Q + |v[k] - vr[k]|^2_Qv + |u[k] - vr[k]|^2_R
         + |u[k] - u[k-1]|^2_S + rho1 s + rho2 s^2
    s.t. |u[k]| <= v_max                                   (velocity, hard, per axis)
         |v[k+1] - v[k]| <= a_max dt                       (acceleration, hard)
         lo[k] <= p[k] <= hi[k], k = 1..N                  (workspace box, hard)
         z[k] + s >= c[k]                                  (clearance plane, soft)
         z[k] - c |x[k] - ox[k]| + s >= h[k]  (same in y)  (approach funnel, soft)

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
depend on the phase): only the linear term and the bounds change from step to step.

Phases (explicit, :class:`Phase`)
---------------------------------
APPROACH (reference: hover above the object's predicted path) -> DESCEND (reference: the grasp
point, once aligned laterally; back to APPROACH only if the lateral error grows beyond
:attr:`MpcConfig.abort_tolerance_m`, the funnel keeping the gripper high enough in between) ->
GRASP (close the fingers while tracking, for a few steps) -> LIFT (reference: straight up;
funnel off). A grasp that closes on nothing (fingers shut) opens and goes back to APPROACH.
The defaults were tuned on the conveyor with perception noise and a variable belt speed.

Why a QP with qpOASES
---------------------
The model is linear and the constraints are polyhedral, so the problem is a small, dense,
strictly convex QP (3N + 1 variables, 11N constraints: 46 and 165 at N = 15); an NLP solver
(IPOPT, FATROP) would only add overhead and iterations. qpOASES is an active-set method made
for parametric MPC: its hot start begins from the previous step's active set, so most steps
take zero to a few iterations, and its solutions are exact vertices (bounds respected to
machine precision, where an ADMM solver such as OSQP stops at a tolerance and needs polishing).
On the recorded closed-loop problems it is the fastest of the three plugins (median about
0.5 ms of CPU per step, ``codesign bench mpc``); DAQP (dual active set) is close, with a
slightly higher median and a tighter tail, OSQP an order of magnitude slower at the accuracy
used here. Both stay selectable through :attr:`MpcConfig.solver`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import io
import math
import sys
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.control.conic_buffer import ConicBuffer
from codesign_mb.control.mpc_kernels import fill_parameters, stopping_bounds, worst_violation

__all__ = ["MpcConfig", "MpcController", "MpcQp", "Phase"]

_SOLVERS = ("qpoases", "osqp", "daqp")
_SUCCESS_STATUS = {"qpoases": "Successful return."}
"""What a solver's ``return_status`` says on success, when it is known without asking."""

OFF = 1e3
"""A constraint whose lower bound is ``-OFF`` metres is inactive."""


class Phase(enum.IntEnum):
    """The pick's phases, in order."""

    APPROACH = 0
    DESCEND = 1
    GRASP = 2
    LIFT = 3


@dataclass(frozen=True)
class MpcConfig:
    """Settings of :class:`MpcController` (lengths in m, times in s).

    Parameters
    ----------
    horizon:
        Prediction horizon ``N`` in control steps (10-25 is sensible at 40 ms).
    lag_time_constant_s:
        Time constant ``T`` of the gripper velocity's response to the command (0: none).
    position_blend:
        With ``T = 0``: share of a step travelled at the previous velocity (see
        :func:`lag_discretisation`). The defaults are identified from the plant's
        operational-space loop, whose velocity reference slews at 12 m/s^2: the TCP velocity
        reaches a command within one 40 ms step, on a ramp.
    max_accel_mps2:
        Bound on the predicted gripper acceleration, per axis.
    speed_fraction:
        Fraction of the plant's maximum Cartesian speed the MPC may command, in (0, 1].
    workspace_low, workspace_high:
        Corners of the box the gripper must stay in, world frame; ``None``: the plant's box
        shrunk by :attr:`workspace_margin_m` (:meth:`MpcController.from_env`).
    workspace_margin_m:
        How far inside the plant's workspace box the MPC's box lies.
    funnel_slope:
        ``c``: height gained per metre of lateral offset from the object (approach funnel).
    clearance_m:
        Height of the clearance plane above the grasp point while not aligned (APPROACH).
    hover_height_m:
        Height of the APPROACH reference above the grasp point.
    grasp_offset_m:
        Gripper position minus object position at the grasp (world frame, e.g. the fingertip
        centre slightly above the object's centre).
    lift_height_m:
        How far the LIFT reference rises above where the gripper closed.
    align_tolerance_m:
        Lateral error below which APPROACH becomes DESCEND.
    abort_tolerance_m:
        Lateral error above which DESCEND returns to APPROACH (in between, the funnel keeps
        the gripper high enough while it re-aligns).
    grasp_tolerance_m, grasp_height_tolerance_m:
        Lateral and vertical distances to the grasp point below which the fingers close.
    funnel_apex_depth_m:
        How far below the grasp point the funnel's apex lies: room for the last centimetre
        of the descent despite a small lateral error (perception noise).
    close_steps:
        Steps the fingers get to close before LIFT.
    min_grip_width_m:
        A finger width below this after closing means the grasp missed (back to APPROACH).
    weight_position, weight_height, weight_velocity, weight_command, weight_rate, weight_terminal:
        Cost weights: lateral and vertical position error, velocity tracking, command
        deviation from the feed-forward, command rate, terminal multiplier.
    slack_linear, slack_quadratic:
        Penalties ``rho1, rho2`` on the slack of the soft constraints (plane and funnel).
    solver:
        ``"qpoases"`` (default), ``"osqp"`` or ``"daqp"``.
    """

    horizon: int = 15
    lag_time_constant_s: float = 0.0
    position_blend: float = 0.25
    max_accel_mps2: float = 10.0
    speed_fraction: float = 1.0
    workspace_low: tuple[float, float, float] | None = None
    workspace_high: tuple[float, float, float] | None = None
    workspace_margin_m: float = 0.005
    funnel_slope: float = 1.5
    clearance_m: float = 0.04
    hover_height_m: float = 0.06
    grasp_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lift_height_m: float = 0.15
    align_tolerance_m: float = 0.01
    abort_tolerance_m: float = 0.04
    grasp_tolerance_m: float = 0.012
    grasp_height_tolerance_m: float = 0.015
    funnel_apex_depth_m: float = 0.015
    close_steps: int = 5
    min_grip_width_m: float = 0.005
    weight_position: float = 100.0
    weight_height: float = 100.0
    weight_velocity: float = 1.0
    weight_command: float = 0.1
    weight_rate: float = 1.0
    weight_terminal: float = 5.0
    slack_linear: float = 1e3
    slack_quadratic: float = 1e4
    solver: str = "qpoases"

    def __post_init__(self) -> None:
        for name in ("horizon", "close_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f"{name} must be an integer, got {value!r}")
        if not 2 <= self.horizon <= 100:
            raise ValueError(f"horizon must be in [2, 100], got {self.horizon}")
        if self.close_steps < 0:
            raise ValueError(f"close_steps must be >= 0, got {self.close_steps}")
        for name in ("workspace_low", "workspace_high", "grasp_offset_m"):
            if getattr(self, name) is None and name != "grasp_offset_m":
                continue
            value = tuple(float(v) for v in getattr(self, name))
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise ValueError(f"{name} must be 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        if (self.workspace_low is None) != (self.workspace_high is None):
            raise ValueError("workspace_low and workspace_high must be given together")
        if self.workspace_low is not None and any(
            lo >= hi for lo, hi in zip(self.workspace_low, self.workspace_high, strict=True)
        ):
            raise ValueError(
                f"workspace_low must be < workspace_high, got {self.workspace_low} and "
                f"{self.workspace_high}"
            )
        if not 0.0 <= self.position_blend <= 1.0:
            raise ValueError(f"position_blend must be in [0, 1], got {self.position_blend}")
        if not 0.0 < self.speed_fraction <= 1.0:
            raise ValueError(f"speed_fraction must be in (0, 1], got {self.speed_fraction}")
        positive = (
            "max_accel_mps2",
            "align_tolerance_m",
            "abort_tolerance_m",
            "grasp_tolerance_m",
            "grasp_height_tolerance_m",
        )
        non_negative = (
            "lag_time_constant_s",
            "workspace_margin_m",
            "funnel_slope",
            "funnel_apex_depth_m",
            "clearance_m",
            "hover_height_m",
            "lift_height_m",
            "min_grip_width_m",
            "weight_position",
            "weight_height",
            "weight_velocity",
            "weight_command",
            "weight_terminal",
            "slack_linear",
            "slack_quadratic",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value}")
        for name in non_negative:
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0, got {value}")
        if not (math.isfinite(self.weight_rate) and self.weight_rate > 0):
            raise ValueError(f"weight_rate must be > 0, got {self.weight_rate}")
        if self.solver not in _SOLVERS:
            raise ValueError(f"solver must be one of {', '.join(_SOLVERS)}, got {self.solver!r}")


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


@dataclass
class MpcSolution:
    """One solve: the command sequence ``(N, 3)``, success, the solver's wall and CPU time."""

    commands: NDArray[np.float64]
    success: bool
    status: str
    solve_time_s: float
    slack: float = 0.0
    cpu_time_s: float = 0.0


class MpcQp:
    """The MPC's parametric QP, built once with CasADi.

    The parameter vector ``theta`` (:meth:`pack`) holds the measured gripper position and
    velocity, the previous command, and per horizon step the position reference, the velocity
    reference (also the command's feed-forward), the funnel apex ``(ox, oy, h)`` and the
    clearance plane's height. The QP data
    are affine in ``theta``: ``g = G theta + g0``, bounds ``= const - (B theta + b0)``; the
    Hessian ``H`` and the constraint matrix ``A`` are constant. :meth:`solve` evaluates these
    maps (numpy products, the rest compiled in :mod:`~codesign_mb.control.mpc_kernels`)
    straight into the arrays bound to the ``casadi.conic`` solver's buffer
    (:class:`~codesign_mb.control.conic_buffer.ConicBuffer`; ``H`` and ``A`` set once per
    instance); :meth:`qp_data` is the same data as a dict. Warm start comes from qpOASES'
    hot start (or the shifted previous solution for OSQP/DAQP).

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

    def __init__(self, config: MpcConfig, *, dt: float, max_speed_mps: float) -> None:
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
        self.dt = float(dt)
        self.v_max = float(max_speed_mps) * config.speed_fraction
        self.n = config.horizon
        self.n_theta = 9 + 10 * self.n
        self.n_var = 3 * self.n + 1
        self._build()
        self._solver: Any = None
        self.reset()

    # -- construction -------------------------------------------------------------------
    def _build(self) -> None:
        import casadi as ca

        cfg, n, dt = self.config, self.n, self.dt
        a, bp_v, bp_u = lag_discretisation(dt, cfg.lag_time_constant_s, cfg.position_blend)
        theta = ca.SX.sym("theta", self.n_theta)
        w = ca.SX.sym("w", self.n_var)
        p, v, u_prev = theta[0:3], theta[3:6], theta[6:9]
        ref = ca.reshape(theta[9 : 9 + 3 * n], 3, n)
        vref = ca.reshape(theta[9 + 3 * n : 9 + 6 * n], 3, n)
        apex = ca.reshape(theta[9 + 6 * n : 9 + 9 * n], 3, n)
        plane = theta[9 + 9 * n : 9 + 10 * n]
        U = ca.reshape(w[: 3 * n], 3, n)
        s = w[3 * n]
        q_pos = ca.diag(ca.DM([cfg.weight_position, cfg.weight_position, cfg.weight_height]))
        cost = cfg.slack_linear * s + cfg.slack_quadratic * s**2
        acc, pos, funnel, clearance = [], [], [], []
        u_last = u_prev
        c = cfg.funnel_slope
        for k in range(n):
            uk = U[:, k]
            v_next = a * v + (1 - a) * uk
            p = p + bp_v * v + bp_u * uk
            acc.append(v_next - v)
            v = v_next
            pos.append(p)
            e = p - ref[:, k]
            terminal = cfg.weight_terminal if k == n - 1 else 1.0
            cost += terminal * ca.bilin(q_pos, e, e)
            cost += terminal * cfg.weight_velocity * ca.sumsqr(v - vref[:, k])
            cost += cfg.weight_command * ca.sumsqr(uk - vref[:, k])
            cost += cfg.weight_rate * ca.sumsqr(uk - u_last)
            u_last = uk
            dx = p[0] - apex[0, k]
            dy = p[1] - apex[1, k]
            rel = p[2] - apex[2, k] + s
            funnel.extend([rel - c * dx, rel + c * dx, rel - c * dy, rel + c * dy])
            clearance.append(p[2] + s - plane[k])
        g = ca.vertcat(*acc, *pos, *funnel, *clearance)
        self.n_con = g.shape[0]
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
        self.H = H_num
        self.A = A_num
        self.G, self.g0 = G_num, g0
        self.B, self.b0 = B_num, b0
        self._H_dm = ca.DM(H_num)
        self._A_dm = ca.DM(A_num)
        acc_bound = cfg.max_accel_mps2 * dt
        self._model = (a, bp_v, bp_u)
        self._acc_bound = acc_bound
        self._ws_low, self._ws_high = np.asarray(cfg.workspace_low), np.asarray(cfg.workspace_high)
        lo = np.array(cfg.workspace_low)
        hi = np.array(cfg.workspace_high)
        self.con_low = np.concatenate([np.full(3 * n, -acc_bound), np.tile(lo, n), np.zeros(5 * n)])
        self.con_high = np.concatenate(
            [np.full(3 * n, acc_bound), np.tile(hi, n), np.full(5 * n, np.inf)]
        )
        self.var_low = np.concatenate([np.full(3 * n, -self.v_max), [0.0]])
        self.var_high = np.concatenate([np.full(3 * n, self.v_max), [np.inf]])
        # Constraint row blocks, for tests and diagnostics.
        self.rows = {
            "acceleration": slice(0, 3 * n),
            "workspace": slice(3 * n, 6 * n),
            "funnel": slice(6 * n, 10 * n),
            "clearance": slice(10 * n, 11 * n),
        }
        self._ca = ca
        # Work arrays of the hot path (solve), allocated once.
        self._k_step = np.arange(n + 1)[:, None] * (acc_bound / (1.0 - a))  # k * step, k = 0..N
        self._offset = np.empty(self.n_con)
        self._low = self.con_low.copy()
        self._high = self.con_high.copy()
        self._ax = np.empty(self.n_con)

    def _make_solver(self) -> Any:
        with _quiet_stdout():  # qpOASES prints its licence banner on every instance
            return self._make_solver_loud()

    def _make_solver_loud(self) -> Any:
        ca = self._ca
        name = self.config.solver
        spec = {"h": self._H_dm.sparsity(), "a": self._A_dm.sparsity()}
        opts: dict[str, Any] = {"error_on_fail": False}
        if name == "qpoases":
            opts.update(printLevel="none", sparse=False, hessian_type="posdef")
        elif name == "osqp":
            opts["osqp"] = {
                "verbose": False,
                "eps_abs": 1e-6,
                "eps_rel": 1e-6,
                "polishing": True,
                "max_iter": 10000,
            }
        elif name == "daqp":
            opts["daqp"] = {}
        return ca.conic("mpc_qp", name, spec, opts)

    def reset(self) -> None:
        """Forget the warm start: a fresh solver instance, so episodes do not depend on history."""
        self._solver = self._make_solver()
        self._warm_inputs = self.config.solver != "qpoases"
        self._x0 = np.zeros(self.n_var)
        self._lam_x0 = np.zeros(self.n_var)
        self._lam_a0 = np.zeros(self.n_con)
        with _quiet_stdout():  # a new solver memory: qpOASES prints its banner again
            self._conic = ConicBuffer(
                self._solver, {"h": self._H_dm.nonzeros(), "a": self._A_dm.nonzeros()}
            )
        self._conic.inputs["lbx"][:] = self.var_low
        self._conic.inputs["ubx"][:] = self.var_high

    # -- runtime ------------------------------------------------------------------------
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

    def qp_data(self, theta: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
        """The QP ``min 1/2 w'Hw + g'w, lba <= A w <= uba, lbx <= w <= ubx`` at ``theta``.

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
        return {
            "h": self.H,
            "g": self.G @ theta + self.g0,
            "a": self.A,
            "lba": low - offset,
            "uba": high - offset,
            "lbx": self.var_low,
            "ubx": self.var_high,
        }

    def stopping_path(
        self, position: NDArray[np.float64], velocity: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Positions ``p[1..N]`` (shape ``(N, 3)``) when braking as hard as the constraints allow.

        Per axis, the command steps the velocity towards zero by the acceleration bound each
        step (it satisfies the velocity and acceleration constraints whenever the measured
        speed is within ``v_max + a_max dt``).
        """
        a, bp_v, bp_u = self._model
        step = self._acc_bound / (1.0 - a)
        if a == 0.0:  # the velocity is the command: closed form
            v = np.asarray(velocity, dtype=float)
            speeds = np.maximum(np.abs(v) - self._k_step, 0.0)
            np.minimum(speeds[1:], self.v_max, out=speeds[1:])
            vs = np.sign(v) * speeds  # v[0..N]; u[k] = v[k+1]
            return position + np.cumsum(bp_v * vs[:-1] + bp_u * vs[1:], axis=0)
        p = np.asarray(position, dtype=float).copy()
        v = np.asarray(velocity, dtype=float).copy()
        out = np.empty((self.n, 3))
        for k in range(self.n):
            u = np.clip(np.sign(v) * np.maximum(np.abs(v) - step, 0.0), -self.v_max, self.v_max)
            p = p + bp_v * v + bp_u * u
            v = a * v + (1.0 - a) * u
            out[k] = p
        return out

    def solve(self, theta: NDArray[np.float64]) -> MpcSolution:
        """Solve the QP at ``theta`` (warm-started from the previous solve).

        The data of :meth:`qp_data` are written into the arrays bound to the solver's buffer
        (:class:`~codesign_mb.control.conic_buffer.ConicBuffer`), so a step converts nothing.
        """
        conic = self._conic
        inputs = conic.inputs
        self._fill(np.asarray(theta, dtype=float), inputs["g"], inputs["lba"], inputs["uba"])
        if self._warm_inputs:  # qpOASES hot-starts from its own active set instead
            inputs["x0"][:] = self._x0
            inputs["lam_x0"][:] = self._lam_x0
            inputs["lam_a0"][:] = self._lam_a0
        saved, sys.stdout = sys.stdout, _NULL_TEXT  # as _quiet_stdout, without its overhead
        try:
            start_cpu = time.thread_time()
            start = time.perf_counter()
            flag = conic()
            elapsed = time.perf_counter() - start
            cpu = time.thread_time() - start_cpu
        finally:
            sys.stdout = saved
        outputs = conic.outputs
        x = outputs["x"].copy()
        # qpOASES: CasADi's unified return status is 0 exactly when it returned successfully.
        success = bool(conic.stats().get("success", False)) if self._warm_inputs else flag == 0
        n = self.n
        if not (success and self._feasible(x, inputs)):
            status = str(conic.stats().get("return_status", ""))
            self.reset()  # never hot-start from a failed solve
            return MpcSolution(np.zeros((n, 3)), False, status or "failed", elapsed, 0.0, cpu)
        if self._warm_inputs:  # shifted primal, previous duals
            self._x0 = np.concatenate([x[3 : 3 * n], x[3 * n - 3 : 3 * n], x[3 * n :]])
            self._lam_x0 = outputs["lam_x"].copy()
            self._lam_a0 = outputs["lam_a"].copy()
        status = _SUCCESS_STATUS.get(self.config.solver) or str(conic.stats()["return_status"])
        return MpcSolution(x[: 3 * n].reshape(n, 3), True, status, elapsed, float(x[3 * n]), cpu)

    def _fill(
        self,
        theta: NDArray[np.float64],
        g: NDArray[np.float64],
        lba: NDArray[np.float64],
        uba: NDArray[np.float64],
    ) -> None:
        """Write :meth:`qp_data`'s ``g``, ``lba``, ``uba`` at ``theta`` into the given arrays."""
        np.matmul(self.G, theta, out=g)
        g += self.g0
        offset = self._offset
        np.matmul(self.B, theta, out=offset)
        offset += self.b0
        a, bp_v, bp_u = self._model
        if a == 0.0:  # compiled closed form, the same arithmetic as below
            row0 = self.rows["workspace"].start
            stopping_bounds(
                theta[0:3], theta[3:6], self._k_step, self.v_max, bp_v, bp_u,
                self.con_low, self.con_high, row0, offset, lba, uba,
            )  # fmt: skip
            return
        low, high = self._low, self._high
        rows = self.rows["workspace"]
        stop = self.stopping_path(theta[0:3], theta[3:6]).ravel()
        np.minimum(self.con_low[rows], stop, out=low[rows])
        np.maximum(self.con_high[rows], stop, out=high[rows])
        np.subtract(low, offset, out=lba)
        np.subtract(high, offset, out=uba)

    def _feasible(
        self, x: NDArray[np.float64], data: Mapping[str, NDArray], tol: float = 1e-5
    ) -> bool:
        """Whether ``x`` satisfies the hard bounds (a solver's "success" is not taken on trust)."""
        ax = np.matmul(self.A, x, out=self._ax)
        worst = worst_violation(x, ax, data["lbx"], data["ubx"], data["lba"], data["uba"])
        return bool(worst <= tol)

    def __getstate__(self) -> dict[str, Any]:
        # The CasADi objects are rebuilt on unpickling (worker processes).
        return {
            "config": self.config,
            "dt": self.dt,
            "max_speed_mps": self.v_max / self.config.speed_fraction,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["config"], dt=state["dt"], max_speed_mps=state["max_speed_mps"])  # type: ignore[misc]


@dataclass
class _EpisodeLog:
    solve_times_s: list[float] = field(default_factory=list)
    cpu_times_s: list[float] = field(default_factory=list)
    failures: int = 0
    phases: list[int] = field(default_factory=list)


class MpcController:
    """MPC ideal controller for the conveyor pick (a :class:`~codesign_mb.control.base.Controller`).

    Reads the gripper's position, velocity and finger width and the object's position and
    (if present) velocity from the plant-layout observation, runs the phase logic, solves the
    QP of :class:`MpcQp` and returns the action ``(u / max_speed, grip)`` in ``[-1, 1]^4``.

    On a solver failure (infeasible or not converged) it returns a safe command instead: no
    motion inside the workspace (a bounded push back towards it from outside), the grip kept.
    Failures are counted (:attr:`failures`, :meth:`episode_metrics`).

    Parameters
    ----------
    layout:
        Name -> slice of the observation (``observation_layout`` of the plant).
    control_period_s:
        The plant's control period (40 ms).
    max_speed_mps:
        Cartesian speed of a unit action.
    config:
        :class:`MpcConfig`.
    belt_velocity:
        Object velocity assumed when the observation carries none (world frame, m/s).
    """

    def __init__(
        self,
        layout: Mapping[str, slice],
        *,
        control_period_s: float,
        max_speed_mps: float,
        config: MpcConfig | None = None,
        belt_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        required = ("gripper_pos", "gripper_vel", "finger_width", "object_pos")
        missing = [k for k in required if k not in layout]
        if missing:
            raise ValueError(f"observation layout lacks {', '.join(missing)}")
        self.layout = dict(layout)
        self.config = config or MpcConfig()
        self.control_period_s = float(control_period_s)
        self.max_speed_mps = float(max_speed_mps)
        self.belt_velocity = np.asarray(belt_velocity, dtype=float).reshape(3)
        self.qp = MpcQp(self.config, dt=self.control_period_s, max_speed_mps=self.max_speed_mps)
        self._prepare()
        self.total_failures = 0
        self.recorder: list[NDArray[np.float64]] | None = None
        """When a list, every QP parameter vector solved is appended (benchmarks replay them)."""
        self.reset()

    @classmethod
    def from_env(cls, env: Any, config: MpcConfig | None = None) -> MpcController:
        """Build for a conveyor env (wrapped or not).

        Layout, control period, maximum speed, belt velocity and (unless ``config`` sets it)
        the workspace box come from the plant.
        """
        plant = env.unwrapped
        plant_cfg = getattr(plant, "config", None)
        config = config or MpcConfig()
        max_speed = _first_attr((plant_cfg, plant), ("max_gripper_speed_mps", "max_speed_mps"))
        period = _first_attr((plant, plant_cfg), ("control_period_s",))
        belt = getattr(plant, "belt_velocity", None)
        if belt is None and plant_cfg is not None and hasattr(plant_cfg, "belt_speed_mps"):
            belt = (0.0, float(plant_cfg.belt_speed_mps), 0.0)  # the belt runs along +y
        if config.workspace_low is None:
            margin = config.workspace_margin_m
            lo = np.asarray(_first_attr((plant,), ("workspace_low",)), dtype=float) + margin
            hi = np.asarray(_first_attr((plant,), ("workspace_high",)), dtype=float) - margin
            config = dataclasses.replace(
                config, workspace_low=tuple(lo.tolist()), workspace_high=tuple(hi.tolist())
            )
        return cls(
            plant.observation_layout,
            control_period_s=float(period),
            max_speed_mps=float(max_speed),
            config=config,
            belt_velocity=tuple(np.asarray(belt if belt is not None else (0, 0, 0), dtype=float)),
        )

    # -- Controller protocol -------------------------------------------------------------
    def reset(self, *, seed: int | None = None) -> None:
        self.qp.reset()
        self.phase = Phase.APPROACH
        self._closing = 0
        self._lift_origin: NDArray[np.float64] | None = None
        self._u_prev = np.zeros(3)
        self._grip = -1.0
        self.failures = 0
        self.last_solution: MpcSolution | None = None
        self._log = _EpisodeLog()

    def act(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        obs = np.asarray(observation, dtype=float)
        grip_pos = obs[self.layout["gripper_pos"]]
        grip_vel = obs[self.layout["gripper_vel"]]
        if self._width_index is None:
            width = float(np.mean(obs[self.layout["finger_width"]]))
        else:  # one entry: its mean is itself
            width = float(obs[self._width_index])
        obj = obs[self.layout["object_pos"]]
        if "object_vel" in self.layout:
            obj_vel = obs[self.layout["object_vel"]]
        else:
            obj_vel = self.belt_velocity
        theta = self._parameters(grip_pos, grip_vel, width, obj, obj_vel)
        if self.recorder is not None:
            self.recorder.append(theta.copy())
        solution = self.qp.solve(theta)
        self.last_solution = solution
        self._log.solve_times_s.append(solution.solve_time_s)
        self._log.cpu_times_s.append(solution.cpu_time_s)
        self._log.phases.append(int(self.phase))
        if solution.success:
            u = solution.commands[0]
        else:
            self.failures += 1
            self.total_failures += 1
            self._log.failures += 1
            u = self._safe_command(grip_pos)
        self._u_prev = u
        action = np.empty(4)
        np.minimum(np.maximum(u / self.max_speed_mps, -1.0), 1.0, out=action[:3])  # np.clip
        action[3] = self._grip
        return action

    # -- phase logic ----------------------------------------------------------------------
    def _prepare(self) -> None:
        """Constants and the parameter vector's views, so a step allocates little."""
        cfg, n, dt = self.config, self.qp.n, self.control_period_s
        self._kdt = np.arange(1, n + 1)[:, None] * dt  # k dt, k = 1..N
        self._offset = np.asarray(cfg.grasp_offset_m)
        self._hover = np.array([0.0, 0.0, cfg.hover_height_m])
        self._lift = np.array([0.0, 0.0, cfg.lift_height_m])
        self._ws_low = np.asarray(cfg.workspace_low)
        self._ws_high = np.asarray(cfg.workspace_high)
        width = self.layout["finger_width"]
        indices = range(width.stop)[width] if width.stop is not None else range(0)
        self._width_index: int | None = indices[0] if len(indices) == 1 else None
        self._theta = np.empty(self.qp.n_theta)  # the layout of MpcQp.pack

    def _parameters(
        self,
        p: NDArray[np.float64],
        v: NDArray[np.float64],
        width: float,
        obj: NDArray[np.float64],
        obj_vel: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """Advance the phase and return ``theta`` (:meth:`MpcQp.pack`), written in place."""
        cfg = self.config
        p0, p1, p2 = p.tolist()
        o0, o1, o2 = obj.tolist()
        g0, g1, g2 = self._offset.tolist()
        e0, e1, e2 = p0 - (o0 + g0), p1 - (o1 + g1), p2 - (o2 + g2)  # p - (obj + offset)
        lateral = float(np.hypot(e0, e1))
        if self.phase == Phase.APPROACH and lateral <= cfg.align_tolerance_m:
            self.phase = Phase.DESCEND
        elif self.phase == Phase.DESCEND:
            if lateral > cfg.abort_tolerance_m:
                self.phase = Phase.APPROACH
            elif lateral <= cfg.grasp_tolerance_m and abs(e2) <= cfg.grasp_height_tolerance_m:
                self.phase = Phase.GRASP
                self._closing = 0
        elif self.phase == Phase.GRASP:
            self._closing += 1
            if self._closing > cfg.close_steps:
                if width < cfg.min_grip_width_m:
                    self.phase = Phase.APPROACH  # closed on nothing: open and retry
                else:
                    self.phase = Phase.LIFT
                    self._lift_origin = p.copy()
        elif self.phase == Phase.LIFT and width < cfg.min_grip_width_m:
            self.phase = Phase.APPROACH
            self._lift_origin = None
        self._grip = 1.0 if self.phase in (Phase.GRASP, Phase.LIFT) else -1.0
        origin = self._lift_origin if self._lift_origin is not None else p
        fill_parameters(
            self._theta, p, v, self._u_prev, obj, self._offset, obj_vel, self._kdt,
            int(self.phase), self._hover, cfg.clearance_m, cfg.funnel_apex_depth_m, self._lift,
            origin, self._ws_low, self._ws_high, OFF,
        )  # fmt: skip
        return self._theta

    def _safe_command(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        lo = np.asarray(self.config.workspace_low)
        hi = np.asarray(self.config.workspace_high)
        back = (np.clip(p, lo, hi) - p) / self.control_period_s
        return np.clip(back, -0.25 * self.qp.v_max, 0.25 * self.qp.v_max)

    # -- metrics --------------------------------------------------------------------------
    def episode_metrics(self) -> dict[str, float]:
        """Per-episode solver statistics: solves, failures, solver-call times in ms.

        ``mpc_solve_ms_*`` are wall-clock times (what the control loop waits, including any
        preemption by other processes); ``mpc_solve_cpu_ms_*`` the thread's CPU time.
        """
        times = np.asarray(self._log.solve_times_s) * 1e3
        cpu = np.asarray(self._log.cpu_times_s) * 1e3
        if times.size == 0:
            times = cpu = np.array([np.nan])
        return {
            "mpc_solves": float(len(self._log.solve_times_s)),
            "mpc_failures": float(self._log.failures),
            "mpc_solve_ms_median": float(np.median(times)),
            "mpc_solve_ms_p99": float(np.percentile(times, 99)),
            "mpc_solve_ms_max": float(np.max(times)),
            "mpc_solve_cpu_ms_median": float(np.median(cpu)),
            "mpc_solve_cpu_ms_p99": float(np.percentile(cpu, 99)),
        }

    @property
    def solve_times_s(self) -> list[float]:
        """Wall times of this episode's solves."""
        return list(self._log.solve_times_s)

    def __getstate__(self) -> dict[str, Any]:
        return {
            "layout": self.layout,
            "control_period_s": self.control_period_s,
            "max_speed_mps": self.max_speed_mps,
            "config": self.config,
            "belt_velocity": tuple(self.belt_velocity),
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        layout = state.pop("layout")
        self.__init__(layout, **state)  # type: ignore[misc]


class _NullText(io.TextIOBase):
    def write(self, text: str) -> int:
        return len(text)


_NULL_TEXT = _NullText()


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silence ``sys.stdout`` inside the block.

    qpOASES prints its licence banner for every instance and some error traces regardless of
    its ``printLevel``, through CasADi's output stream, which writes to Python's
    ``sys.stdout``; ``--json`` output must stay clean.
    """
    saved = sys.stdout
    sys.stdout = _NULL_TEXT
    try:
        yield
    finally:
        sys.stdout = saved


def _first_attr(objects: tuple[Any, ...], names: tuple[str, ...]) -> Any:
    for obj in objects:
        if obj is None:
            continue
        for name in names:
            if hasattr(obj, name):
                return getattr(obj, name)
    raise ValueError(f"the plant exposes none of {', '.join(names)}")


def config_fields() -> list[str]:
    """Names of :class:`MpcConfig`'s fields (for CLIs and docs)."""
    return [f.name for f in fields(MpcConfig)]
