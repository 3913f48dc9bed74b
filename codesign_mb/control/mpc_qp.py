"""The conveyor MPC's QP solved each step (:class:`MpcQp`): the solver back-ends, warm starts.

The problem itself (model, construction, data at ``theta``) is
:class:`~codesign_mb.control.mpc_qp_problem.MpcQpProblem`, which :class:`MpcQp` extends.

Why an active-set QP solver, and why DAQP on its own workspace
--------------------------------------------------------------
The model is linear and the constraints are polyhedral, so the problem is a small, dense,
strictly convex QP (3N + 1 variables, 15N constraints and 14 per joint-limited step: 46 and
295 at N = 15); an NLP solver (IPOPT, FATROP) would only add overhead and iterations.
Active-set methods (qpOASES, DAQP) suit parametric MPC: started from the previous step's
active set, most steps take zero to a few iterations, and their solutions are exact vertices
(bounds respected to machine precision, where an ADMM solver such as OSQP stops at a
tolerance and needs polishing). Through ``casadi.conic`` every solver is handed the whole QP
each step and redoes its matrix setup, although ``H`` never changes and ``A`` only in its
joint rows. The default, ``"daqp_native"``, calls DAQP directly on a workspace set up once
per episode
(:class:`~codesign_mb.control.daqp_workspace.DaqpWorkspace`): a step updates the linear term
and the bounds (and ``A``, after a relinearisation) and hot-starts from the last working set.
On the recorded closed-loop problems it gives qpOASES' solutions to about 1e-12 in less than
half its time (whole :meth:`MpcQp.solve`, median CPU: about 0.14 ms against 0.33 ms with the
joint rows; 0.09 ms on the two thirds of the steps that keep ``A``, 0.32 ms on those that
rewrite it; ``codesign bench mpc``). The
CasADi plugins stay selectable through :attr:`MpcConfig.solver`: qpOASES (hot start), DAQP
and OSQP (warm start from the shifted previous solution).
"""

from __future__ import annotations

import contextlib
import io
import sys
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.control.conic_buffer import ConicBuffer
from codesign_mb.control.daqp_workspace import DAQP_STATUS, DaqpWorkspace
from codesign_mb.control.mpc_config import MpcConfig
from codesign_mb.control.mpc_kernels import stopping_bounds, worst_violation
from codesign_mb.control.mpc_model import JointLimits
from codesign_mb.control.mpc_qp_problem import Joints, MpcQpProblem

__all__ = ["MpcQp", "MpcSolution"]

NATIVE_DAQP = "daqp_native"
"""The solver name of DAQP called directly (:class:`DaqpWorkspace`), not through CasADi."""
_SUCCESS_STATUS = {"qpoases": "Successful return."}
"""What a solver's ``return_status`` says on success, when it is known without asking."""

FEASIBILITY_TOL = 1e-5
"""Largest violation of a hard bound a solution may have (a solver's "success" is not trusted)."""


@dataclass
class MpcSolution:
    """One solve: the command sequence ``(N, 3)``, success, the solver's wall and CPU time."""

    commands: NDArray[np.float64]
    success: bool
    status: str
    solve_time_s: float
    slack: float = 0.0
    cpu_time_s: float = 0.0


class MpcQp(MpcQpProblem):
    """The MPC's parametric QP (:class:`MpcQpProblem`, same parameters) and its solver.

    :meth:`solve` evaluates the QP's affine maps
    (numpy products, the rest compiled in :mod:`~codesign_mb.control.mpc_kernels`)
    straight into the solver's arrays: those of the kept DAQP workspace
    (:class:`~codesign_mb.control.daqp_workspace.DaqpWorkspace`, ``"daqp_native"``: ``H`` and
    ``A`` set up once per episode, hot start from the last working set), or those bound to a
    ``casadi.conic`` solver's buffer (:class:`~codesign_mb.control.conic_buffer.ConicBuffer`;
    warm start from qpOASES' hot start, or the shifted previous solution for OSQP/DAQP);
    :meth:`qp_data` is the same data as a dict.
    """

    def __init__(
        self,
        config: MpcConfig,
        *,
        dt: float,
        max_speed_mps: float,
        joint_limits: JointLimits | None = None,
    ) -> None:
        super().__init__(config, dt=dt, max_speed_mps=max_speed_mps, joint_limits=joint_limits)
        self._solver: Any = None
        self._workspace: DaqpWorkspace | None = None
        # Work arrays of the hot path (solve), allocated once.
        self._offset = np.empty(self.n_con)
        self._low = self.con_low.copy()
        self._high = self.con_high.copy()
        self._ax = np.empty(self.n_con)
        self._matrix_changed = self._joints_on = False
        self._pinv: NDArray[np.float64] | None = None
        self.reset()

    # -- solvers ------------------------------------------------------------------------
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
        if self.joints is not None:  # the next solve with joints writes their rows afresh
            self.A[self._joint_rows] = 0.0
            self._joints_on, self._pinv = False, None
        if self.config.solver == NATIVE_DAQP:  # H and A set up at the first solve
            if self._workspace is None:
                self._workspace = DaqpWorkspace(self.H, self.A)
                self._workspace.lower_x[:] = self.var_low
                self._workspace.upper_x[:] = self.var_high
            self._workspace.reset()
            return
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
    def solve(self, theta: NDArray[np.float64], joints: Joints | None = None) -> MpcSolution:
        """Solve the QP at ``theta`` (warm-started from the previous solve).

        The data of :meth:`qp_data` are written into the arrays bound to the solver's buffer
        (:class:`~codesign_mb.control.conic_buffer.ConicBuffer`), so a step converts nothing.
        ``joints``: the configuration's joint-limit rows (:meth:`qp_data`).
        """
        if self._workspace is not None:
            return self._solve_native(theta, joints)
        conic = self._conic
        inputs = conic.inputs
        self._fill(
            np.asarray(theta, dtype=float), inputs["g"], inputs["lba"], inputs["uba"], joints
        )
        if self._matrix_changed:
            inputs["a"][:] = self.A.ravel(order="F")  # the dense A's nonzeros, column-major
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

    def _solve_native(self, theta: NDArray[np.float64], joints: Joints | None) -> MpcSolution:
        """:meth:`solve` by DAQP on its kept workspace (:class:`DaqpWorkspace`)."""
        workspace = self._workspace
        assert workspace is not None
        lower, upper = workspace.lower_a, workspace.upper_a
        self._fill(np.asarray(theta, dtype=float), workspace.f, lower, upper, joints)
        start_cpu = time.thread_time()
        start = time.perf_counter()
        x, flag = workspace.solve(matrix_changed=self._matrix_changed)
        elapsed = time.perf_counter() - start
        cpu = time.thread_time() - start_cpu
        n = self.n
        ax = np.matmul(self.A, x, out=self._ax)
        worst = worst_violation(x, ax, self.var_low, self.var_high, lower, upper)
        if not (flag > 0 and worst <= FEASIBILITY_TOL):
            workspace.reset()  # never hot-start from a failed solve
            status = DAQP_STATUS.get(flag, f"exit flag {flag}") if flag <= 0 else "infeasible x"
            return MpcSolution(np.zeros((n, 3)), False, status, elapsed, 0.0, cpu)
        return MpcSolution(x[: 3 * n].reshape(n, 3), True, "optimal", elapsed, float(x[3 * n]), cpu)

    def _fill(
        self,
        theta: NDArray[np.float64],
        g: NDArray[np.float64],
        lba: NDArray[np.float64],
        uba: NDArray[np.float64],
        joints: Joints | None = None,
    ) -> None:
        """Write :meth:`qp_data`'s ``g``, ``lba``, ``uba`` (and ``A``'s joint rows, in
        :attr:`A`; :attr:`_matrix_changed` says whether they changed) into the given arrays."""
        self._fill_common(theta, g, lba, uba)
        self._matrix_changed = False
        if self.joints is None:
            return
        rows = self._joint_rows
        if joints is not None:
            # The same J_v^+ object as last step (the caller kept its linearisation): the
            # rows are unchanged, so the solver keeps its matrix setup.
            same = self._joints_on and joints[1] is self._pinv
            matrix = None if same else self.A[rows]
            self._joint_data(theta, joints, matrix, lba[rows], uba[rows])
            self._matrix_changed, self._joints_on, self._pinv = not same, True, joints[1]
        elif self._joints_on:  # back to zero rows (their bounds are already +-OFF)
            self.A[rows] = 0.0
            self._matrix_changed, self._joints_on, self._pinv = True, False, None

    def _fill_common(
        self,
        theta: NDArray[np.float64],
        g: NDArray[np.float64],
        lba: NDArray[np.float64],
        uba: NDArray[np.float64],
    ) -> None:
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
        self, x: NDArray[np.float64], data: Mapping[str, NDArray], tol: float = FEASIBILITY_TOL
    ) -> bool:
        """Whether ``x`` satisfies the hard bounds (a solver's "success" is not taken on trust)."""
        ax = np.matmul(self.A, x, out=self._ax)
        worst = worst_violation(x, ax, data["lbx"], data["ubx"], data["lba"], data["uba"])
        return bool(worst <= tol)


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
