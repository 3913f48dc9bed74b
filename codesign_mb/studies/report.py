"""``codesign report``: the paper's Table I and Figs. 4-6 from a results folder, both pipelines.

The report reads the tables of one results folder (written by
:func:`~codesign_mb.core.results.write_results`) and renders, for each known table
that is present, a PNG figure and a section of ``report.md``; absent tables are listed as
skipped. The learned pipeline (the paper's) and its model-based counterpart are shown side by
side wherever the table holds both (column ``pipeline``).

Table names and columns
-----------------------
A figure's data may be split over several tables: ``<name>`` and any ``<name>.<suffix>``
(e.g. ``tab_p.learned`` written by one command, ``tab_p.model_based`` by another) are
concatenated. A table without a ``pipeline`` column gets the suffix as its pipeline, else
the ``pipeline`` string of its stored config. Curves and rows are identified by whichever
*label columns* are present, in this order: ``pipeline`` (``"learned"`` = the paper's, also
spelt ``"model-free"``; ``"model_based"`` = ours, also ``"model-based"``; solid and dashed
lines), ``policy``, ``row``, ``controller``, ``estimator``, ``qos_policy``, ``qos``,
``scheduler``, ``allocator``, ``channel``. Success is any of: a per-episode bool
``success`` (counted, with Wilson intervals), ``successes`` + ``trials`` per row, or
``success_rate`` in [0, 1] (with ``trials`` when known). Column aliases: ``robots`` =
``n_robots``, ``mean_reliability`` = ``mean_requested_reliability`` (the average PDR).

``tab_p`` -- Table I: success rate and average PDR per policy (100 trials each in the paper)
    required: a label column (best: ``pipeline`` and ``policy``, e.g. "MLP state est., static
    QoS", "predictor, rule QoS") and success; optional: ``mean_requested_reliability``,
    ``delivered_fraction``, ``mean_age``. An
    :func:`~codesign_mb.evaluation.evaluate.evaluate` table (one row per episode) plus the
    label columns fits.

``fig_cn`` -- Fig. 4: success rate versus latency, per estimator, at belt speeds 0.2/0.6 m/s
    required: ``latency_steps`` (tau in control periods of 40 ms) and success; optional:
    ``belt_speed_mps`` (one panel each), ``sweep`` (rows ``"reliability"`` are drawn in a
    second row of panels versus ``reliability``; other rows versus latency), label columns.
    :func:`~codesign_mb.studies.fig_cn.run_fig_cn`'s table fits.

``fig_lat`` -- Fig. 5: the requested reliability over one episode
    required: ``t`` (step) and ``qos_reliability`` (requested ``q_t``); optional: ``episode``
    (several episodes: a successful one is shown, picked with the report seed),
    ``delivered`` (bool), ``lifted`` (bool; the first lift is marked), ``success`` (bool),
    label columns (one panel per combination). A
    :func:`~codesign_mb.rollout.loop.rollout` frame plus ``pipeline`` fits.

``fig_wifi`` (alias ``wifi_capacity``) -- Fig. 6: success versus the number of robots sharing
    a 40 MHz WiFi 6 channel
    required: ``n_robots`` and success; optional: ``delivered_fraction`` (second panel),
    ``mean_requested_reliability``, label columns (e.g. ``pipeline`` or ``policy`` "static
    QoS" / "dynamic QoS", ``scheduler``, ``channel``). ``codesign wifi capacity``'s table fits.

Sweeps -- any table written by :func:`~codesign_mb.studies.sweep.run_sweep` (metadata
``extra.kind == "sweep"``): the mean of ``success_rate`` (or ``--metric``) over replicates
versus ``n_robots``, one panel per belt speed, one line per pipeline.

A table with ``mpc_failures`` (per episode, or summed per row) shows the failed MPC solves,
summed, next to its success rates.

Values are checked before anything is drawn (:mod:`~codesign_mb.studies.report_checks`): a
success that is not true/false, a rate outside [0, 1], a NaN or negative latency or robot
count, text in a number column stop the report with the table file, row and value; a missing
optional metric (NaN in ``mean_requested_reliability``, ``mpc_failures``, ...) is allowed.

Figures
-------
The report draws each figure with the one renderer of the study that owns it:
:func:`~codesign_mb.studies.table_pareto_plot.plot_pareto` (``tab_p``, with the paper's
Table I as crosses), :func:`~codesign_mb.studies.fig_cn.plot_fig_cn`,
:func:`~codesign_mb.studies.table_figures.plot_timeline` (``fig_lat``),
:func:`~codesign_mb.studies.fig_wifi_figures.plot_capacity` (``fig_wifi``) and
:func:`~codesign_mb.studies.sweep_figures.plot_sweep`; this module turns a results folder's
tables into their inputs (:mod:`codesign_mb.studies.report_sections`) and writes ``report.md``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.core.results import ResultsDir, atomic_write, package_version
from codesign_mb.studies.report_checks import (
    SUCCESS_COLUMNS,
    check_sweep,
    check_values,
    not_results,
)
from codesign_mb.studies.report_sections import (
    LABEL_COLUMNS,
    PAPER_TAB_P,
    RENDERERS,
    ReportConfig,
    Section,
    labels_of,
    render_sweep,
    success_summary,
)

__all__ = [
    "COLUMN_ALIASES",
    "LABEL_COLUMNS",
    "PAPER_TAB_P",
    "PIPELINE_ALIASES",
    "REPORT_TABLES",
    "TABLE_ALIASES",
    "Report",
    "ReportConfig",
    "Section",
    "build_report",
    "collect",
    "labels_of",
    "success_summary",
]

REPORT_TABLES: dict[str, tuple[str, ...]] = {
    "tab_p": (),
    "fig_cn": ("latency_steps",),
    "fig_lat": ("t", "qos_reliability"),
    "fig_wifi": ("n_robots",),
}
"""Known tables and their required columns (besides success and a label column, see the
module docstring)."""

TABLE_ALIASES: dict[str, tuple[str, ...]] = {"fig_wifi": ("wifi_capacity",)}
"""Other table names read as a known table."""

COLUMN_ALIASES: dict[str, str] = {
    "robots": "n_robots",
    "mean_reliability": "mean_requested_reliability",
}
"""Column name -> the report's name (applied when the report's name is absent)."""

PIPELINE_ALIASES: dict[str, str] = {
    "model-free": "learned",
    "model_free": "learned",
    "model-based": "model_based",
}
"""Other spellings of the two pipelines."""

_NEEDS_SUCCESS = ("tab_p", "fig_cn", "fig_wifi")


@dataclass(frozen=True)
class Report:
    """What :func:`build_report` wrote."""

    out_dir: Path
    markdown: Path
    sections: list[Section]
    skipped: dict[str, str] = field(default_factory=dict)

    @property
    def figures(self) -> dict[str, Path]:
        return {s.name: s.figure for s in self.sections if s.figure is not None}


# ----------------------------------------------------------------------------- data


def collect(results: ResultsDir, name: str) -> pd.DataFrame | None:
    """Concatenate the tables ``name``, ``name.<suffix>`` and their aliases; ``None`` if none.

    A ``source`` column names the table each row came from. A missing ``pipeline`` column is
    filled with the table's suffix (``tab_p.learned`` -> ``"learned"``), else with the string
    ``pipeline`` of its stored config; :data:`PIPELINE_ALIASES` and :data:`COLUMN_ALIASES`
    are applied.
    """
    parts = []
    for base in (name, *TABLE_ALIASES.get(name, ())):
        for table_name in results.names:
            if table_name != base and not table_name.startswith(f"{base}."):
                continue
            frame = results.table(table_name)
            if "pipeline" not in frame.columns:
                config = results.config(table_name)
                if table_name != base:
                    frame = frame.assign(pipeline=table_name[len(base) + 1 :])
                elif isinstance(config, dict) and isinstance(config.get("pipeline"), str):
                    frame = frame.assign(pipeline=config["pipeline"])
            if "pipeline" in frame.columns:
                frame = frame.assign(pipeline=frame["pipeline"].replace(PIPELINE_ALIASES))
            renames = {
                a: b
                for a, b in COLUMN_ALIASES.items()
                if a in frame.columns and b not in frame.columns
            }
            parts.append(frame.rename(columns=renames).assign(source=table_name))
    if not parts:
        return None
    return pd.concat(parts, ignore_index=True)


def _check(frame: pd.DataFrame, name: str) -> str | None:
    """Why ``frame`` cannot be rendered as ``name`` (``None`` if it can)."""
    missing = [c for c in REPORT_TABLES[name] if c not in frame.columns]
    if name in _NEEDS_SUCCESS and not set(SUCCESS_COLUMNS) & set(frame.columns):
        missing.append("success | successes | success_rate")
    if name == "tab_p" and not labels_of(frame):
        missing.append(" | ".join(LABEL_COLUMNS))
    if missing:
        return f"missing column{'s' if len(missing) > 1 else ''} {', '.join(missing)}"
    if frame.empty:
        return "the table is empty"
    return None


# ----------------------------------------------------------------------------- report


def build_report(
    results_dir: str | Path,
    out_dir: str | Path | None = None,
    config: ReportConfig | None = None,
    *,
    progress: Callable[[Sequence[str]], Any] | None = None,
) -> Report:
    """Render every known table of ``results_dir`` into ``out_dir`` (PNG + ``report.md``).

    Parameters
    ----------
    results_dir:
        A folder written by :func:`~codesign_mb.core.results.write_results`.
    out_dir:
        Where the figures and ``report.md`` go; default ``<results_dir>/report``.
    config:
        Figure settings.
    progress:
        Wraps the list of table names being rendered (e.g. a progress bar).

    Returns
    -------
    Report
        The sections rendered and the tables skipped (absent, or without a column their
        figure needs), with the reason.

    Raises
    ------
    ValueError
        ``results_dir`` is missing or holds no results table at all ("not a results
        folder"); a table's metadata is not a JSON object; a column a figure is drawn from
        holds a value it cannot mean (text, NaN, a rate outside [0, 1], a negative latency:
        :mod:`~codesign_mb.studies.report_checks`), named with its table file, row and value; a
        sweep table has no numeric ``cfg.metric`` column. Nothing is written then.
    """
    cfg = config or ReportConfig()
    results = ResultsDir(results_dir)
    if not results.names:
        raise ValueError(not_results(results.path))
    sweeps = [n for n in results.names if results.meta(n).get("extra", {}).get("kind") == "sweep"]
    # Every table is checked before anything is drawn: a corrupt one stops the report whole.
    frames: dict[str, pd.DataFrame] = {}
    skipped: dict[str, str] = {}
    for name in REPORT_TABLES:
        frame = collect(results, name)
        problem = "no such table in the results folder" if frame is None else _check(frame, name)
        if problem:
            skipped[name] = problem
            continue
        assert frame is not None
        check_values(frame, name, results, required=REPORT_TABLES[name])
        frames[name] = frame
    for name in sweeps:
        frames[name] = results.table(name)
        check_sweep(name, frames[name], cfg.metric, results)
    out = Path(out_dir) if out_dir is not None else results.path / "report"
    out.mkdir(parents=True, exist_ok=True)
    sections: list[Section] = []
    todo = list(frames)
    for name in progress(todo) if progress is not None else todo:
        if name in REPORT_TABLES:
            sections.append(RENDERERS[name](frames[name], out, cfg))
        else:
            sections.append(render_sweep(name, frames[name], out, cfg))
    markdown = _markdown(results, sections, skipped)
    md_path = out / "report.md"
    with atomic_write(md_path, "w") as fh:
        fh.write(markdown)
    return Report(out_dir=out, markdown=md_path, sections=sections, skipped=skipped)


def _markdown(results: ResultsDir, sections: list[Section], skipped: dict[str, str]) -> str:
    parts = [
        "# codesign_mb report",
        "",
        f"Results folder: `{results.path}`; report by codesign_mb {package_version()} at "
        f"{datetime.now(UTC).isoformat(timespec='seconds')}.",
        "",
    ]
    for section in sections:
        parts += [f"## {section.title}", "", section.markdown.rstrip(), ""]
    if skipped:
        parts += ["## Not rendered", ""]
        parts += [f"- `{name}`: {reason}" for name, reason in skipped.items()]
        parts += [
            "",
            "Table names and columns are documented in `codesign_mb.studies.report`.",
            "",
        ]
    if results.names:
        parts += ["## Provenance", "", "| table | rows | version | created |", "|---|---|---|---|"]
        for name in results.names:
            meta = results.meta(name)
            parts.append(
                f"| `{name}` | {meta.get('n_rows', '')} | {meta.get('version', '')} | "
                f"{meta.get('created', '')} |"
            )
        parts.append("")
    return "\n".join(parts)
