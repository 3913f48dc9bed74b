"""The summary records of a table: one per (plant, row), from its episodes or why it has none.

Columns: :mod:`codesign_mb.studies.table` (the module docstring); the labels ``row``,
``plant``, ``scenario`` (the plant's scenario name, else its label), ``kind`` (``"row"``
or a reference kind of :mod:`codesign_mb.studies.table_refs`), ``reference``,
``reference_of`` (the row a ``random`` reference matches), ``pipeline``, ``controller``,
``estimator``, ``qos``, ``qos_options`` (the QoS policy's options as run, JSON),
``rule_threshold_m`` and ``rule_threshold_source`` (the covariance rule's threshold on this
plant and where it came from, :func:`~codesign_mb.studies.table_rows.row_for_plant`; NaN
and ``""`` without a rule) and ``status``.
"""

from __future__ import annotations

import json
import math
from typing import Any

import pandas as pd

from codesign_mb.core.results import to_jsonable
from codesign_mb.evaluation.evaluate import summarize
from codesign_mb.evaluation.phase_metrics import SUMMARY_COLUMNS as PHASE_COLUMNS
from codesign_mb.plants.outcomes import FAILURE_REASONS
from codesign_mb.studies.table_cost import CPU_COLUMNS, TrainingCost
from codesign_mb.studies.table_refs import ROW_KIND, Reference
from codesign_mb.studies.table_rows import TablePlant, TableRow, stack_of
from codesign_mb.studies.tuned import rule_defaults

__all__ = ["missing_record", "record"]


def _labels(plant: TablePlant, ref: Reference) -> dict[str, Any]:
    row = ref.row
    return {
        "row": row.name,
        "plant": plant.label,
        "scenario": plant.scenario or plant.label,
        "kind": ref.kind,
        "reference": ref.kind != ROW_KIND,
        "reference_of": ref.of,
        "pipeline": stack_of(row),
        "controller": row.controller.kind,
        "estimator": row.estimator.kind,
        "qos": row.qos.kind,
        "qos_options": json.dumps(to_jsonable(row.qos.options), sort_keys=True),
        **_threshold(row),
        "status": "ok",
    }


def _threshold(row: TableRow) -> dict[str, Any]:
    """``rule_threshold_m`` and ``rule_threshold_source`` of a row (NaN and ``""``: no rule)."""
    if row.qos.kind != "rule":
        return {"rule_threshold_m": math.nan, "rule_threshold_source": ""}
    if "threshold_m" not in row.qos.options:
        value, source = rule_defaults()["threshold_m"], "the rule's default"
    else:
        value, source = row.qos.options["threshold_m"], row.threshold_source or "given in the row"
    return {"rule_threshold_m": float(value), "rule_threshold_source": source}


def _paper(row: TableRow) -> dict[str, Any]:
    return {
        "paper_success_rate": row.paper_success_rate,
        "paper_mean_reliability": row.paper_mean_reliability,
    }


def missing_record(plant: TablePlant, ref: Reference, status: str) -> dict[str, Any]:
    """The summary row of a row that was not run: its status, no figures."""
    return {
        **_labels(plant, ref),
        "status": status,
        "trials": 0,
        "successes": 0,
        **{c: math.nan for c in _NUMBERS},
        "train_env_steps": math.nan,
        "train_wall_time_s": math.nan,
        "train_sources": "",
        "success_by_seed": "",
        **_paper(ref.row),
    }


def record(
    plant: TablePlant, ref: Reference, table: pd.DataFrame, cost: TrainingCost
) -> dict[str, Any]:
    """The summary row of one (plant, row) cell from its episodes.

    ``mpc_failures`` is the MPC's failed solves summed over the episodes
    (:func:`~codesign_mb.evaluation.evaluate.summarize`), NaN for a row without an MPC.
    """
    summary = summarize(table)
    record: dict[str, Any] = {
        **_labels(plant, ref),
        "trials": summary["trials"],
        "successes": summary["successes"],
        **{c: summary.get(c, math.nan) for c in _SUMMARY},
        "train_env_steps": cost.env_steps,
        "train_wall_time_s": cost.wall_time_s,
        "train_sources": ", ".join(cost.sources)
        + (f" (unknown: {', '.join(cost.unknown)})" if cost.unknown else ""),
        **{c: float(table[c].mean()) for c in CPU_COLUMNS},
        "eval_wall_time_s": float(table["wall_time_s"].sum()),
    }
    record["cpu_ms_per_step"] = float(sum(record[c] for c in CPU_COLUMNS))
    record["mpc_failures"] = summary.get("mpc_failures", math.nan)
    record["success_by_seed"] = _success_by_seed(table)
    return {**record, **_paper(ref.row)}


def _success_by_seed(table: pd.DataFrame) -> str:
    """Each root seed's success rate, ``"0: 97 %, 1: 95 %"`` (``""``: one root seed)."""
    if "root_seed" not in table or table["root_seed"].nunique() < 2:
        return ""
    rates = table.groupby("root_seed", sort=True)["success"].mean()
    return ", ".join(f"{int(s)}: {100 * r:.0f} %" for s, r in rates.items())


_SUMMARY = (
    "success_rate",
    "success_ci_low",
    "success_ci_high",
    "mean_requested_reliability",
    "delivered_fraction",
    "mean_age",
    "mean_estimation_error",
    "mean_time_to_grasp_s",
    *(f"failures_{reason}" for reason in FAILURE_REASONS),
    *PHASE_COLUMNS,
)
_NUMBERS = (*_SUMMARY, *CPU_COLUMNS, "cpu_ms_per_step", "mpc_failures", "eval_wall_time_s")
