"""Admission control of the convex allocator (``eq_admit``): which head frames can still make it.

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
:func:`must_serve_lists` are the same on Python lists, the per-tick hot path's form.
"""

from __future__ import annotations

import heapq
import math

import numpy as np
from numpy.typing import NDArray

__all__ = ["admit_edf", "admit_lists", "must_serve", "must_serve_lists"]


def admit_edf(
    work_ticks: NDArray[np.float64] | list[float],
    slack_ticks: NDArray[np.float64] | list[float],
    weights: NDArray[np.float64] | list[float] | None = None,
) -> NDArray[np.bool_]:
    """``eq_admit``: which jobs of a single machine to keep so that EDF meets every deadline.

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
    (of one tick) each job must get now, summing to at most 1 (``eq_admit``).

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
