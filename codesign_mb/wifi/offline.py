"""The whole-horizon allocation LP: an upper bound on the frames any scheduler delivers in time.

For a recorded :class:`~codesign_mb.wifi.sim.Trace` (every admitted frame, every station's
MCS at every tick) we relax the RU layout of each tick to its total data subcarriers and
track, per frame ``f`` and tick ``k``, the cumulative fractions ``U_fk`` of its camera frame
and ``V_fk`` of its state frame that have been sent ([lp])::

    max  sum_f V_f,last
    s.t. U_f,k-1 <= U_f,k,   V_f,k-1 <= V_f,k,   0 <= U, V <= 1
         V_f,k <= U_f,k-1-p                                  state frame after camera frame
         V_f,k - V_f,k-1 <= y_k,   0 <= y_k <= 1             a DL exchange in tick k
         sum_f B_f^UL (U_fk - U_f,k-1) / b_ik <= S (N_UL - (N_UL - N_UL') y_k)
                                                             UL subcarrier-symbols of tick k
         sum_f B_f^DL (V_fk - V_f,k-1) / (b_ik N_DL) <= S    DL subcarriers of tick k

with ``U`` defined on ``[capture, deadline - 1 - p)`` and ``V`` on ``[capture + 1 + p,
deadline)`` ([deadline]), ``b_ik`` the bits per subcarrier-symbol of station ``i``,
``N_UL`` the most UL data symbols a tick can hold (one user, no DL, no BSRP poll, no beacon),
``N_UL'`` the most when the tick also holds a DL exchange (its shortest: one user, one data
and one ack symbol), ``N_DL`` the most DL data symbols of a DL MU PPDU
(``MacTiming.dl_data_symbols``), and ``S`` the data subcarriers of the full-band RU, which no
valid layout exceeds. Every simulated schedule is feasible for this LP (with ``y_k = 1`` in
the ticks that carry a DL PPDU: its layouts use at most ``S`` subcarriers, its PPDUs at most
``N_UL``, or ``N_UL'`` next to a DL exchange, and at most ``N_DL`` symbols, and a state frame
is queued only after its camera frame), so the optimum bounds the delivered count of any
online allocator. Frames the channel will lose are left out: no schedule can deliver them.

Solvers: HiGHS (``scipy.optimize.linprog``), Clarabel and OSQP, each called on the same
matrices.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import scipy.sparse as sp
from numpy.typing import NDArray

from codesign_mb.wifi.sim import Trace

__all__ = [
    "LP_SOLVERS",
    "AirtimePrices",
    "OfflineLp",
    "OfflineResult",
    "airtime_prices",
    "build_offline_lp",
    "offline_optimum",
]

LP_SOLVERS = ("highs", "clarabel", "osqp")


@dataclass(frozen=True)
class OfflineLp:
    """[lp] as ``max c'x  s.t.  A x <= b, 0 <= x <= 1``.

    ``frame_rows`` are the rows of the trace's frame table in the LP (one per frame, in
    order; ``objective_vars`` their ``V_f,last``), ``ul_rows``/``ul_ticks`` and
    ``dl_rows``/``dl_ticks`` the capacity constraints of each tick.
    """

    c: NDArray[np.float64]
    A: sp.csc_matrix
    b: NDArray[np.float64]
    n_frames: int
    frame_rows: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    objective_vars: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    ul_rows: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    ul_ticks: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    dl_rows: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    dl_ticks: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def n_variables(self) -> int:
        return int(self.c.size)

    @property
    def n_constraints(self) -> int:
        return int(self.A.shape[0])


@dataclass(frozen=True)
class OfflineResult:
    """Optimum of [lp] (frames deliverable in time, fractional) and how it was found."""

    optimum: float
    solver: str
    solve_time_s: float
    status: str
    n_variables: int
    n_constraints: int
    n_frames: int
    n_frames_admitted: int


_Entries = list[tuple[int, int, float]]
"""Capacity entries ``(tick, variable, coefficient)``."""


class _LpAssembly:
    """[lp] of one trace under assembly: COO triplets of the rows, per-tick capacity entries.

    Rows come in the order of the frames (per frame: the camera frame's monotonicity rows, then
    per state-frame tick its monotonicity and precedence rows), then the DL-exchange rows, then
    one UL and one DL capacity row per tick; variables per frame ``U`` then ``V``, then ``y``.
    """

    def __init__(self, trace: Trace) -> None:
        cfg = trace.config
        mac, phy = cfg.mac, cfg.phy
        self.trace = trace
        self.p = cfg.traffic.processing_ticks(mac.tick_us)
        self.n_ul = mac.max_ul_data_symbols(phy, with_dl=False)
        self.n_ul_dl = mac.max_ul_data_symbols(phy, with_dl=True)
        self.n_dl = mac.dl_data_symbols
        self.full = float(phy.plan.full_band_data_subcarriers)
        self.rows: list[NDArray[np.int64]] = []
        self.cols: list[NDArray[np.int64]] = []
        self.vals: list[NDArray[np.float64]] = []
        self.b: list[float] = []
        self.nv = 0
        self.ul_cap: _Entries = []
        self.dl_cap: _Entries = []
        self.dl_steps: list[tuple[int, int, int]] = []  # (tick, V_k, V_k-1 or -1)
        self.objective: list[int] = []
        self.frame_rows: list[int] = []

    def _variables(self, n: int) -> int:
        first = self.nv
        self.nv += n
        return first

    def _row(self, entries: list[tuple[int, float]], rhs: float) -> None:
        idx = np.array([e[0] for e in entries], dtype=np.int64)
        self.rows.append(np.full(idx.size, len(self.b), dtype=np.int64))
        self.cols.append(idx)
        self.vals.append(np.array([e[1] for e in entries]))
        self.b.append(rhs)

    def _window(self, first: int, ticks: NDArray[np.int64], coef: NDArray, cap: _Entries) -> None:
        """Capacity entries of a cumulative fraction over ``ticks`` (``coef (X_k - X_k-1)``)."""
        for j, (k, c) in enumerate(zip(ticks.tolist(), coef.tolist(), strict=True)):
            cap.append((k, first + j, c))
            if j > 0:
                cap.append((k, first + j - 1, -c))

    def add_frame(self, row: int, station: int, cap: int, dead: int, ul: int, dl: int) -> None:
        """The ``U`` and ``V`` of one frame (skipped when its windows are empty)."""
        trace, p = self.trace, self.p
        dead = min(dead, trace.horizon_ticks)
        ul_ticks = np.arange(cap, dead - 1 - p)
        dl_ticks = np.arange(cap + 1 + p, dead)
        if ul_ticks.size == 0 or dl_ticks.size == 0:
            return
        self.frame_rows.append(row)
        u0 = self._variables(ul_ticks.size)
        v0 = self._variables(dl_ticks.size)
        for j in range(1, ul_ticks.size):  # U_k-1 <= U_k
            self._row([(u0 + j - 1, 1.0), (u0 + j, -1.0)], 0.0)
        for j, k in enumerate(dl_ticks.tolist()):
            if j > 0:  # V_k-1 <= V_k
                self._row([(v0 + j - 1, 1.0), (v0 + j, -1.0)], 0.0)
            self.dl_steps.append((k, v0 + j, v0 + j - 1 if j > 0 else -1))
            ju = min(k - 1 - p - cap, ul_ticks.size - 1)  # V_k <= U_{k-1-p}
            self._row([(v0 + j, 1.0), (u0 + ju, -1.0)], 0.0)
        ul_coef = ul / (trace.ul_bpss[station, ul_ticks] * self.n_ul * self.full)
        dl_coef = dl / (trace.dl_bpss[station, dl_ticks] * self.n_dl * self.full)
        self._window(u0, ul_ticks, ul_coef, self.ul_cap)
        self._window(v0, dl_ticks, dl_coef, self.dl_cap)
        self.objective.append(v0 + dl_ticks.size - 1)

    def add_dl_exchanges(self) -> None:
        """``y_k >= V_k - V_k-1``: a tick that carries any state frame holds a DL exchange,
        which leaves the UL PPDU at most ``n_ul_dl`` of the ``n_ul`` symbols."""
        if not self.dl_steps or self.n_ul_dl >= self.n_ul:
            return
        y0 = self._variables(self.trace.horizon_ticks)
        for k, v, v_prev in self.dl_steps:
            prev = [(v_prev, -1.0)] if v_prev >= 0 else []
            self._row([(v, 1.0), *prev, (y0 + k, -1.0)], 0.0)
        share = (self.n_ul - self.n_ul_dl) / self.n_ul
        for k in sorted({k for k, _, _ in self.dl_steps}):
            self.ul_cap.append((k, y0 + k, share))

    def _capacity(self, entries: _Entries) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """One row ``sum coef * var <= 1`` per tick of ``entries``; their rows and ticks."""
        if not entries:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        r = len(self.b)
        ticks = np.array([e[0] for e in entries], dtype=np.int64)
        uniq, inverse = np.unique(ticks, return_inverse=True)
        self.rows.append(r + inverse.astype(np.int64))
        self.cols.append(np.array([e[1] for e in entries], dtype=np.int64))
        self.vals.append(np.array([e[2] for e in entries], dtype=float))
        self.b.extend([1.0] * uniq.size)
        return r + np.arange(uniq.size, dtype=np.int64), uniq

    def build(self) -> OfflineLp:
        ul_rows, ul_ticks = self._capacity(self.ul_cap)
        dl_rows, dl_ticks = self._capacity(self.dl_cap)
        shape = (len(self.b), self.nv)
        A = (
            sp.csc_matrix(
                (np.concatenate(self.vals), (np.concatenate(self.rows), np.concatenate(self.cols))),
                shape=shape,
            )
            if self.rows
            else sp.csc_matrix(shape)
        )
        c = np.zeros(self.nv)
        c[self.objective] = 1.0
        return OfflineLp(
            c=c,
            A=A,
            b=np.asarray(self.b, dtype=float),
            n_frames=len(self.frame_rows),
            frame_rows=np.asarray(self.frame_rows, dtype=np.int64),
            objective_vars=np.asarray(self.objective, dtype=np.int64),
            ul_rows=ul_rows,
            ul_ticks=ul_ticks,
            dl_rows=dl_rows,
            dl_ticks=dl_ticks,
        )


def _int_column(frames: pd.DataFrame, name: str) -> list[int]:
    return [int(x) for x in frames[name].to_numpy(dtype=np.int64)]


def build_offline_lp(trace: Trace) -> OfflineLp:
    """Assemble [lp] for a trace (sparse, ``O(frames x window)`` non-zeros).

    Frames the channel loses on either hop are left out: no schedule can deliver them.
    """
    frames = trace.frames[(trace.frames["ul_ok"] != 0) & (trace.frames["dl_ok"] != 0)]
    lp = _LpAssembly(trace)
    columns = ("station", "capture_tick", "deadline_tick", "ul_bits", "dl_bits")
    rows = frames.index.to_numpy(dtype=np.int64).tolist()
    for row, *values in zip(rows, *(_int_column(frames, c) for c in columns), strict=True):
        lp.add_frame(row, *values)
    lp.add_dl_exchanges()
    return lp.build()


def _solve(lp: OfflineLp, solver: str) -> tuple[float, str]:
    nv = lp.n_variables
    if nv == 0:
        return 0.0, "optimal"
    if solver == "highs":
        from scipy.optimize import linprog

        res = linprog(-lp.c, A_ub=lp.A, b_ub=lp.b, bounds=(0.0, 1.0), method="highs")
        if res.status != 0:
            return float("nan"), f"highs: {res.message}"
        return float(-res.fun), "optimal"
    if solver == "clarabel":
        import clarabel

        A = sp.vstack([lp.A, sp.identity(nv), -sp.identity(nv)], format="csc")
        b = np.concatenate([lp.b, np.ones(nv), np.zeros(nv)])
        P = sp.csc_matrix((nv, nv))
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        s = clarabel.DefaultSolver(
            P, -lp.c, A, b, [clarabel.NonnegativeConeT(A.shape[0])], settings
        )
        sol = s.solve()
        status = str(sol.status)
        if "Solved" not in status:
            return float("nan"), f"clarabel: {status}"
        return float(lp.c @ np.asarray(sol.x)), "optimal"
    if solver == "osqp":
        import osqp

        A = sp.vstack([lp.A, sp.identity(nv)], format="csc")
        lower = np.concatenate([np.full(lp.A.shape[0], -np.inf), np.zeros(nv)])
        upper = np.concatenate([lp.b, np.ones(nv)])
        m = osqp.OSQP()
        m.setup(
            sp.csc_matrix((nv, nv)),
            -lp.c,
            A,
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
            return float("nan"), f"osqp: {status}"
        return float(lp.c @ res.x), status
    raise ValueError(f"solver must be one of {LP_SOLVERS}, got {solver!r}")


def offline_optimum(trace: Trace, *, solver: str = "highs") -> OfflineResult:
    """Solve [lp] for ``trace``: the most frames any scheduler can deliver in time.

    Parameters
    ----------
    trace:
        A recorded trace (:func:`codesign_mb.wifi.cell.generate_trace`,
        :meth:`SharedChannel.trace`, or an instance file).
    solver:
        ``"highs"`` (exact simplex/IPM, default), ``"clarabel"`` (interior point) or ``"osqp"``
        (first order; approximate on LPs).
    """
    if not isinstance(solver, str) or solver.lower() not in LP_SOLVERS:
        raise ValueError(f"solver must be one of {LP_SOLVERS}, got {solver!r}")
    solver = solver.lower()
    if not isinstance(trace, Trace):
        raise TypeError(f"trace must be a Trace, got {type(trace).__name__}")
    lp = build_offline_lp(trace)
    start = time.perf_counter()
    value, status = _solve(lp, solver)
    elapsed = time.perf_counter() - start
    return OfflineResult(
        optimum=value,
        solver=solver,
        solve_time_s=elapsed,
        status=status,
        n_variables=lp.n_variables,
        n_constraints=lp.n_constraints,
        n_frames=lp.n_frames,
        n_frames_admitted=len(trace.frames),
    )


@dataclass(frozen=True)
class AirtimePrices:
    """[lp] solved with its duals: what airtime is worth, in frames delivered in time.

    Attributes
    ----------
    optimum:
        The LP optimum (frames).
    ticks:
        One row per tick: ``ul_price`` and ``dl_price``, the dual prices of the tick's UL and
        DL capacity rows, i.e. how many more frames one more full band of UL (DL) PPDU in
        that tick would deliver (0 when the tick has spare capacity).
    frames:
        The LP's frames (the trace's frame table rows it holds) with ``delivered`` (``V_f``
        at the deadline, in [0, 1]), ``ul_work`` (full-band UL ticks the camera frame needs
        at the station's MCS at capture) and ``ul_bill`` (the cheapest UL airtime of the
        frame at the prices: ``min_k ul_price_k * work_fk`` over its window).
    """

    optimum: float
    ticks: pd.DataFrame
    frames: pd.DataFrame


def airtime_prices(trace: Trace) -> AirtimePrices:
    """Solve [lp] with HiGHS and read the dual prices of the per-tick capacity rows.

    By LP duality a frame the optimum delivers pays for its airtime at these prices with the
    value it creates (1 frame), and one left out would cost more than that: ``ul_bill`` is
    a lower bound of that cost (the UL part at the cheapest tick of the frame's window).
    """
    from scipy.optimize import linprog

    lp = build_offline_lp(trace)
    horizon = trace.horizon_ticks
    ticks = pd.DataFrame({"tick": np.arange(horizon), "ul_price": 0.0, "dl_price": 0.0})
    frames = trace.frames.loc[lp.frame_rows].reset_index(drop=True)
    if lp.n_variables == 0:
        frames = frames.assign(delivered=0.0, ul_work=0.0, ul_bill=0.0)
        return AirtimePrices(0.0, ticks, frames)
    res = linprog(-lp.c, A_ub=lp.A, b_ub=lp.b, bounds=(0.0, 1.0), method="highs")
    if res.status != 0:
        raise ValueError(f"the offline LP could not be solved: {res.message}")
    duals = -np.asarray(res.ineqlin.marginals)  # prices of "<=" rows of the max problem
    ticks.loc[lp.ul_ticks, "ul_price"] = duals[lp.ul_rows]
    ticks.loc[lp.dl_ticks, "dl_price"] = duals[lp.dl_rows]
    cfg = trace.config
    mac, phy = cfg.mac, cfg.phy
    p = cfg.traffic.processing_ticks(mac.tick_us)
    n_ul = mac.max_ul_data_symbols(phy, with_dl=False)
    full = float(phy.plan.full_band_data_subcarriers)
    ul_price = ticks["ul_price"].to_numpy()
    work, bill = [], []
    columns = ("station", "capture_tick", "deadline_tick", "ul_bits")
    for station, cap, dead, bits in zip(*(_int_column(frames, c) for c in columns), strict=True):
        window = np.arange(cap, min(dead, horizon) - 1 - p)
        w = bits / (trace.ul_bpss[station, window] * n_ul * full)
        work.append(float(w[0]))
        bill.append(float(np.min(ul_price[window] * w)))
    frames = frames.assign(
        delivered=np.clip(np.asarray(res.x)[lp.objective_vars], 0.0, 1.0),
        ul_work=work,
        ul_bill=bill,
    )
    return AirtimePrices(float(-res.fun), ticks, frames)
