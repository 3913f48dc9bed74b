"""Admission control of the convex allocator ([admit]): which head frames can still make it.

The channel is one machine that serves ``c`` full bands per tick (``c`` =
:attr:`~codesign_mb.wifi.convex.ConvexAllocatorConfig.admission_capacity`); station ``i``'s
head frame needs ``p_i = H_i / (S e_i)`` ticks of the full band (``S`` data subcarriers of the
widest RU) and is due in ``s_i`` ticks. The admitted set is the largest set that
earliest-deadline-first finishes in time (Moore-Hodgson: take the frames in deadline order
and, whenever the running total of ``p / c`` passes a deadline, reject the frame of the
largest ``p_i / w_i``, ``w_i`` the frame's value, 1 by default). Rejected frames get no share
of the relaxation, only the spectrum left at the end of the rounding: under overload the band
goes to the frames that can still make it instead of being spread over all of them (EDF's
domino effect).

For the admitted frames in deadline order, the as-late-as-possible schedule starts frame ``j``
at ``L_j = min_{k >= j} (s_k - P_k) + P_{j-1}`` (``P`` the running sum of ``p / c``); the part
of ``[L_j, L_j + p_j / c]`` inside the current tick is what frame ``j`` *must* get now for all
admitted frames to stay feasible: ``T_j = c |[L_j, L_j + p_j/c] & [0, 1]|``, and ``sum T <=
c``.

:func:`admit_edf` and :func:`must_serve` take and return arrays; :func:`admit_lists` and
:func:`must_serve_lists` are the same on Python lists (the reference). :func:`admit_ru_aware`
is the convex allocators' hot path, compiled: admission, the must-serve shares and the
RU-size check (the shares, each rounded up to an RU size, must fit one layout; while they do
not, the admitted frame with a share and the largest work per value is rejected).
"""

from __future__ import annotations

import heapq
import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

__all__ = [
    "admit_edf",
    "admit_lists",
    "admit_ru_aware",
    "must_serve",
    "must_serve_lists",
    "tick_admission",
]


def admit_edf(
    work_ticks: NDArray[np.float64] | list[float],
    slack_ticks: NDArray[np.float64] | list[float],
    weights: NDArray[np.float64] | list[float] | None = None,
) -> NDArray[np.bool_]:
    """[admit]: which jobs of a single machine to keep so that EDF meets every deadline.

    Jobs are given in deadline order (``slack_ticks`` non-decreasing). With unit weights this
    is Moore-Hodgson's algorithm (the most jobs in time); with weights, the job rejected when
    a deadline is passed is the one of the largest ``work / weight``. A job that cannot make
    its deadline alone is never admitted.

    Examples
    --------
    >>> admit_edf(np.array([2.0, 2.0, 1.0]), np.array([2.0, 3.0, 4.0])).tolist()
    [True, False, True]
    """
    work = np.asarray(work_ticks, dtype=float)
    ratio = None if weights is None else (work / np.maximum(weights, 1e-12)).tolist()
    return np.array(admit_lists(work.tolist(), np.asarray(slack_ticks, float).tolist(), ratio))


def admit_lists(work: list[float], slack: list[float], ratio: list[float] | None) -> list[bool]:
    """:func:`admit_edf` on lists (the hot path's form)."""
    ratio = work if ratio is None else ratio
    admitted = [True] * len(work)
    heap: list[tuple[float, int]] = []
    total = 0.0
    for j, (pj, sj) in enumerate(zip(work, slack, strict=True)):
        sj += 1e-9
        if pj > sj:  # cannot make it even alone
            admitted[j] = False
            continue
        total += pj
        heapq.heappush(heap, (-ratio[j], -j))  # largest ratio first, then the latest deadline
        if total > sj:
            _, neg = heapq.heappop(heap)
            admitted[-neg] = False
            total -= work[-neg]
    return admitted


def must_serve(
    work_ticks: NDArray[np.float64] | list[float], slack_ticks: NDArray[np.float64] | list[float]
) -> NDArray[np.float64]:
    """Part of the current tick each job of a feasible EDF set needs (as-late-as-possible).

    ``work_ticks`` and ``slack_ticks`` in deadline order; returns the fraction of the machine
    (of one tick) each job must get now, summing to at most 1 ([admit]).

    Examples
    --------
    >>> must_serve([0.5, 1.5], [1.0, 2.0]).tolist()  # two ticks of work in two ticks
    [0.5, 0.5]
    >>> must_serve([0.5, 1.0], [1.0, 2.0]).tolist()  # the second can wait
    [0.5, 0.0]
    """
    work = np.asarray(work_ticks, dtype=float).tolist()
    return np.array(must_serve_lists(work, np.asarray(slack_ticks, dtype=float).tolist()))


def must_serve_lists(work: list[float], slack: list[float]) -> list[float]:
    """:func:`must_serve` on lists: ``L_j = min_{k >= j}(s_k - P_k) + P_j - p_j``."""
    cum, total = [], 0.0
    for pj in work:
        total += pj
        cum.append(total)
    must = [0.0] * len(work)
    latest = math.inf
    for j in range(len(work) - 1, -1, -1):
        pj, cj = work[j], cum[j]
        latest = min(latest, slack[j] - cj)
        start = latest + cj - pj
        if start < 1.0:
            start = max(start, 0.0)
            must[j] = min(start + pj, 1.0) - start
    return must


@njit(cache=True)
def _fits(counts: np.ndarray, code: np.ndarray, widest: int, n_sub: int, extra: int) -> bool:
    """:meth:`codesign_mb.wifi.tick_dp.TickDp.fits` (``code``: 0..4 for 26..484 tones)."""
    if counts[widest] > 0:
        return counts[widest] == 1 and counts.sum() == 1
    by = np.zeros(5, dtype=np.int64)
    for k in range(counts.size):
        by[code[k]] += counts[k]
    h = n_sub - by[3] - 2 * by[4]
    if h < 0:
        return False
    centre = min(by[0], h + extra)
    return (by[0] - centre) + 2 * by[1] + 4 * by[2] <= 8 * h


@njit(cache=True)
def _must_into(work: np.ndarray, slack: np.ndarray, keep: np.ndarray, out: np.ndarray) -> None:
    """:func:`must_serve_lists` of the kept jobs, written into ``out`` (0 for the others)."""
    out[:] = 0.0
    cum = np.zeros(work.size)
    total = 0.0
    for j in range(work.size):
        if keep[j]:
            total += work[j]
            cum[j] = total
    latest = np.inf
    for j in range(work.size - 1, -1, -1):
        if not keep[j]:
            continue
        latest = min(latest, slack[j] - cum[j])
        start = latest + cum[j] - work[j]
        if start < 1.0:
            start = max(start, 0.0)
            out[j] = min(start + work[j], 1.0) - start


@njit(cache=True)
def _admit_kernel(
    work: np.ndarray,
    slack: np.ndarray,
    ratio: np.ndarray,
    admission: bool,
    c: float,
    full_sd: float,
    size_sd_lo: np.ndarray,
    code: np.ndarray,
    widest: int,
    n_sub: int,
    extra: int,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """:func:`admit_lists`, the must-serve shares (times ``c``) and the RU-size check."""
    n = work.size
    keep = np.zeros(n, dtype=np.bool_)
    total = 0.0
    for j in range(n):
        sj = slack[j] + 1e-9
        if work[j] > sj:
            continue
        keep[j] = True
        if not admission:
            continue
        total += work[j]
        if total > sj:  # reject the largest ratio (ties: the later deadline)
            worst = -1
            for q in range(j + 1):
                if keep[q] and (worst < 0 or ratio[q] >= ratio[worst]):
                    worst = q
            keep[worst] = False
            total -= work[worst]
    must = np.zeros(n)
    _must_into(work, slack, keep, must)
    must *= c
    counts = np.zeros(size_sd_lo.size, dtype=np.int64)
    while admission:
        counts[:] = 0
        for j in range(n):
            if keep[j] and must[j] > 0.0:
                k = np.searchsorted(size_sd_lo, must[j] * full_sd)
                counts[min(k, size_sd_lo.size - 1)] += 1
        if _fits(counts, code, widest, n_sub, extra):
            break
        worst = -1
        for q in range(n):
            if keep[q] and must[q] > 0.0 and (worst < 0 or ratio[q] >= ratio[worst]):
                worst = q
        keep[worst] = False
        _must_into(work, slack, keep, must)
        must *= c
    return keep, must


def admit_ru_aware(
    work: NDArray[np.float64],
    slack: NDArray[np.float64],
    ratio: NDArray[np.float64],
    *,
    admission: bool,
    capacity: float,
    full_sd: float,
    size_sd_lo: NDArray[np.float64],
    size_code: NDArray[np.int64],
    n_sub: int,
    extra: int,
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """The per-tick admission of the convex allocators, compiled (their hot path).

    Jobs in deadline order (``work`` in ticks at ``capacity`` bands per tick). With
    ``admission``: :func:`admit_lists` (ratio ``work / weight``), then while the must-serve
    shares ``capacity * must_serve`` of the admitted, each rounded up to the smallest RU size
    carrying it (``size_sd_lo``: the sizes' data subcarriers, ``full_sd`` the band's), do not
    fit one layout (``size_code`` 0..4 for 26..484 tones, ``n_sub`` 242-tone sub-channels,
    ``extra`` centre units outside them), the admitted job with a share of the largest ratio
    (ties: the later deadline) is rejected. Without: every job that can make it alone. Returns
    the admitted mask and the shares (fractions of the band, 0 for the rejected).
    """
    return _admit_kernel(
        np.ascontiguousarray(work, dtype=np.float64),
        np.ascontiguousarray(slack, dtype=np.float64),
        np.ascontiguousarray(ratio, dtype=np.float64),
        admission,
        float(capacity),
        float(full_sd),
        size_sd_lo,
        size_code,
        len(size_code) - 1,
        n_sub,
        extra,
    )


@njit(cache=True)
def _tick_kernel(
    backlog: np.ndarray,
    head: np.ndarray,
    slack_ticks: np.ndarray,
    e: np.ndarray,
    weights: np.ndarray,
    admission: bool,
    c: float,
    full_sd: float,
    size_sd_lo: np.ndarray,
    code: np.ndarray,
    n_sub: int,
    extra: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Stations with a queue in deadline order, then :func:`_admit_kernel` on their frames."""
    m = backlog.size
    count = 0
    for i in range(m):
        if backlog[i] > 0.0 and e[i] > 0.0:
            count += 1
    act = np.empty(count, dtype=np.int64)
    j = 0
    for i in range(m):
        if backlog[i] > 0.0 and e[i] > 0.0:
            act[j] = i
            j += 1
    act = act[np.argsort(slack_ticks[act], kind="mergesort")]  # stable: ties by index
    work, slack, ratio, need = np.empty(count), np.empty(count), np.empty(count), np.empty(count)
    for q in range(count):
        i = act[q]
        need[q] = backlog[i] / e[i]
        work[q] = head[i] / (e[i] * (full_sd * c))
        slack[q] = max(slack_ticks[i], 1.0)
        ratio[q] = work[q]
        if admission and weights.size:
            ratio[q] = work[q] / max(weights[i], 1e-12)
    keep, must = _admit_kernel(
        work, slack, ratio, admission, c, full_sd, size_sd_lo, code, code.size - 1, n_sub, extra
    )
    return act, keep, must, need


def tick_admission(
    backlog_bits: NDArray[np.float64],
    head_bits: NDArray[np.float64],
    slack_ticks: NDArray[np.float64],
    bits_per_subcarrier: NDArray[np.float64],
    weights: NDArray[np.float64] | None,
    *,
    admission: bool,
    capacity: float,
    full_sd: float,
    size_sd_lo: NDArray[np.float64],
    size_code: NDArray[np.int64],
    n_sub: int,
    extra: int,
) -> tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """One tick's admission from its demand, compiled: :func:`admit_ru_aware` of the head
    frames of the stations with a queue, in deadline order (ties: lower index).

    Returns those stations, the admitted mask, the must-serve shares (of the band) and each
    one's whole backlog in data subcarriers (all aligned with the stations).
    """

    def f64(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.ascontiguousarray(x, dtype=np.float64)

    return _tick_kernel(
        f64(backlog_bits),
        f64(head_bits),
        f64(slack_ticks),
        f64(bits_per_subcarrier),
        _NO_WEIGHTS if weights is None else f64(weights),
        admission,
        float(capacity),
        float(full_sd),
        size_sd_lo,
        size_code,
        n_sub,
        extra,
    )


_NO_WEIGHTS = np.zeros(0)
