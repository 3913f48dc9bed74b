"""What a results folder must hold before :func:`~codesign_mb.studies.report.build_report`
draws from it: every value of the columns a figure reads (:data:`COLUMN_RULES`), checked
before anything is drawn, and named with its table file, row and value when it cannot mean
what the figure says (text in a number column, a NaN latency, a success rate of 3)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from codesign_mb.core.config import show
from codesign_mb.core.results import ResultsDir

__all__ = ["COLUMN_RULES", "SUCCESS_COLUMNS", "check_sweep", "check_values", "not_results"]

SUCCESS_COLUMNS = ("success", "successes", "success_rate")
"""The columns a success rate is counted from, one of them per table."""


@dataclass(frozen=True)
class _Rule:
    """What a column the report reads must hold (each non-missing value)."""

    what: str
    """The values, as the error says them: "true or false", "a number in [0, 1]", ..."""
    ge: float | None = None
    le: float | None = None
    integer: bool = False
    boolean: bool = False
    missing: bool = False
    """Whether a missing value (NaN, None) is allowed: an optional metric of some rows."""


_FRACTION = _Rule("a number in [0, 1]", ge=0.0, le=1.0, missing=True)
_COUNT = _Rule("an integer >= 0", ge=0, integer=True)
COLUMN_RULES: dict[str, _Rule] = {
    "success": _Rule("true or false (or 0 / 1)", boolean=True),
    "successes": _COUNT,
    "trials": _COUNT,
    "success_rate": _FRACTION,
    "mean_requested_reliability": _FRACTION,
    "delivered_fraction": _FRACTION,
    "mean_age": _Rule("a finite number >= 0", ge=0.0, missing=True),
    "mpc_failures": _Rule("a finite number >= 0", ge=0.0, missing=True),
    "latency_steps": _COUNT,
    "belt_speed_mps": _Rule("a finite number >= 0", ge=0.0),
    "reliability": _FRACTION,
    "n_robots": _Rule("an integer >= 1", ge=1, integer=True),
    "t": _COUNT,
    "qos_reliability": _Rule("a number in [0, 1]", ge=0.0, le=1.0),
    "delivered": _Rule("true or false (or 0 / 1)", boolean=True, missing=True),
    "lifted": _Rule("true or false (or 0 / 1)", boolean=True, missing=True),
}
"""The values of every column a known table's figure is drawn from (see :func:`check_values`)."""

_SUCCESS_READS = (*SUCCESS_COLUMNS, "trials")
_METRIC_READS = ("mean_requested_reliability", "delivered_fraction", "mean_age", "mpc_failures")
_READS: dict[str, tuple[str, ...]] = {
    "tab_p": (*_SUCCESS_READS, *_METRIC_READS),
    "fig_cn": (*_SUCCESS_READS, *_METRIC_READS, "latency_steps", "belt_speed_mps", "reliability"),
    "fig_lat": ("t", "qos_reliability", "delivered", "lifted", "success"),
    "fig_wifi": (*_SUCCESS_READS, *_METRIC_READS, "n_robots"),
}
"""The columns of each known table whose values the report reads."""


def _success_column(frame: pd.DataFrame) -> tuple[str, ...]:
    """The columns the success rate is counted from (as :func:`success_summary` picks them)."""
    if "success" in frame.columns:
        return ("success",)
    if "successes" in frame.columns and "trials" in frame.columns:
        return ("successes", "trials")
    return ("success_rate",)


def _bad_values(
    frame: pd.DataFrame, column: str, rule: _Rule, required: bool
) -> tuple[str, int] | None:
    """Why ``frame[column]`` breaks ``rule`` and the first bad row, or ``None``."""
    values = frame[column]
    if pd.api.types.is_bool_dtype(values):
        numbers = values.astype(float)
    else:
        numbers = pd.to_numeric(values, errors="coerce")
        if pd.api.types.is_bool_dtype(numbers):
            numbers = numbers.astype(float)
    missing = values.isna().to_numpy()
    text = numbers.isna().to_numpy() & ~missing  # a string (or any non-number) in the column
    array = numbers.to_numpy(dtype=float, na_value=np.nan)
    bad = text.copy()
    if not rule.missing or required:
        bad |= missing
    present = ~missing & ~text
    with np.errstate(invalid="ignore"):
        wrong = ~np.isfinite(array)
        if rule.boolean:
            wrong |= (array != 0.0) & (array != 1.0)
        if rule.integer:
            wrong |= array != np.round(array)
        if rule.ge is not None:
            wrong |= array < rule.ge
        if rule.le is not None:
            wrong |= array > rule.le
    bad |= present & wrong
    if not bad.any():
        return None
    row = int(np.flatnonzero(bad)[0])
    return f"{column} must be {rule.what}, got {show(values.iloc[row])}", row


def check_values(
    frame: pd.DataFrame, name: str, results: ResultsDir, *, required: tuple[str, ...]
) -> None:
    """``ValueError`` naming the table file, column, row and value the report cannot draw.

    A figure drawn from a text success column, a NaN latency or a success rate of 3 would be
    nonsense (or a crash deep in pandas): refused, as a corrupt metadata file is.
    """
    needed = {*required, *_success_column(frame)}
    if name == "fig_cn":
        needed.add("belt_speed_mps")  # a panel per speed: NaN is no speed
    for column in _READS[name]:
        if column not in frame.columns:
            continue
        found = _bad_values(frame, column, COLUMN_RULES[column], column in needed)
        if found is None:
            continue
        problem, row = found
        raise ValueError(_where(frame, row, results) + problem)
    if {"successes", "trials"} <= set(frame.columns):
        over = (pd.to_numeric(frame["successes"]) > pd.to_numeric(frame["trials"])).to_numpy()
        if over.any():
            row = int(np.flatnonzero(over)[0])
            raise ValueError(
                _where(frame, row, results) + "successes must be <= trials, got "
                f"{show(frame['successes'].iloc[row])} > {show(frame['trials'].iloc[row])}"
            )


def _where(frame: pd.DataFrame, row: int, results: ResultsDir) -> str:
    """``"results table 'fig_cn' (DIR/fig_cn.parquet), row 3: "``: where a row comes from."""
    source = str(frame["source"].iloc[row]) if "source" in frame.columns else "?"
    index = int(row - np.flatnonzero((frame["source"] == source).to_numpy())[0])
    path = results.path / f"{source}.parquet"
    return f"results table {source!r} ({str(path)!r}), row {index}: "


def check_sweep(name: str, frame: pd.DataFrame, metric: str, results: ResultsDir) -> None:
    """``ValueError`` unless the sweep table ``name`` has numbers to plot in ``metric``."""
    path = results.path / f"{name}.parquet"
    missing = [
        c for c in ("pipeline", "belt_speed_mps", "n_robots", metric) if c not in frame.columns
    ]
    if missing:
        numeric = [c for c in frame.columns if pd.api.types.is_numeric_dtype(frame[c])]
        raise ValueError(
            f"sweep table {name!r} ({str(path)!r}) has no column {', '.join(missing)}"
            + (f" (--metric may name one of {', '.join(numeric)})" if metric in missing else "")
        )
    frame = frame.assign(source=name)
    rules = {
        "belt_speed_mps": COLUMN_RULES["belt_speed_mps"],
        "n_robots": COLUMN_RULES["n_robots"],
        metric: _Rule("a finite number", missing=True),
    }
    for column, rule in rules.items():
        found = _bad_values(frame, column, rule, required=False)
        if found is not None:
            problem, row = found
            raise ValueError(_where(frame, row, results) + problem)


def not_results(path: Path) -> str:
    """Why ``path`` is no results folder: it holds no complete table."""
    partial = sorted(
        p.name
        for p in (*path.glob("*.json"), *path.glob("*.parquet"))
        if not p.name.startswith(".")
    )
    return (
        f"{str(path)!r} is not a results folder: it holds no results table (a NAME.parquet "
        "next to its NAME.json, as evaluate, table, wifi capacity and sweep write)"
        + (
            f"; found only {', '.join(partial[:5])}{', ...' if len(partial) > 5 else ''}"
            if partial
            else ""
        )
    )
