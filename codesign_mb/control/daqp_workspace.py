"""A DAQP QP whose Hessian and constraint matrix stay fixed: set up once, hot-started after.

``casadi.conic`` hands every solver the whole QP on every call, so a solver redoes its matrix
setup each step (qpOASES refactorises ``H`` and the working set, DAQP recomputes
``R = chol(H)`` and ``M = A R^-1``) although, in the MPC, only the linear term and the bounds
change. DAQP's own ``daqp.Model`` keeps that setup: :meth:`DaqpWorkspace.solve` passes the new
``f`` and bounds to ``Model.update`` and the solve starts from the previous solve's working
set (a hot start: most steps of a closed loop take one or two iterations).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["DAQP_STATUS", "DaqpWorkspace"]

DAQP_STATUS = {
    1: "optimal",
    2: "soft optimal",
    -1: "infeasible",
    -2: "cycling",
    -3: "unbounded",
    -4: "iteration limit",
    -5: "nonconvex",
    -6: "overdetermined initial active set",
}
"""DAQP's exit flags (positive: solved)."""


class DaqpWorkspace:
    """``min 1/2 x'Hx + f'x  s.t.  lower <= (x, A x) <= upper``, ``H`` fixed, ``A`` mostly.

    ``A`` may be rewritten in place (:attr:`constraints`; then :meth:`solve` with
    ``matrix_changed``).

    Write :attr:`f`, :attr:`lower` and :attr:`upper` in place (the views :attr:`lower_x`,
    :attr:`upper_x` for the simple bounds on ``x``, :attr:`lower_a`, :attr:`upper_a` for
    ``A x``), then call :meth:`solve`. The first solve after construction or :meth:`reset`
    sets the workspace up (cold start); later ones update it and hot-start.

    Parameters
    ----------
    hessian:
        ``H``, shape ``(n, n)``, positive definite.
    constraints:
        ``A``, shape ``(m, n)``.
    """

    def __init__(self, hessian: ArrayLike, constraints: ArrayLike) -> None:
        import daqp  # optional at import time: only this backend needs it

        self._daqp = daqp
        self.hessian = np.ascontiguousarray(hessian, dtype=float)
        self.constraints = np.ascontiguousarray(constraints, dtype=float)
        n = self.hessian.shape[0]
        m = self.constraints.shape[0]
        if self.hessian.shape != (n, n) or self.constraints.shape[1] != n:
            raise ValueError(
                f"hessian must be (n, n) and constraints (m, n), got {self.hessian.shape} "
                f"and {self.constraints.shape}"
            )
        self.f = np.zeros(n)
        self.lower = np.full(n + m, -np.inf)
        self.upper = np.full(n + m, np.inf)
        self.lower_x, self.lower_a = self.lower[:n], self.lower[n:]
        self.upper_x, self.upper_a = self.upper[:n], self.upper[n:]
        self._sense = np.zeros(n + m, dtype=np.int32)
        self._model: Any = None

    def reset(self) -> None:
        """Drop the working set: the next :meth:`solve` starts cold."""
        self._model = None

    def solve(self, *, matrix_changed: bool = False) -> tuple[NDArray[np.float64], int]:
        """Solve on the current data; ``(x, exit flag)``, the flag > 0 on success.

        ``matrix_changed``: :attr:`constraints` was written since the last solve (DAQP then
        redoes ``M = A R^-1``, keeping ``R = chol(H)`` and the working set).
        """
        model = self._model
        if model is None:
            model = self._daqp.Model()
            flag, _ = model.setup(
                self.hessian, self.f, self.constraints, self.upper, self.lower, self._sense
            )
            if flag < 0:
                return np.full(self.f.shape, np.nan), int(flag)
            self._model = model
        elif matrix_changed:
            flag = model.update(f=self.f, A=self.constraints, bupper=self.upper, blower=self.lower)
            if flag < 0:
                self._model = None
                return np.full(self.f.shape, np.nan), int(flag)
        else:
            model.update(f=self.f, bupper=self.upper, blower=self.lower)
        x, _, flag, _ = model.solve()
        return x, int(flag)
