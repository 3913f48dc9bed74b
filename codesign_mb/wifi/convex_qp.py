"""The convex allocator's per-tick QP relaxation [qp]: an OSQP workspace and a cvxpy model.

[qp] (per tick; variables scaled to fractions of the full band's ``S`` data subcarriers;
only the admitted stations are variables)::

    max  sum_i a_i t_i + b_i z_i - rho/2 (|x|^2 + |t|^2 + |z|^2)
    s.t. t_i + z_i <= sum_k (N_SD,k / S) x_ik      served subcarriers of station i
         sum_k x_ik <= 1                            one RU per station
         sum_i x_ik <= count_k                      RUs of size k in the channel
         sum_ik units_k x_ik <= n_units             26-tone units of the channel
         0 <= t_i <= T_i,  0 <= z_i <= Z_i,  0 <= x_ik <= active_i

``t_i`` is the service frame ``i`` must get now (value ``a_i = 1``), ``z_i`` service ahead of
need up to the station's backlog ``Z_i`` (value ``b_i = beta gamma^rank_i``, ``rank`` the
frame's place in deadline order among the admitted: earliest deadline first; ``beta`` =
:attr:`~codesign_mb.wifi.convex.ConvexAllocatorConfig.surplus_weight`, ``gamma`` =
:attr:`~codesign_mb.wifi.convex.ConvexAllocatorConfig.surplus_decay`).

Both models solve the same problem on the variables ``v = [x (m*k, row-major), t (m), z (m)]``
and check the solver's status after every solve: :meth:`OsqpQp.solve` and
:meth:`CvxpyQp.solve` return ``None`` when the solution cannot be used (a failed status, or
values that are not finite) and keep the reason in ``last_status``; the caller falls back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["OSQP_SETTINGS", "CvxpyQp", "OsqpQp", "QpShape", "qp_matrices"]

OSQP_SETTINGS: dict[str, Any] = {
    "verbose": False,
    "polishing": False,
    "warm_starting": True,
    "adaptive_rho": True,
    "adaptive_rho_interval": 25,
    "check_termination": 5,
    "rho": 0.1,
}
"""OSQP settings of the hot path (tolerances and the iteration cap come from the config)."""

_OSQP_USABLE = ("OSQP_SOLVED", "OSQP_SOLVED_INACCURATE", "OSQP_MAX_ITER_REACHED")
"""OSQP statuses whose iterate the rounding uses: the relaxation only picks RU sizes, so an
inaccurate solution or the iterate at the (deliberately low) iteration cap still does."""

_CVXPY_USABLE = ("optimal", "optimal_inaccurate", "user_limit")
"""cvxpy statuses with a usable solution (``user_limit``: the solver's iteration cap)."""


@dataclass(frozen=True)
class QpShape:
    """The channel's data in [qp], per RU size ``k`` (arrays of shape ``(k,)``).

    Attributes
    ----------
    frac_sd:
        ``N_SD,k / S``: data subcarriers of an RU of size ``k`` as a fraction of the full band.
    counts:
        ``count_k``: RUs of size ``k`` in the channel.
    units:
        ``units_k``: 26-tone units an RU of size ``k`` covers.
    n_units:
        26-tone units of the channel.
    regularization:
        ``rho``.
    """

    frac_sd: NDArray[np.float64]
    counts: NDArray[np.float64]
    units: NDArray[np.float64]
    n_units: int
    regularization: float

    @property
    def k(self) -> int:
        return int(self.frac_sd.size)


def qp_matrices(m: int, shape: QpShape) -> tuple[sp.csc_matrix, sp.csc_matrix, int]:
    """[qp] for ``m`` stations as OSQP's ``A`` (constraints, then variable bounds), ``P``.

    Returns ``A``, ``P`` (without ``rho``) and the number of constraint rows before the bounds.
    """
    k = shape.k
    nv = m * k + 2 * m
    ix = np.arange(m * k).reshape(m, k)
    it = m * k + np.arange(m)
    iz = m * k + m + np.arange(m)
    r_serve = np.arange(m)  # t_i + z_i - sum_k sd_k x_ik <= 0
    r_one = m + np.arange(m)  # sum_k x_ik <= 1
    r_count = 2 * m + np.arange(k)  # sum_i x_ik <= count_k
    r_units = 2 * m + k  # sum units x <= n_units
    rows = np.concatenate(
        [r_serve, r_serve, np.repeat(r_serve, k), np.repeat(r_one, k), np.tile(r_count, m),
         np.full(m * k, r_units)]
    )  # fmt: skip
    cols = np.concatenate([it, iz, ix.ravel(), ix.ravel(), ix.ravel(), ix.ravel()])
    vals = np.concatenate(
        [np.ones(2 * m), np.tile(-shape.frac_sd, m), np.ones(2 * m * k), np.tile(shape.units, m)]
    )
    n_rows = 2 * m + k + 1
    A = sp.vstack(
        [sp.csc_matrix((vals, (rows, cols)), shape=(n_rows, nv)), sp.identity(nv, format="csc")],
        format="csc",
    )
    return A, sp.identity(nv, format="csc"), n_rows


class OsqpQp:
    """An OSQP workspace of [qp] for ``m`` station slots (matrices fixed, vectors per tick).

    The solver is driven through its extension object when the installed ``osqp`` exposes it
    (``OSQP._solver``): the Python wrapper's ``update``/``solve`` add ~50 us of bookkeeping
    per tick (derivative caches, an info namespace) that the hot path does not need.

    Parameters
    ----------
    m:
        Station slots.
    shape:
        The channel's data.
    eps, max_iter:
        OSQP absolute and relative tolerance, iteration cap.
    """

    def __init__(self, m: int, shape: QpShape, *, eps: float, max_iter: int) -> None:
        import osqp

        k = shape.k
        self.m, self.k = m, k
        A, P, n_rows = qp_matrices(m, shape)
        nv = m * k + 2 * m
        self.nv, self.n_rows = nv, n_rows
        self.q = np.zeros(nv)
        self.u = np.concatenate(
            [np.zeros(m), np.ones(m), shape.counts, [float(shape.n_units)], np.zeros(nv)]
        )
        lower = np.concatenate([np.full(n_rows, -np.inf), np.zeros(nv)])
        solver = osqp.OSQP()
        settings = {**OSQP_SETTINGS, "eps_abs": eps, "eps_rel": eps, "max_iter": max_iter}
        solver.setup(P * shape.regularization, self.q, A, lower, self.u, **settings)
        self.solver = solver
        raw = getattr(solver, "_solver", None)
        self._raw = raw if raw is not None and hasattr(raw, "update_data_vec") else None
        self._usable = frozenset(int(osqp.SolverStatus[name]) for name in _OSQP_USABLE)
        self.last_status = "unsolved"
        # views of the per-tick parts of q and u
        self._qa = self.q[m * k : m * k + m]
        self._qb = self.q[m * k + m :]
        self._ux = self.u[n_rows : n_rows + m * k].reshape(m, k)
        self._ut = self.u[n_rows + m * k : n_rows + m * k + m]
        self._uz = self.u[n_rows + m * k + m :]
        self._j = 0  # slots holding a station in q and u

    def _run(self) -> tuple[NDArray[np.float64], int, str]:
        """One OSQP solve on the current ``q, u``: the iterate, status value and status text."""
        if self._raw is None:  # pragma: no cover - osqp builds without the extension object
            self.solver.update(q=self.q, u=self.u)
            result = self.solver.solve(raise_error=False)
            info = result.info
            return np.asarray(result.x, dtype=float), int(info.status_val), str(info.status)
        self._raw.update_data_vec(q=self.q, l=None, u=self.u)
        self._raw.solve()
        info = self._raw.info
        return np.asarray(self._raw.solution.x, dtype=float), int(info.status_val), str(info.status)

    def solve(
        self,
        a: NDArray[np.float64],
        b: NDArray[np.float64],
        t_max: NDArray[np.float64],
        z_max: NDArray[np.float64],
    ) -> NDArray[np.float64] | None:
        """Solution ``[x (m*k), t, z]`` (the first ``len(a)`` slots are the stations), or
        ``None`` when OSQP failed (``last_status`` says how)."""
        j = a.size
        self._qa[:j] = -a
        self._qb[:j] = -b
        self._ux[:j] = 1.0
        self._ut[:j] = t_max
        self._uz[:j] = z_max
        if j < self._j:  # slots used last time and not now: no station, all zero
            for part in (self._qa, self._qb, self._ux, self._ut, self._uz):
                part[j : self._j] = 0.0
        self._j = j
        x, status_val, status = self._run()
        if status_val not in self._usable:
            self.last_status = f"osqp status {status!r}"
        elif x.shape != (self.nv,) or not math.isfinite(float(x.sum())):
            self.last_status = f"osqp returned a non-finite solution (status {status!r})"
        else:
            self.last_status = status
            return x
        self._restart()
        return None

    def _restart(self) -> None:
        """Forget the warm start and the adapted ``rho`` after a failed solve: a non-finite
        iterate would otherwise seed every later solve of this workspace."""
        x0, y0 = np.zeros(self.nv), np.zeros(self.n_rows + self.nv)
        if self._raw is None:  # pragma: no cover - osqp builds without the extension object
            self.solver.warm_start(x=x0, y=y0)
            self.solver.update_settings(rho=OSQP_SETTINGS["rho"])
            return
        self._raw.warm_start(x0, y0)
        self._raw.update_rho(OSQP_SETTINGS["rho"])


class CvxpyQp:
    """[qp] for ``n`` stations as a cvxpy model, built once with ``Parameter``s (DPP).

    The per-tick data ``a, b, T, Z, active`` are parameters; ``active_i = 0`` pins station
    ``i``'s variables to 0 (not admitted, or no station in that slot).
    """

    def __init__(self, n: int, shape: QpShape) -> None:
        import cvxpy as cp

        k = shape.k
        self.n, self.k = n, k
        x = cp.Variable((n, k), name="x")
        t = cp.Variable(n, name="t")
        z = cp.Variable(n, name="z")
        a = cp.Parameter(n, nonneg=True, name="a")
        b = cp.Parameter(n, nonneg=True, name="b")
        t_max = cp.Parameter(n, nonneg=True, name="t_max")
        z_max = cp.Parameter(n, nonneg=True, name="z_max")
        active = cp.Parameter(n, nonneg=True, name="active")
        rho = shape.regularization
        objective = cp.Maximize(
            a @ t + b @ z - rho / 2 * (cp.sum_squares(x) + cp.sum_squares(t) + cp.sum_squares(z))
        )
        constraints = [
            t + z <= x @ shape.frac_sd,
            cp.sum(x, axis=1) <= 1,
            cp.sum(x, axis=0) <= shape.counts,
            cp.sum(x @ shape.units) <= shape.n_units,
            x >= 0,
            x <= cp.reshape(active, (n, 1), order="C") @ np.ones((1, k)),
            t >= 0,
            t <= t_max,
            z >= 0,
            z <= z_max,
        ]
        self.problem = cp.Problem(objective, constraints)
        if not self.problem.is_dpp():
            raise AssertionError("[qp] must be DPP")
        self._warm_start = True  # off for the solve after a failure
        self._variables = (x, t, z)
        self._parameters = (a, b, t_max, z_max, active)
        self.last_status = "unsolved"

    def solve(
        self, values: tuple[NDArray[np.float64], ...], *, solver: str, eps: float
    ) -> NDArray[np.float64] | None:
        """``v = [x, t, z]`` for the parameter ``values`` ``(a, b, T, Z, active)``, or ``None``
        when the solver failed (``last_status`` says how)."""
        for param, value in zip(self._parameters, values, strict=True):
            param.value = value
        # OSQP as on the hot path (no polishing: it also prints to stdout, past verbose=False)
        kwargs = {"eps_abs": eps, "eps_rel": eps, "polish": False} if solver == "OSQP" else {}
        v = self._solve(solver, kwargs)
        if v is None:
            self._warm_start = False
            return None
        self.last_status = str(self.problem.status)
        self._warm_start = True
        return v

    def _solve(self, solver: str, kwargs: dict[str, float]) -> NDArray[np.float64] | None:
        """One solve: ``v``, or ``None`` with the reason in ``last_status``."""
        import cvxpy as cp

        try:
            self.problem.solve(solver=solver, warm_start=self._warm_start, **kwargs)
        except cp.error.SolverError as exc:
            self.last_status = f"cvxpy {solver} raised SolverError: {exc}"
            return None
        status = str(self.problem.status)
        if status not in _CVXPY_USABLE:
            self.last_status = f"cvxpy {solver} status {status!r}"
            return None
        parts = [var.value for var in self._variables]
        if any(part is None for part in parts):
            self.last_status = f"cvxpy {solver} returned no solution ({status!r})"
            return None
        v = np.concatenate([np.asarray(part, dtype=float).ravel() for part in parts])
        if v.shape != (self.n * self.k + 2 * self.n,) or not np.all(np.isfinite(v)):
            self.last_status = f"cvxpy {solver} returned a non-finite solution ({status!r})"
            return None
        return v
