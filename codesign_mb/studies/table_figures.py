"""Table I's outputs: Fig. 5 (``fig_lat``), the Markdown table, the files of ``codesign table``.

:func:`plot_timeline` is the one renderer of Fig. 5: ``codesign table`` draws it from
:func:`~codesign_mb.studies.table.run_table`'s summary and ``codesign report`` from whatever
``fig_lat`` table a results folder holds; the Pareto plot's renderer is
:func:`~codesign_mb.studies.table_pareto_plot.plot_pareto`.
:func:`write_table_outputs` writes everything ``codesign table`` leaves in its folder;
:func:`run_table_study` runs the table and writes it.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.core.records import RECORDS_DIR, RecordStore
from codesign_mb.core.registry import resolve_checkpoint
from codesign_mb.core.results import atomic_write, to_jsonable, write_results
from codesign_mb.evaluation.phase_metrics import SUMMARY_COLUMNS as PHASE_COLUMNS
from codesign_mb.studies.figures import new_figure, save_png
from codesign_mb.studies.table import TableConfig, run_table
from codesign_mb.studies.table_pareto_plot import plot_pareto
from codesign_mb.studies.table_refs import ROW_KIND, fixed_references
from codesign_mb.studies.table_rows import row_for_plant
from codesign_mb.studies.table_select import qos_timeline, timeline_row_name
from codesign_mb.studies.tuned import tuned_file

__all__ = [
    "SUMMARY_COLUMNS",
    "TableOutputs",
    "expanded_rows",
    "markdown_table",
    "plot_timeline",
    "run_table_study",
    "table_inputs",
    "write_table_outputs",
]

SUMMARY_COLUMNS: tuple[str, ...] = (
    "plant",
    "scenario",
    "row",
    "kind",
    "reference",
    "reference_of",
    "status",
    "success_rate",
    "success_ci_low",
    "success_ci_high",
    "mean_requested_reliability",
    "delivered_fraction",
    "train_env_steps",
    "train_wall_time_s",
    "cpu_ms_per_step",
    "pareto",
    "paper_success_rate",
    "paper_mean_reliability",
    "mpc_failures",
    "rule_threshold_m",
    "success_by_seed",
    *PHASE_COLUMNS,
)
"""The summary columns ``codesign table --json`` prints (with the estimation error and NEES per
phase, :mod:`codesign_mb.evaluation.phase_metrics`; NaN where an estimator has no covariance)."""


# -- Fig. 5 --------------------------------------------------------------------------------------
def plot_timeline(
    panels: Sequence[tuple[str, pd.DataFrame]], path: str | Path, *, dpi: int = 120
) -> Path:
    """Fig. 5 (PNG): the requested reliability along an episode, one panel per ``(title, steps)``.

    ``steps`` is a :func:`~codesign_mb.rollout.loop.rollout` record: columns ``t`` and
    ``qos_reliability`` (``q_t``); optional ``delivered`` (dots on ``q_t``), ``lifted`` and
    ``success`` (their first step is marked). A panel's title gets the average ``q_t``.
    """
    fig, axes = new_figure(len(panels), 1, width=7.0, height=3.2 if len(panels) == 1 else 2.6)
    for ax, (title, steps) in zip(axes[:, 0], panels, strict=True):
        _timeline_panel(ax, steps.sort_values("t"), title)
    axes[-1, 0].set_xlabel("step t (40 ms)")
    return save_png(fig, path, dpi=dpi)


def _timeline_panel(ax: Any, steps: pd.DataFrame, title: str) -> None:
    t = steps["t"].to_numpy()
    q = steps["qos_reliability"].to_numpy(float)
    ax.step(t, q, where="post", color="tab:blue", label="requested reliability $q_t$")
    if "delivered" in steps:
        delivered = steps["delivered"].astype(bool).to_numpy()
        ax.plot(t[delivered], q[delivered], "o", ms=3, color="tab:green", label="packet delivered")
    for column, label, style in (("lifted", "object lifted", "--"), ("success", "success", ":")):
        if column in steps and steps[column].astype(bool).any():
            first = int(np.argmax(steps[column].astype(bool).to_numpy()))
            ax.axvline(t[first], color="tab:red", ls=style, lw=1, label=f"{label} (t={t[first]})")
    ax.set_ylabel("reliability (PDR)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"{title}: average PDR {q.mean():.0%}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=7)


# -- Markdown ------------------------------------------------------------------------------------
def _pct(v: float) -> str:
    return "" if v is None or not np.isfinite(v) else f"{100 * v:.0f} %"


def markdown_table(summary: pd.DataFrame) -> str:
    """The summary as a Markdown table (percentages, interval, training cost, CPU per step).

    Reference rows (column ``reference``) have their name in italics, followed by
    ``(reference: KIND)``.

    A column ``MPC failures`` (failed solves summed over the episodes) is added when a row of
    the summary has an MPC.
    """
    failures = summary["mpc_failures"] if "mpc_failures" in summary else pd.Series(dtype=float)
    with_mpc = bool(np.isfinite(failures.astype(float)).any())
    columns = [
        "plant",
        "row",
        "success (95 % CI)",
        "avg. requested reliability",
        "delivered",
        "training (env steps, wall)",
        "CPU ms/step",
        *(["MPC failures"] if with_mpc else []),
        "Pareto",
        "paper (success / PDR)",
    ]
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for _, r in summary.iterrows():
        paper = ""
        if r["paper_success_rate"] is not None and np.isfinite(r["paper_success_rate"]):
            paper = f"{_pct(r['paper_success_rate'])} / {_pct(r['paper_mean_reliability'])}"
        if r["status"] != "ok":
            blanks = " |" * (6 if with_mpc else 5)
            lines.append(f"| {r['plant']} | {_row_cell(r)} | {r['status']} |{blanks} {paper} |")
        else:
            lines.append("| " + " | ".join(_markdown_cells(r, with_mpc, paper)) + " |")
    return "\n".join(lines) + "\n"


def _row_cell(r: pd.Series) -> str:
    """The row's name; a reference row's in italics, marked with its kind."""
    kind = str(r.get("kind", ROW_KIND))
    if kind == ROW_KIND or not bool(r.get("reference", False)):
        return str(r["row"])
    return f"*{r['row']}* (reference: {kind})"


def _markdown_cells(r: pd.Series, with_mpc: bool, paper: str) -> list[str]:
    steps, wall = r["train_env_steps"], r["train_wall_time_s"]
    cost = "0" if steps == 0 else f"{int(steps):,} steps, {wall / 60:.0f} min"
    failures = r.get("mpc_failures", math.nan)
    return [
        str(r["plant"]),
        _row_cell(r),
        f"{_pct(r['success_rate'])} "
        f"[{100 * r['success_ci_low']:.1f}, {100 * r['success_ci_high']:.1f}]"
        + (f" (by seed {r['success_by_seed']})" if r.get("success_by_seed") else ""),
        _pct(r["mean_requested_reliability"]),
        _pct(r["delivered_fraction"]),
        cost,
        f"{r['cpu_ms_per_step']:.2f}",
        *([f"{int(failures)}" if np.isfinite(failures) else ""] if with_mpc else []),
        "yes" if r["pareto"] else "",
        paper,
    ]


# -- the files of ``codesign table`` -------------------------------------------------------------
@dataclass(frozen=True)
class TableOutputs:
    """What :func:`write_table_outputs` wrote.

    Attributes
    ----------
    summary, episodes:
        The tables written (``tab_p``, ``tab_p_episodes``).
    out_dir:
        The results folder.
    files:
        Name -> path: ``tab_p`` and ``tab_p_episodes`` (their Parquet file), ``tab_p.md``,
        ``fig_pareto.png`` and, when drawn, ``fig_lat`` and ``fig_lat.png``.
    fig_lat_note:
        Why Fig. 5 was not drawn (``None`` when it was).
    computed, reused:
        Episodes run now and taken from an earlier run's records (:func:`run_table_study`).
    """

    summary: pd.DataFrame
    episodes: pd.DataFrame
    out_dir: Path
    files: dict[str, Path] = field(default_factory=dict)
    fig_lat_note: str | None = None
    computed: int = 0
    reused: int = 0


def write_table_outputs(
    summary: pd.DataFrame,
    episodes: pd.DataFrame,
    out_dir: str | Path,
    config: TableConfig,
    *,
    extra: dict[str, Any] | None = None,
) -> TableOutputs:
    """Write the files of ``codesign table`` into ``out_dir``.

    ``tab_p.{parquet,csv,json}`` (the summary), ``tab_p.md`` (:func:`markdown_table`),
    ``tab_p_episodes.*``, ``fig_pareto.png`` (:func:`plot_pareto`) and, when the row of
    :func:`~codesign_mb.studies.table_select.timeline_row_name` has a successful episode on the
    first plant, ``fig_lat.*`` (its per-step record, re-run from its seed) and
    ``fig_lat.png`` (:func:`plot_timeline`). ``extra`` goes into every table's metadata,
    with the plants and the rows as run on each (:func:`expanded_rows`); the provenance
    holds the SHA-256 of every file the rows read (:func:`table_inputs`).
    """
    out = Path(out_dir)
    plants = {
        p.label: {"name": p.name, "options": p.options, "scenario": p.scenario}
        for p in config.table_plants()
    }
    extra = {**(extra or {}), "plants": plants, "rows": expanded_rows(config)}
    files: dict[str, Path] = {}
    inputs = table_inputs(config)
    files["tab_p"] = write_results(
        out, table=summary, config=config, name="tab_p", extra=extra, checkpoints=inputs
    )["parquet"]
    files["tab_p_episodes"] = write_results(
        out, table=episodes, config=config, name="tab_p_episodes", extra=extra, checkpoints=inputs
    )["parquet"]
    with atomic_write(out / "tab_p.md", "w") as fh:
        fh.write(markdown_table(summary))
    files["tab_p.md"] = out / "tab_p.md"
    files["fig_pareto.png"] = plot_pareto(
        summary, out / "fig_pareto.png", title=f"codesign table --pipeline {config.pipeline}"
    )
    note = _write_timeline(summary, episodes, out, config, extra, files)
    return TableOutputs(summary, episodes, out, files, note)


def _write_timeline(
    summary: pd.DataFrame,
    episodes: pd.DataFrame,
    out: Path,
    config: TableConfig,
    extra: dict[str, Any],
    files: dict[str, Path],
) -> str | None:
    """Fig. 5's table and PNG into ``out`` (added to ``files``), or why it was not drawn."""
    first = config.table_plants()[0]
    name = timeline_row_name(config, summary)
    row = next((row_for_plant(r, first) for r in config.table_rows() if r.name == name), None)
    found = None if row is None else qos_timeline(first, row, episodes)
    if row is None or found is None:
        status = summary.loc[(summary["row"] == name) & (summary["plant"] == first.label), "status"]
        why = (
            f"{name!r} was not run ({status.iloc[0]})"
            if len(status) and status.iloc[0] != "ok"
            else f"no successful episode of {name!r} on {first.label}"
        )
        return f"{why}: fig_lat not drawn"
    steps, seed = found
    files["fig_lat"] = write_results(
        out,
        table=steps,
        config=config,
        name="fig_lat",
        extra={**extra, "row": row.name, "plant": first.label, "episode_seed": seed},
    )["parquet"]
    files["fig_lat.png"] = plot_timeline(
        [(f"{row.name}, {first.label}", steps)], out / "fig_lat.png"
    )
    return None


def expanded_rows(config: TableConfig) -> dict[str, list[dict[str, Any]]]:
    """Plant label -> the table's rows and fixed references as they run on it.

    Every component's kind, checkpoint and options, the covariance rule's threshold resolved
    for the plant with its source (:func:`~codesign_mb.studies.table_rows.row_for_plant`);
    the ``random`` references' probabilities are in the summary's ``qos_options``.
    """
    rows = list(config.table_rows())
    if config.with_references():
        rows += [ref.row for ref in fixed_references(config.table_rows())]
    return {
        plant.label: [to_jsonable(row_for_plant(row, plant)) for row in rows]
        for plant in config.table_plants()
    }


def table_inputs(config: TableConfig) -> dict[str, Path]:
    """The shipped files the table's rows read, by name: each checkpoint found (a missing one
    is in the summary's ``status``) and the tuned thresholds' file when it exists."""
    found: dict[str, Path] = {}
    for row in config.table_rows():
        for spec in (row.controller, row.estimator, row.qos):
            if spec.checkpoint and spec.checkpoint not in found:
                with contextlib.suppress(ValueError):
                    found[spec.checkpoint] = resolve_checkpoint(spec.checkpoint)
    if tuned_file().is_file():
        found["tuned/rule_threshold.json"] = tuned_file()
    return found


def run_table_study(
    config: TableConfig,
    out_dir: str | Path,
    *,
    progress: Callable[..., Any] | None = None,
    command: str = "",
    fresh: bool = False,
) -> TableOutputs:
    """Run the table (:func:`~codesign_mb.studies.table.run_table`) and write its files.

    Torch runs on one thread in this process (the machine is shared; the workers add the
    parallelism). ``command`` and the run's wall time go into the tables' metadata. Every
    finished episode is kept in ``<out_dir>/.records`` as it finishes
    (:mod:`codesign_mb.core.records`): a rerun computes only the missing ones and writes the
    same tables (``fresh``: it recomputes every episode).
    """
    import torch

    torch.set_num_threads(1)
    started = time.perf_counter()
    store = RecordStore(Path(out_dir) / RECORDS_DIR, fresh=fresh)
    with store.on_interrupt():
        summary, episodes = run_table(config, progress=progress, store=store)
    extra = {
        "command": command,
        "wall_time_s": round(time.perf_counter() - started, 1),
        "episodes_computed": store.computed,
        "episodes_reused": store.reused,
    }
    outputs = write_table_outputs(summary, episodes, out_dir, config, extra=extra)
    return replace(outputs, computed=store.computed, reused=store.reused)
