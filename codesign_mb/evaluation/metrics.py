"""Per-episode metrics of an evaluation and their aggregate (the columns of every table).

:func:`episode_row` turns one episode's step record into its row (success, QoS, age,
estimation error, the conveyor's outcome and per-phase figures); :func:`summarize` aggregates
the rows of one evaluated triple (success with its Wilson interval, QoS, failure reasons, MPC
timing, per-phase consistency). Both are pure functions of their tables, shared by every
study that evaluates (:mod:`codesign_mb.evaluation.evaluate`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.core.stats import wilson_interval
from codesign_mb.evaluation.phase_metrics import episode_phase_metrics, summarize_phases
from codesign_mb.plants.outcomes import FAILURE_REASONS, failure_reason

__all__ = ["TIMING_COLUMNS", "episode_row", "rows_to_table", "summarize"]

TIMING_COLUMNS = (
    "wall_time_s",
    "mpc_solve_ms_median",
    "mpc_solve_ms_p99",
    "mpc_solve_ms_max",
    "mpc_solve_cpu_ms_median",
    "mpc_solve_cpu_ms_p99",
)
"""Per-episode columns measuring wall time: they vary from run to run, the rest does not."""


def summarize(table: pd.DataFrame, confidence: float = 0.95) -> dict[str, Any]:
    """Aggregate an evaluation table (:func:`~codesign_mb.evaluation.evaluate.evaluate`):
    success rate with its Wilson interval, QoS, age, MPC.

    Solve-time figures are over episodes: the median of the episodes' medians, the median of
    their 99th percentiles and the overall maximum. With the conveyor's outcome columns:
    ``mean_time_to_grasp_s`` (over the episodes that grasped) and ``failures_<reason>``, the
    number of failed episodes per reason of
    :data:`~codesign_mb.plants.outcomes.FAILURE_REASONS`. With the per-phase columns, the
    estimation error per phase and the NEES with its band under a consistent filter
    (``est_error_mm_<phase>``, ``nees_<phase>``, ...: pooled over the steps,
    :func:`~codesign_mb.evaluation.phase_metrics.summarize_phases`).
    """
    if len(table) == 0:
        raise ValueError("cannot summarise an empty table")
    n = len(table)
    k = int(table["success"].sum())
    low, high = wilson_interval(k, n, confidence)
    out: dict[str, Any] = {
        "trials": n,
        "successes": k,
        "success_rate": k / n,
        "success_ci_low": low,
        "success_ci_high": high,
        "confidence": confidence,
    }
    for column in (
        "mean_requested_reliability",
        "delivered_fraction",
        "mean_age",
        "mean_qos_cost",
        "mean_estimation_error",
        "steps",
    ):
        if column in table:
            out[column] = float(table[column].mean())
    if "max_age" in table:
        out["max_age"] = int(table["max_age"].max())
    if "time_to_grasp_s" in table:
        out["mean_time_to_grasp_s"] = float(table["time_to_grasp_s"].mean())  # NaN: no grasp
    if "failure_reason" in table:
        for reason in FAILURE_REASONS:
            out[f"failures_{reason}"] = int((table["failure_reason"] == reason).sum())
    if "mpc_solve_ms_median" in table:
        out["mpc_solve_ms_median"] = float(table["mpc_solve_ms_median"].median())
        out["mpc_solve_ms_p99"] = float(table["mpc_solve_ms_p99"].median())
        out["mpc_solve_ms_max"] = float(table["mpc_solve_ms_max"].max())
        if "mpc_solve_cpu_ms_median" in table:
            out["mpc_solve_cpu_ms_median"] = float(table["mpc_solve_cpu_ms_median"].median())
            out["mpc_solve_cpu_ms_p99"] = float(table["mpc_solve_cpu_ms_p99"].median())
        out["mpc_failures"] = int(table["mpc_failures"].sum())
    out.update(summarize_phases(table, confidence))
    return out


def episode_row(steps: pd.DataFrame) -> dict[str, Any]:
    """One episode's metrics from its :func:`~codesign_mb.rollout.loop.rollout` record."""
    success = steps["success"].astype(bool) if "success" in steps else pd.Series(False)
    row: dict[str, Any] = {
        "success": bool(success.any()),
        "success_step": int(np.argmax(success.to_numpy())) if success.any() else -1,
        "steps": len(steps),
        "return": float(steps["reward"].sum()) if "reward" in steps else math.nan,
        "mean_requested_reliability": float(steps["qos_reliability"].mean()),
        "mean_latency_steps": float(steps["qos_latency_steps"].mean()),
        "mean_qos_cost": float(steps["qos_cost"].mean()),
        "delivered_fraction": float(steps["delivered"].astype(float).mean()),
        "mean_age": float(steps["age"].mean()),
        "max_age": int(steps["age"].max()),
        "mean_estimation_error": float(steps["estimation_error"].mean()),
        "max_estimation_error": float(steps["estimation_error"].max()),
    }
    if "lifted" in steps:
        row["lifted"] = bool(steps["lifted"].astype(bool).any())
    if "gripper_object_distance" in steps:
        row["min_gripper_object_distance"] = float(steps["gripper_object_distance"].min())
    if "perceived" in steps:
        row["perceived_fraction"] = float(steps["perceived"].astype(float).mean())
    if "off_belt" in steps:  # the conveyor's latched outcome events (plants.outcomes)
        last = steps.iloc[-1]
        row["failure_reason"] = failure_reason(
            row["success"],
            missed_grasp=bool(last["missed_grasp"]),
            dropped=bool(last["dropped"]),
            off_belt=bool(last["off_belt"]),
        )
        grasp_s = float(last["time_to_grasp_s"])
        row["time_to_grasp_s"] = grasp_s if grasp_s >= 0 else math.nan  # -1: never grasped
    row.update(episode_phase_metrics(steps))
    return row


def rows_to_table(rows: Sequence[Mapping[str, Any]]) -> pd.DataFrame:
    """The per-episode table from rows in any order: sorted by ``episode``."""
    return pd.DataFrame(list(rows)).sort_values("episode", kind="stable").reset_index(drop=True)
