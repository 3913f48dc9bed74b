"""The per-tick layout problem of the convex allocators, solved exactly by dynamic programming.

Per-tick objective
------------------
For the admitted stations ``i`` (deadline order) with must-serve share ``T_i``, backlog
share ``Z_i`` beyond it (both fractions of the widest RU's ``S`` data subcarriers), value
``a_i`` of must-serve service and ``b_i < a_i`` of service ahead of need, a valid layout
([layout]) giving station ``i`` the RU ``r_i`` is worth::

    V(r) = sum_i a_i min(s_i, T_i) + b_i min((s_i - T_i)^+, Z_i),   s_i = N_SD(r_i) / S

which is the objective of the relaxation [qp] (:mod:`codesign_mb.wifi.convex_qp`) at
``rho = 0``, maximised over ``t, z`` for the fixed layout (``a >= b``: must-serve service
first). The exact per-tick optimum maximises ``V`` over every valid layout of the plan;
:mod:`codesign_mb.wifi.tick_milp` writes it as a MILP for HiGHS (the reference).

Structure used here
-------------------
Every 802.11ax plan (IEEE 802.11ax-2021, Tables 27-7 to 27-9) is made of ``n_sub`` 242-tone
sub-channels, each two 106-tone blocks of 4 units (split in 52- and 26-tone RUs by halves)
around one centre 26-tone unit, plus, in 80 MHz, one more centre 26-tone unit; a 484-tone RU
covers two adjacent sub-channels, and the widest RU covers all. So a multiset of RUs other
than the widest fits iff, with ``g = n242 + 2 n484`` sub-channels taken whole (``nX``: RUs of
``X`` tones) and ``h = n_sub - g`` free ones, the 26-tone RUs split into ``n26_block`` in the
blocks and ``n26_centre`` on centre units such that::

    n26_block + 2 n52 + 4 n106 <= 8 h,    n26_centre <= h + extra

(sizes 1, 2, 4 units divide each other and the blocks, so first-fit decreasing packs them).
The dynamic programme runs over the stations with state ``(u, c, g)`` (block units, centre
units, sub-channels used) and gives each station one of: nothing, a 26 on a centre unit, a 26
in a block, a 52, a 106, a 242, a 484 (each only if smaller than the widest RU); the widest
RU, which excludes everything else, is compared separately. :meth:`TickDp.solve` returns the
best layout (RU indices), :func:`layout_value` its value.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from codesign_mb.wifi.allocators import RuPacker
from codesign_mb.wifi.phy import RuPlan

__all__ = ["TickDp", "layout_value", "size_values"]

_NEG = -math.inf


def size_values(
    frac_sd: NDArray[np.float64],
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    t_max: NDArray[np.float64],
    z_max: NDArray[np.float64],
) -> NDArray[np.float64]:
    """``V_i`` of each station (rows) given an RU of each size (columns ``N_SD,k / S``)."""
    s = frac_sd[None, :]
    t = t_max[:, None]
    return a[:, None] * np.minimum(s, t) + b[:, None] * np.minimum(
        np.maximum(s - t, 0.0), z_max[:, None]
    )


def layout_value(
    plan: RuPlan,
    layout: NDArray[np.int64],
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    t_max: NDArray[np.float64],
    z_max: NDArray[np.float64],
) -> float:
    """``V(r)`` of the layout of the stations (``layout[i]`` is station ``i``'s RU or -1)."""
    full = plan.full_band_data_subcarriers
    sd = np.array([u.data_subcarriers for u in plan.units] + [0], dtype=float)
    s = sd[np.asarray(layout)] / full
    return float(np.sum(a * np.minimum(s, t_max) + b * np.minimum(np.maximum(s - t_max, 0), z_max)))


@njit(cache=True)
def _dp(
    values: np.ndarray, succ: np.ndarray, pred: np.ndarray
) -> tuple[np.ndarray, float]:  # pragma: no cover - compiled
    """Best choice per station (0 = none) and its value.

    ``succ[s, k]`` is the state after choice ``k`` in state ``s`` (-1: does not fit),
    ``pred[s, k]`` the state before it.
    """
    m, k_count = values.shape
    n_states = succ.shape[0]
    best = np.full(n_states, -np.inf)
    best[0] = 0.0
    choice = np.zeros((m, n_states), dtype=np.int8)
    for i in range(m):
        new = best.copy()
        for s in range(n_states):
            v = best[s]
            if v == -np.inf:
                continue
            for k in range(1, k_count):
                w = values[i, k]
                s2 = succ[s, k]
                if w <= 0.0 or s2 < 0:
                    continue  # no value (never better than nothing), or does not fit
                if v + w > new[s2]:
                    new[s2] = v + w
                    choice[i, s2] = k
        best = new
    s_best, v_best = 0, 0.0
    for s in range(n_states):
        if best[s] > v_best:
            s_best, v_best = s, best[s]
    out = np.zeros(m, dtype=np.int64)
    s = s_best
    for i in range(m - 1, -1, -1):
        k = choice[i, s]
        out[i] = k
        if k:
            s = pred[s, k]
    return out, v_best


@njit(cache=True)
def _solve_objective(
    frac_sd: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    t_max: np.ndarray,
    z_max: np.ndarray,
    allowed: np.ndarray,
    choice_size: np.ndarray,
    succ: np.ndarray,
    pred: np.ndarray,
) -> tuple[np.ndarray, float]:  # pragma: no cover - compiled
    """:func:`size_values`, then :meth:`TickDp.solve` in one compiled call (the hot path)."""
    m, k_count = allowed.shape
    widest = k_count - 1
    values = np.zeros((m, k_count))
    for i in range(m):
        for k in range(k_count):
            if allowed[i, k]:
                s = frac_sd[k]
                over = min(max(s - t_max[i], 0.0), z_max[i])
                values[i, k] = a[i] * min(s, t_max[i]) + b[i] * over
    choice_values = np.zeros((m, choice_size.size))
    for i in range(m):
        for c in range(1, choice_size.size):
            choice_values[i, c] = values[i, choice_size[c]]
    picks, best = _dp(choice_values, succ, pred)
    sizes = np.full(m, -1, dtype=np.int64)
    for i in range(m):
        if picks[i]:
            sizes[i] = choice_size[picks[i]]
    whole, who = best, -1
    for i in range(m):
        if values[i, widest] > whole:
            whole, who = values[i, widest], i
    if who >= 0:
        sizes[:] = -1
        sizes[who] = widest
        best = whole
    return sizes, best


@njit(cache=True)
def _rounding_choices(
    served: np.ndarray,
    x: np.ndarray,
    t_max: np.ndarray,
    full_sd: float,
    size_sd: np.ndarray,
    size_sd_lo: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    """:meth:`TickDp.rounding_choices`, compiled."""
    m, k_count = served.size, size_sd.size
    allowed = np.zeros((m, k_count), dtype=np.bool_)
    for i in range(m):
        sd = served[i] * full_sd
        if sd > 1e-3 * full_sd:
            allowed[i, min(np.searchsorted(size_sd_lo, sd), k_count - 1)] = True
        down = np.searchsorted(size_sd, sd * (1 + 1e-9), side="right") - 1
        if down >= 0:
            allowed[i, down] = True
        t = t_max[i] * full_sd
        if t > 0.0:
            allowed[i, min(np.searchsorted(size_sd_lo, t), k_count - 1)] = True
        if x.shape[0] == m:
            for k in range(k_count):
                if x[i, k] > 1e-3:
                    allowed[i, k] = True
    return allowed


def _transitions(
    n_sub: int, extra: int, du: list[int], dc: list[int], dg: list[int]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``succ`` and ``pred`` tables over the states ``(u, c, g)`` that fit (index 0: empty)."""
    states = [
        (u, c, g)
        for g in range(n_sub + 1)
        for c in range(n_sub - g + extra + 1)
        for u in range(8 * (n_sub - g) + 1)
    ]
    states.sort(key=lambda x: (x[0] + x[1], x))  # less spectrum first (ties: the smaller)
    index = {x: j for j, x in enumerate(states)}
    succ = np.full((len(states), len(du)), -1, dtype=np.int64)
    pred = np.full((len(states), len(du)), -1, dtype=np.int64)
    for j, (u, c, g) in enumerate(states):
        for k in range(1, len(du)):
            nxt = index.get((u + du[k], c + dc[k], g + dg[k]))
            if nxt is not None:
                succ[j, k] = nxt
                pred[nxt, k] = j
    return succ, pred


class TickDp:
    """The exact per-tick layout problem of one RU plan (see the module docstring).

    Parameters
    ----------
    plan:
        The channel's RU plan; its structure is checked against the one the programme assumes.
    packer:
        Places the chosen RU sizes (largest first) into a valid layout.
    """

    def __init__(self, plan: RuPlan, packer: RuPacker) -> None:
        self.plan, self.packer = plan, packer
        sizes = list(plan.sizes)
        self.n_sub = plan.count(242)
        self.extra = plan.n_units - 9 * self.n_sub
        expected = {26: plan.n_units, 52: 4 * self.n_sub, 106: 2 * self.n_sub, 242: self.n_sub}
        for tones, count in expected.items():
            if plan.count(tones) != count:  # pragma: no cover - guards the plan's structure
                raise AssertionError(f"{plan.bandwidth_mhz} MHz: {count} RUs of {tones} expected")
        self.widest = len(sizes) - 1
        # choices: none, 26 centre, 26 block, 52, 106, then 242 and 484 when not the widest
        size_of = [-1, 0, 0, 1, 2]
        du, dc, dg = [0, 0, 1, 2, 4], [0, 1, 0, 0, 0], [0, 0, 0, 0, 0]
        for tones, sub in ((242, 1), (484, 2)):
            if tones in sizes and sizes.index(tones) < self.widest:
                size_of.append(sizes.index(tones))
                du.append(0)
                dc.append(0)
                dg.append(sub)
        self.choice_size = np.array(size_of, dtype=np.int64)
        self._succ, self._pred = _transitions(self.n_sub, self.extra, du, dc, dg)
        self.frac_sd = packer.size_sd / float(plan.full_band_data_subcarriers)
        self._cols = np.maximum(self.choice_size, 0)
        # compile (or load from numba's disk cache) before the first tick
        one = np.zeros(1)
        self.solve_objective(one, one, one, one, np.ones((1, len(sizes)), dtype=bool))
        self._no_x = np.zeros((0, len(sizes)))
        self._size_sd = packer.size_sd.astype(np.float64)
        self.rounding_choices(one, None, one)

    def fits(self, size_counts: list[int] | NDArray[np.int64]) -> bool:
        """Whether RUs of these counts per size (``plan.sizes`` order) fit in one layout."""
        counts = [int(x) for x in size_counts]
        if counts[self.widest]:
            return counts[self.widest] == 1 and sum(counts) == 1
        by = dict(zip(self.plan.sizes, counts, strict=True))
        h = self.n_sub - by.get(242, 0) - 2 * by.get(484, 0)
        if h < 0:
            return False
        centre = min(by[26], h + self.extra)
        return (by[26] - centre) + 2 * by[52] + 4 * by[106] <= 8 * h

    def solve(
        self, values: NDArray[np.float64], allowed: NDArray[np.bool_] | None = None
    ) -> tuple[list[int], float]:
        """Best size index per station (``-1`` = none) and its value ``V``.

        ``values[i, k]`` is station ``i``'s value of an RU of size ``k`` (:func:`size_values`);
        ``allowed[i, k]`` (default all) restricts the sizes station ``i`` may get.
        """
        m = values.shape[0]
        if allowed is not None:
            values = np.where(allowed, values, 0.0)
        choice_values = values[:, self._cols]
        choice_values[:, 0] = 0.0
        picks, best = _dp(choice_values, self._succ, self._pred)
        sizes = self.choice_size[picks].tolist()
        whole = values[:, self.widest]
        if m and float(whole.max()) > best:
            i = int(np.argmax(whole))
            sizes = [-1] * m
            sizes[i] = self.widest
            best = float(whole[i])
        return sizes, float(best)

    def solve_objective(
        self,
        a: NDArray[np.float64],
        b: NDArray[np.float64],
        t_max: NDArray[np.float64],
        z_max: NDArray[np.float64],
        allowed: NDArray[np.bool_],
    ) -> tuple[list[int], float]:
        """:meth:`solve` of :func:`size_values` ``(a, b, T, Z)``, in one compiled call."""
        sizes, best = _solve_objective(
            self.frac_sd, a, b, t_max, z_max, allowed, self._cols, self._succ, self._pred
        )
        return sizes.tolist(), float(best)

    def rounding_choices(
        self,
        served: NDArray[np.float64],
        x: NDArray[np.float64] | None,
        t_max: NDArray[np.float64],
    ) -> NDArray[np.bool_]:
        """RU sizes each station may get when rounding a relaxed solution ([round]):
        the sizes in the support of its relaxed ``x`` (rows: stations; ``None``: none), the
        sizes just below and just above its relaxed service ``served`` and the smallest
        carrying its must-serve share ``T`` (both fractions of the band)."""
        x = self._no_x if x is None else np.ascontiguousarray(x, dtype=np.float64)
        return _rounding_choices(
            np.ascontiguousarray(served, dtype=np.float64),
            x,
            np.ascontiguousarray(t_max, dtype=np.float64),
            float(self.plan.full_band_data_subcarriers),
            self._size_sd,
            self.packer.size_sd_lo,
        )

    def place(self, stations: list[int], sizes: list[int], lay: list[int]) -> int:
        """Give ``stations[j]`` an RU of size ``sizes[j]`` in ``lay`` (largest first, best fit);
        returns the used-unit mask."""
        packer, used = self.packer, 0
        for j in sorted(range(len(sizes)), key=lambda j: -sizes[j]):
            k = sizes[j]
            if k < 0:
                break
            r = packer.place(k, used)
            if r < 0:  # pragma: no cover - the programme only picks sizes that fit
                raise AssertionError(f"RU sizes {sizes} do not fit the plan")
            lay[stations[j]] = r
            used |= packer.mask[r]
        return used
