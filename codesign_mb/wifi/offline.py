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

Solvers (:mod:`codesign_mb.wifi.lp_solvers`): HiGHS through ``highspy``, Clarabel and OSQP,
each handed the same sparse arrays; :mod:`codesign_mb.wifi.offline_windows` splits a trace
into independent windows, :mod:`codesign_mb.wifi.offline_reference` writes the same LP in
cvxpy (the readable reference the tests check the assembly against).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import scipy.sparse as sp
from numpy.typing import NDArray

from codesign_mb.wifi.lp_solvers import LP_SOLVERS, solve_box_lp
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


@dataclass(frozen=True)
class OfflineLp:
    """[lp] as ``max c'x  s.t.  A x <= b, 0 <= x <= 1``.

    ``frame_rows`` are the rows of the trace's frame table in the LP (one per frame, in
    order; ``objective_vars`` their ``V_f,last``), ``ul_rows``/``ul_ticks`` and
    ``dl_rows``/``dl_ticks`` the capacity constraints of each tick. ``bounded``: the
    variables whose bounds ``0 <= x <= 1`` are not implied by the rows (each chain's first
    and last, and ``y``; ``None``: all), which an interior-point solver needs as rows.
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
    bounded: NDArray[np.int64] | None = None

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
    build_time_s: float = 0.0
    frame_rows: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """The trace's frame-table rows the LP holds (frames both hops deliver, in time)."""
    delivered: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    """Per LP frame (``frame_rows``), the fraction the optimum delivers in time (``V_f``)."""
    ul_price: NDArray[np.float64] | None = None
    """Per tick, the dual price of its UL capacity row (:class:`AirtimePrices`); ``None``
    when the solver gave no duals."""
    dl_price: NDArray[np.float64] | None = None
    """Per tick, the dual price of its DL capacity row."""


def _ranges(lengths: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """For blocks of ``lengths``: each entry's block and its index inside the block."""
    block = np.repeat(np.arange(lengths.size), lengths)
    starts = np.cumsum(lengths) - lengths
    return block, np.arange(int(lengths.sum())) - starts[block]


class _Rows:
    """COO triplets of ``<=`` rows under assembly (numpy blocks, no per-entry Python)."""

    def __init__(self) -> None:
        self.rows: list[NDArray[np.int64]] = []
        self.cols: list[NDArray[np.int64]] = []
        self.vals: list[NDArray[np.float64]] = []
        self.b: list[NDArray[np.float64]] = []
        self.n = 0

    def pairs(self, first: NDArray[np.int64], second: NDArray[np.int64]) -> None:
        """Rows ``x_first - x_second <= 0``."""
        r = self.n + np.arange(first.size)
        self.rows += [r, r]
        self.cols += [first, second]
        self.vals += [np.ones(first.size), -np.ones(first.size)]
        self.b.append(np.zeros(first.size))
        self.n += first.size

    def grouped(
        self, group: NDArray[np.int64], cols: NDArray[np.int64], vals: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """One row ``sum vals * x_cols <= 1`` per distinct ``group``; the rows and groups."""
        uniq, inverse = np.unique(group, return_inverse=True)
        self.rows.append(self.n + inverse.astype(np.int64))
        self.cols.append(cols)
        self.vals.append(vals)
        self.b.append(np.ones(uniq.size))
        rows = self.n + np.arange(uniq.size, dtype=np.int64)
        self.n += uniq.size
        return rows, uniq

    def matrix(self, n_variables: int) -> tuple[sp.csc_matrix, NDArray[np.float64]]:
        if not self.rows:
            return sp.csc_matrix((self.n, n_variables)), np.zeros(self.n)
        A = sp.csc_matrix(
            (np.concatenate(self.vals), (np.concatenate(self.rows), np.concatenate(self.cols))),
            shape=(self.n, n_variables),
        )
        return A, np.concatenate(self.b)


def _chain(
    first: NDArray[np.int64], length: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Variables of cumulative chains (``first``, ``length`` per frame): each one's frame,
    its index in the chain and its column."""
    frame, j = _ranges(length)
    return frame, j, first[frame] + j


def build_offline_lp(trace: Trace) -> OfflineLp:
    """Assemble [lp] for a trace as sparse arrays (``O(frames x window)`` non-zeros).

    Variables per frame ``U`` then ``V``, then one ``y`` per tick; rows: monotonicity,
    precedence and DL-exchange rows, then one UL and one DL capacity row per busy tick.
    Frames the channel loses on either hop are left out: no schedule can deliver them.
    """
    cfg = trace.config
    mac, phy = cfg.mac, cfg.phy
    p = cfg.traffic.processing_ticks(mac.tick_us)
    n_ul = mac.max_ul_data_symbols(phy, with_dl=False)
    n_ul_dl = mac.max_ul_data_symbols(phy, with_dl=True)
    full = float(phy.plan.full_band_data_subcarriers)
    f = trace.frames[(trace.frames["ul_ok"] != 0) & (trace.frames["dl_ok"] != 0)]
    cap = f["capture_tick"].to_numpy(dtype=np.int64)
    dead = np.minimum(f["deadline_tick"].to_numpy(dtype=np.int64), trace.horizon_ticks)
    nu = dead - 1 - p - cap  # U on [capture, deadline - 1 - p)
    nd = dead - (cap + 1 + p)  # V on [capture + 1 + p, deadline)
    keep = (nu > 0) & (nd > 0)
    cap, nu, nd = cap[keep], nu[keep], nd[keep]
    station = f["station"].to_numpy(dtype=np.int64)[keep]
    ul_bits = f["ul_bits"].to_numpy(dtype=float)[keep]
    dl_bits = f["dl_bits"].to_numpy(dtype=float)[keep]
    u0 = np.cumsum(nu + nd) - (nu + nd)
    v0 = u0 + nu
    nv = int((nu + nd).sum())
    rows = _Rows()
    fu, ju, cu = _chain(u0, nu)
    fv, jv, cv = _chain(v0, nd)
    later_u, later_v = ju > 0, jv > 0
    rows.pairs(cu[later_u] - 1, cu[later_u])  # U_k-1 <= U_k
    rows.pairs(cv[later_v] - 1, cv[later_v])  # V_k-1 <= V_k
    rows.pairs(cv, u0[fv] + np.minimum(jv, nu[fv] - 1))  # V_k <= U_k-1-p
    ku, kv = cap[fu] + ju, cap[fv] + 1 + p + jv  # the tick of each U and V
    n_y = trace.horizon_ticks if nv and n_ul_dl < n_ul else 0
    if n_y:  # y_k >= V_k - V_k-1: a tick that carries a state frame holds a DL exchange
        r = rows.n + np.arange(cv.size)
        prev = later_v
        rows.rows += [r, r[prev], r]
        rows.cols += [cv, cv[prev] - 1, nv + kv]
        rows.vals += [np.ones(cv.size), -np.ones(int(prev.sum())), -np.ones(cv.size)]
        rows.b.append(np.zeros(cv.size))
        rows.n += cv.size
    ul_coef = ul_bits[fu] / (trace.ul_bpss[station[fu], ku] * n_ul * full)
    dl_coef = dl_bits[fv] / (trace.dl_bpss[station[fv], kv] * mac.dl_data_symbols * full)
    # capacity of tick k: coef_k (X_k - X_k-1)
    ul_tick = [ku, ku[later_u]]
    ul_col = [cu, cu[later_u] - 1]
    ul_val = [ul_coef, -ul_coef[later_u]]
    if n_y:
        busy = np.unique(kv)
        ul_tick.append(busy)
        ul_col.append(nv + busy)
        ul_val.append(np.full(busy.size, (n_ul - n_ul_dl) / n_ul))
    ul_rows, ul_ticks = rows.grouped(
        np.concatenate(ul_tick), np.concatenate(ul_col), np.concatenate(ul_val)
    )
    dl_rows, dl_ticks = rows.grouped(
        np.concatenate([kv, kv[later_v]]),
        np.concatenate([cv, cv[later_v] - 1]),
        np.concatenate([dl_coef, -dl_coef[later_v]]),
    )
    A, b = rows.matrix(nv + n_y)
    c = np.zeros(nv + n_y)
    objective = v0 + nd - 1
    c[objective] = 1.0
    return OfflineLp(
        c=c,
        A=A,
        b=b,
        n_frames=int(cap.size),
        frame_rows=f.index.to_numpy(dtype=np.int64)[keep],
        objective_vars=objective,
        ul_rows=ul_rows,
        ul_ticks=ul_ticks,
        dl_rows=dl_rows,
        dl_ticks=dl_ticks,
        bounded=np.concatenate([u0, v0 - 1, v0, objective, nv + np.arange(n_y)]),
    )


def _int_column(frames: pd.DataFrame, name: str) -> list[int]:
    return [int(x) for x in frames[name].to_numpy(dtype=np.int64)]


def offline_optimum(trace: Trace, *, solver: str = "auto") -> OfflineResult:
    """Solve [lp] for ``trace``: the most frames any scheduler can deliver in time.

    Parameters
    ----------
    trace:
        A recorded trace (:func:`codesign_mb.wifi.cell.generate_trace`,
        :meth:`SharedChannel.trace`, or an instance file).
    solver:
        ``"auto"`` (default: HiGHS's simplex on small LPs, Clarabel's interior point on large
        ones), ``"highs"``, ``"clarabel"`` or ``"osqp"`` (first order; approximate on LPs);
        see :mod:`codesign_mb.wifi.lp_solvers`.
    """
    if not isinstance(solver, str) or solver.lower() not in LP_SOLVERS:
        raise ValueError(f"solver must be one of {LP_SOLVERS}, got {solver!r}")
    if not isinstance(trace, Trace):
        raise TypeError(f"trace must be a Trace, got {type(trace).__name__}")
    start = time.perf_counter()
    lp = build_offline_lp(trace)
    built = time.perf_counter()
    sol = solve_box_lp(lp.c, lp.A, lp.b, solver=solver, bounded=lp.bounded)
    elapsed = time.perf_counter() - built
    delivered = (
        np.clip(sol.x[lp.objective_vars], 0.0, 1.0)
        if sol.x is not None
        else np.full(lp.n_frames, np.nan)
    )
    prices = _tick_prices(lp, sol.row_duals, trace.horizon_ticks)
    return OfflineResult(
        optimum=sol.value,
        solver=sol.solver,
        solve_time_s=elapsed,
        status=sol.status,
        n_variables=lp.n_variables,
        n_constraints=lp.n_constraints,
        n_frames=lp.n_frames,
        n_frames_admitted=len(trace.frames),
        build_time_s=built - start,
        frame_rows=lp.frame_rows,
        delivered=delivered,
        ul_price=None if prices is None else prices[0],
        dl_price=None if prices is None else prices[1],
    )


def _tick_prices(
    lp: OfflineLp, duals: NDArray[np.float64] | None, horizon: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Per tick, the duals of its UL and DL capacity rows (0 for a tick without a row)."""
    if duals is None:
        return None
    ul, dl = np.zeros(horizon), np.zeros(horizon)
    ul[lp.ul_ticks] = duals[lp.ul_rows]
    dl[lp.dl_ticks] = duals[lp.dl_rows]
    return ul, dl


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
    lp = build_offline_lp(trace)
    horizon = trace.horizon_ticks
    ticks = pd.DataFrame({"tick": np.arange(horizon), "ul_price": 0.0, "dl_price": 0.0})
    frames = trace.frames.loc[lp.frame_rows].reset_index(drop=True)
    if lp.n_variables == 0:
        frames = frames.assign(delivered=0.0, ul_work=0.0, ul_bill=0.0)
        return AirtimePrices(0.0, ticks, frames)
    sol = solve_box_lp(lp.c, lp.A, lp.b, solver="highs")
    # the duals are the prices of the "<=" rows of the max problem
    prices = _tick_prices(lp, sol.row_duals, horizon)
    if sol.x is None or prices is None:
        raise ValueError(f"the offline LP could not be solved: {sol.status}")
    ticks["ul_price"], ticks["dl_price"] = prices
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
        delivered=np.clip(sol.x[lp.objective_vars], 0.0, 1.0),
        ul_work=work,
        ul_bill=bill,
    )
    return AirtimePrices(sol.value, ticks, frames)
