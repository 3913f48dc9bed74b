"""Estimation error per phase and the estimator's consistency (NEES), per episode and pooled.

From the per-step record of a plant that reports the object's phase (the conveyor:
:mod:`codesign_mb.plants.phases`, :mod:`codesign_mb.rollout.object_errors`). Per episode
(:func:`episode_phase_metrics`), for each phase ``p`` of
:data:`~codesign_mb.plants.phases.PHASES` and overall (no suffix: every step with the object on
the scene, i.e. the three phases; the steps before it spawned are in none):

``phase_steps_<p>``
    The steps in the phase.
``est_error_mm_<p>``
    The RMS over those steps of the error of the object position the controller acted on
    (mm; NaN without steps).
``nees_<p>``, ``nees_state_<p>``
    The mean NEES over those steps, of the position (3 degrees of freedom) and of position
    and velocity (6), for an estimator exposing its covariance (else absent).
``nees_inside_<p>``
    The share of those steps whose position NEES is within the chi-square 95 % quantile (3
    degrees of freedom): the true object inside the estimator's 95 % ellipsoid, 0.95 for a
    consistent filter. Unlike the mean, it is not carried by a few large errors: a switching
    filter seeing a rare unannounced jump late has a heavy-tailed NEES whose mean says little
    about the bulk of its steps.

Pooled over the episodes (:func:`summarize_phases`, in
:func:`~codesign_mb.evaluation.evaluate.summarize`): ``phase_steps_<p>`` summed,
``est_error_mm_<p>`` the RMS over all the phase's steps of all episodes (pooled: every step
weighs the same, whatever its episode), ``nees_<p>`` the mean NEES over all those steps,
``nees_inside_<p>`` the share of them inside the ellipsoid, and ``nees_<p>_low`` /
``nees_<p>_high`` the two-sided band in which that mean lies with the summary's confidence
under a consistent filter
(:func:`~codesign_mb.estimation.consistency.nees_band`, ``N`` = the steps). The band assumes
independent samples; consecutive steps' errors are correlated (the filter's error decays over
several steps), so the true band of a consistent filter is wider: a mean just outside it is no
evidence, a mean several times the degrees of freedom is (overconfidence).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import chi2

from codesign_mb.estimation.consistency import nees_band
from codesign_mb.plants.phases import PHASES

__all__ = [
    "INSIDE_PROBABILITY",
    "NEES_DOF",
    "PHASE_SUFFIXES",
    "SUMMARY_COLUMNS",
    "episode_phase_metrics",
    "summarize_phases",
]

PHASE_SUFFIXES = ("", *(f"_{p}" for p in PHASES))
"""Column suffixes: overall (none), then one per phase."""

NEES_DOF = {"nees": 3, "nees_state": 6}
"""Degrees of freedom of each NEES: the position, the position and velocity."""

INSIDE_PROBABILITY = 0.95
"""The ellipsoid of ``nees_inside_<p>``: the position NEES within this chi-square quantile."""

_INSIDE_LIMIT = float(chi2.ppf(INSIDE_PROBABILITY, NEES_DOF["nees"]))

_NEES_COLUMNS = {"nees": "nees_position", "nees_state": "nees_state"}

SUMMARY_COLUMNS = tuple(
    f"{name}{suffix}{end}"
    for name, ends in (
        ("phase_steps", ("",)),
        ("est_error_mm", ("",)),
        ("nees", ("", "_low", "_high")),
        ("nees_inside", ("",)),
        ("nees_state", ("", "_low", "_high")),
    )
    for suffix in PHASE_SUFFIXES
    for end in ends
)
"""Every column :func:`summarize_phases` may give (the NEES ones only with a covariance)."""


def episode_phase_metrics(steps: pd.DataFrame) -> dict[str, Any]:
    """One episode's per-phase columns (see the module docstring) from its per-step record;
    empty without the ``phase`` and ``position_error_m`` columns."""
    if "phase" not in steps or "position_error_m" not in steps:
        return {}
    phase = steps["phase"].to_numpy()
    squared = steps["position_error_m"].to_numpy(dtype=float) ** 2
    nees = {
        name: steps[column].to_numpy(dtype=float)
        for name, column in _NEES_COLUMNS.items()
        if column in steps
    }
    row: dict[str, Any] = {}
    for suffix, mask in zip(
        PHASE_SUFFIXES, [phase >= 0, *(phase == k for k in range(len(PHASES)))], strict=True
    ):
        n = int(mask.sum())
        row[f"phase_steps{suffix}"] = n
        row[f"est_error_mm{suffix}"] = 1e3 * math.sqrt(squared[mask].mean()) if n else math.nan
        for name, values in nees.items():
            row[f"{name}{suffix}"] = float(values[mask].mean()) if n else math.nan
        if "nees" in nees:
            inside = nees["nees"][mask] <= _INSIDE_LIMIT
            row[f"nees_inside{suffix}"] = float(inside.mean()) if n else math.nan
    return row


def summarize_phases(table: pd.DataFrame, confidence: float = 0.95) -> dict[str, Any]:
    """The pooled per-phase figures of an evaluation table (see the module docstring); empty
    when its episodes carry no per-phase columns."""
    if "phase_steps" not in table:
        return {}
    out: dict[str, Any] = {}
    for suffix in PHASE_SUFFIXES:
        n = table[f"phase_steps{suffix}"].to_numpy(dtype=float)
        total = int(n.sum())
        out[f"phase_steps{suffix}"] = total
        some = n > 0
        rms = table[f"est_error_mm{suffix}"].to_numpy(dtype=float)[some]
        out[f"est_error_mm{suffix}"] = (
            math.sqrt(float(np.dot(n[some], rms**2)) / total) if total else math.nan
        )
        for name, dof in NEES_DOF.items():
            if f"{name}{suffix}" not in table:
                continue
            mean = table[f"{name}{suffix}"].to_numpy(dtype=float)[some]
            out[f"{name}{suffix}"] = float(np.dot(n[some], mean)) / total if total else math.nan
            low, high = nees_band(total, dof, confidence)
            out[f"{name}{suffix}_low"], out[f"{name}{suffix}_high"] = low, high
        if f"nees_inside{suffix}" in table:
            share = table[f"nees_inside{suffix}"].to_numpy(dtype=float)[some]
            pooled = float(np.dot(n[some], share)) / total if total else math.nan
            out[f"nees_inside{suffix}"] = pooled
    return out
