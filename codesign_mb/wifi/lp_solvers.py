"""Box-bounded LPs ``max c'x  s.t.  A x <= b, 0 <= x <= 1`` handed to a solver as sparse arrays.

The offline allocation LP ([lp], :mod:`codesign_mb.wifi.offline`) is assembled as numpy/scipy
arrays and passed to the solver's own API, with no modelling layer on the hot path:

* ``"highs"``: HiGHS through ``highspy`` (dual simplex; an exact vertex, row duals);
* ``"clarabel"``: Clarabel's interior point with a direct sparse factorisation (optimum to its
  tolerances, about 1e-9 relative here; duals). On the allocation LPs of dense cells it is
  much faster than the simplex: their DL-exchange rows make the simplex wander over a
  highly degenerate vertex set (``solvers/README.md``, "What made it slow");
* ``"osqp"``: first order, approximate on LPs (kept for comparison);
* ``"auto"``: HiGHS up to :data:`AUTO_SIMPLEX_MAX_VARIABLES` variables, Clarabel above.

Bounds a row set already implies (``bounded``) are not repeated as rows for the interior-point
solvers, which take bounds as constraints.
"""

from __future__ import annotations

import ctypes
import math
import os
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["AUTO_SIMPLEX_MAX_VARIABLES", "LP_SOLVERS", "LpSolution", "solve_box_lp"]

LP_SOLVERS = ("auto", "highs", "clarabel", "osqp")

AUTO_SIMPLEX_MAX_VARIABLES = 20_000
"""``"auto"`` takes the simplex up to this many variables, the interior point above (on a
48-robot cell, 0.8 s against 1.0 s at 7,600 variables, 50 s against 4.4 s at 95,000)."""


@dataclass(frozen=True)
class LpSolution:
    """What a solver returned: optimum, status (``"optimal"`` or the solver's words), the
    primal point and the row duals (``>= 0``: the optimum's gain per unit of ``b``), or
    ``None`` where the solver failed."""

    value: float
    status: str
    solver: str
    x: NDArray[np.float64] | None = None
    row_duals: NDArray[np.float64] | None = None


def solve_box_lp(
    c: NDArray[np.float64],
    A: sp.spmatrix,
    b: NDArray[np.float64],
    *,
    solver: str = "auto",
    bounded: NDArray[np.int64] | None = None,
) -> LpSolution:
    """Solve ``max c'x s.t. A x <= b, 0 <= x <= 1`` with ``solver`` (:data:`LP_SOLVERS`).

    ``bounded``: the variables whose bounds are not implied by the rows (``None``: all).
    """
    if not isinstance(solver, str) or solver.lower() not in LP_SOLVERS:
        raise ValueError(f"solver must be one of {LP_SOLVERS}, got {solver!r}")
    solver = solver.lower()
    nv = int(c.size)
    if solver == "auto":
        solver = "highs" if nv <= AUTO_SIMPLEX_MAX_VARIABLES else "clarabel"
    if nv == 0:
        return LpSolution(0.0, "optimal", solver, np.zeros(0), np.zeros(A.shape[0]))
    A = sp.csc_matrix(A)
    if solver == "highs":
        return _highs(c, A, b)
    if solver == "clarabel":
        return _clarabel(c, A, b, bounded)
    return _osqp(c, A, b)


def _objective(c: NDArray, x: NDArray) -> float:
    """``c'x`` exactly rounded (``math.fsum``): the same bits in every process, whatever the
    BLAS threads of its dot product (a Ray worker runs single-threaded, a plain process not)."""
    return math.fsum((c * x).tolist())


_BANNER_SHOWN = False


def _new_highs() -> Any:
    """A silent ``highspy.Highs``. The first one of a process prints HiGHS's banner from C to
    file descriptor 1, which would break a command's JSON output: it goes to ``/dev/null``."""
    global _BANNER_SHOWN
    import highspy

    if _BANNER_SHOWN:
        h = highspy.Highs()
    else:
        sys.stdout.flush()
        saved, devnull = os.dup(1), os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 1)
            h = highspy.Highs()
            ctypes.CDLL(None).fflush(None)
        finally:
            os.dup2(saved, 1)
            os.close(saved)
            os.close(devnull)
        _BANNER_SHOWN = True
    h.setOptionValue("output_flag", False)
    return h


def _highs(c: NDArray, A: sp.csc_matrix, b: NDArray) -> LpSolution:
    import highspy

    lp = highspy.HighsLp()
    lp.num_col_, lp.num_row_ = A.shape[1], A.shape[0]
    lp.col_cost_ = -c
    lp.col_lower_, lp.col_upper_ = np.zeros(A.shape[1]), np.ones(A.shape[1])
    lp.row_lower_, lp.row_upper_ = np.full(A.shape[0], -highspy.kHighsInf), b
    lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
    lp.a_matrix_.start_, lp.a_matrix_.index_ = A.indptr, A.indices
    lp.a_matrix_.value_ = A.data
    h = _new_highs()
    h.passModel(lp)
    h.run()
    status = h.getModelStatus()
    if status != highspy.HighsModelStatus.kOptimal:
        return LpSolution(float("nan"), f"highs: {h.modelStatusToString(status)}", "highs")
    sol = h.getSolution()
    x = np.asarray(sol.col_value)
    duals = -np.asarray(sol.row_dual)  # of the minimisation of -c'x: <= rows have duals <= 0
    return LpSolution(_objective(c, x), "optimal", "highs", x, duals)


def _clarabel(c: NDArray, A: sp.csc_matrix, b: NDArray, bounded: NDArray | None) -> LpSolution:
    import clarabel

    nv, m = A.shape[1], A.shape[0]
    idx = np.arange(nv) if bounded is None else np.unique(bounded)
    eye = sp.csc_matrix((np.ones(idx.size), (np.arange(idx.size), idx)), shape=(idx.size, nv))
    K = sp.vstack([A, eye, -eye], format="csc")
    h = np.concatenate([b, np.ones(idx.size), np.zeros(idx.size)])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    s = clarabel.DefaultSolver(
        sp.csc_matrix((nv, nv)), -c, K, h, [clarabel.NonnegativeConeT(K.shape[0])], settings
    )
    sol = s.solve()
    status = str(sol.status)
    if "Solved" not in status:
        return LpSolution(float("nan"), f"clarabel: {status}", "clarabel")
    x = np.clip(np.asarray(sol.x), 0.0, 1.0)
    return LpSolution(_objective(c, x), "optimal", "clarabel", x, np.asarray(sol.z)[:m])


def _osqp(c: NDArray, A: sp.csc_matrix, b: NDArray) -> LpSolution:
    import osqp

    nv = A.shape[1]
    K = sp.vstack([A, sp.identity(nv)], format="csc")
    lower = np.concatenate([np.full(A.shape[0], -np.inf), np.zeros(nv)])
    upper = np.concatenate([b, np.ones(nv)])
    m = osqp.OSQP()
    m.setup(
        sp.csc_matrix((nv, nv)),
        -c,
        K,
        lower,
        upper,
        verbose=False,
        eps_abs=1e-7,
        eps_rel=1e-7,
        max_iter=200_000,
        polishing=True,
    )
    res = m.solve(raise_error=False)
    status = str(res.info.status)
    if res.x is None or not np.all(np.isfinite(res.x)):
        return LpSolution(float("nan"), f"osqp: {status}", "osqp")
    return LpSolution(_objective(c, res.x), status, "osqp", np.asarray(res.x), None)
