"""The sections of ``codesign report``: one per known table, drawn by its study's renderer.

Each ``_render_<name>`` turns a results folder's table (see :mod:`codesign_mb.studies.report`
for names and columns) into the input of the one renderer of its figure, calls it and writes
the Markdown of its section: :func:`~codesign_mb.studies.table_pareto_plot.plot_pareto`
(Table I, with the paper's figures as crosses), :func:`~codesign_mb.studies.fig_cn.plot_fig_cn`,
:func:`~codesign_mb.studies.table_figures.plot_timeline` (Fig. 5),
:func:`~codesign_mb.studies.fig_wifi_figures.plot_capacity` (Fig. 6) and
:func:`~codesign_mb.studies.sweep_figures.plot_sweep`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.core.config import SEED_CAP, Cap, check_range
from codesign_mb.core.stats import wilson_interval
from codesign_mb.studies import (
    fig_cn,
    fig_wifi_figures,
    sweep_figures,
    table_figures,
    table_pareto_plot,
)
from codesign_mb.studies.figures import curve_label, curves, pipeline_label, varying
from codesign_mb.studies.table_select import pareto_front

__all__ = [
    "LABEL_COLUMNS",
    "PAPER_TAB_P",
    "RENDERERS",
    "ReportConfig",
    "Section",
    "labels_of",
    "render_sweep",
    "sort_pipelines",
    "success_summary",
]

LABEL_COLUMNS: tuple[str, ...] = (
    "pipeline",
    "policy",
    "row",
    "controller",
    "estimator",
    "qos_policy",
    "qos",
    "scheduler",
    "allocator",
    "channel",
    "plant",
)
"""Columns identifying a curve or a table row, in display order."""


PAPER_TAB_P = pd.DataFrame(
    {
        "policy": [
            "MLP state est., static QoS",
            "No state est., dynamic QoS",
            "MLP state est., dynamic QoS",
        ],
        "success_rate": [1.00, 0.78, 0.98],
        "mean_requested_reliability": [1.00, 0.52, 0.13],
    }
)
"""The paper's Table I (100 trials each), shown for reference."""

_PIPELINE_ORDER = {"learned": 0, "model_based": 1}


DPI_CAP = Cap(1_200, "dots per inch of a figure")


@dataclass(frozen=True)
class ReportConfig:
    """Settings of ``codesign report`` (config file table ``[report]`` or top level).

    Attributes
    ----------
    dpi:
        Resolution of the PNG figures (dots per inch).
    confidence:
        Confidence level of the Wilson intervals on success rates, in (0, 1).
    seed:
        Picks the representative episode of ``fig_lat`` among the successful ones.
    metric:
        Column of sweep tables to plot (default ``success_rate``).
    """

    dpi: int = 120
    confidence: float = 0.95
    seed: int = 0
    metric: str = "success_rate"

    def __post_init__(self) -> None:
        if isinstance(self.dpi, bool) or not isinstance(self.dpi, int) or not self.dpi >= 20:
            raise ValueError(f"dpi must be an integer >= 20, got {self.dpi!r}")
        check_range("dpi", self.dpi, cap=DPI_CAP)
        if not (isinstance(self.confidence, float | int) and 0.0 < self.confidence < 1.0):
            raise ValueError(f"confidence must be in (0, 1), got {self.confidence!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        check_range("seed", self.seed, cap=SEED_CAP)
        if not isinstance(self.metric, str) or not self.metric:
            raise ValueError(f"metric must be a column name, got {self.metric!r}")


@dataclass(frozen=True)
class Section:
    """One rendered part of the report."""

    name: str
    title: str
    markdown: str
    figure: Path | None = None


# ----------------------------------------------------------------------------- data


def labels_of(frame: pd.DataFrame, *, exclude: Sequence[str] = ()) -> list[str]:
    """The :data:`LABEL_COLUMNS` present in ``frame`` (minus ``exclude``), in order."""
    return [c for c in LABEL_COLUMNS if c in frame.columns and c not in exclude]


def success_summary(
    frame: pd.DataFrame, by: Sequence[str], *, confidence: float = 0.95
) -> pd.DataFrame:
    """Success rate with Wilson interval per group, plus the mean of the optional metrics.

    ``frame`` has a per-episode ``success`` column, or ``successes`` and ``trials``, or an
    aggregated ``success_rate`` (with optional ``trials``). Output columns: ``by``,
    ``trials``, ``success_rate``, ``ci_low``, ``ci_high``, the means of
    ``mean_requested_reliability``, ``delivered_fraction``, ``mean_age`` and the sum of
    ``mpc_failures`` (NaN where no row of the group has one) when present.
    """
    by = list(by)
    if not by:
        frame, by = frame.assign(_all="all"), ["_all"]
    extra = [
        c
        for c in ("mean_requested_reliability", "delivered_fraction", "mean_age")
        if c in frame.columns
    ]
    rows = []
    for key, group in frame.groupby(by, sort=False, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        row: dict[str, Any] = dict(zip(by, key, strict=True))
        if "success" in group.columns:
            success = group["success"].astype(bool)
            n, k = int(success.size), int(success.sum())
            rate = k / n
        elif "successes" in group.columns and "trials" in group.columns:
            n, k = int(group["trials"].sum()), int(group["successes"].sum())
            rate = k / n if n else math.nan
        else:
            trials = group["trials"] if "trials" in group.columns else None
            if trials is not None:
                n = int(trials.sum())
                rate = float((group["success_rate"] * trials).sum() / max(n, 1))
            else:
                n = 0
                rate = float(group["success_rate"].mean())
            k = round(rate * n)
        low, high = wilson_interval(k, n, confidence) if n else (math.nan, math.nan)
        row.update(trials=n, success_rate=rate, ci_low=low, ci_high=high)
        for c in extra:
            row[c] = float(group[c].astype(float).mean())
        if "mpc_failures" in group.columns:
            row["mpc_failures"] = float(group["mpc_failures"].astype(float).sum(min_count=1))
        rows.append(row)
    out = pd.DataFrame(rows).drop(columns="_all", errors="ignore")
    return sort_pipelines(out) if "pipeline" in out.columns else out


def sort_pipelines(frame: pd.DataFrame) -> pd.DataFrame:
    """The learned pipeline's rows first, then the model-based ones, then the others."""
    order = frame["pipeline"].map(lambda p: _PIPELINE_ORDER.get(p, 9))
    return (
        frame.assign(_order=order)
        .sort_values("_order", kind="stable")
        .drop(columns="_order")
        .reset_index(drop=True)
    )


# ----------------------------------------------------------------------------- sections


def _pct(x: float) -> str:
    return "" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.0f}%"


def _markdown_table(frame: pd.DataFrame) -> str:
    columns = list(frame.columns)
    lines = [
        "| " + " | ".join(columns) + " |",
        "|" + "|".join("---" for _ in columns) + "|",
    ]
    for _, row in frame.iterrows():
        lines.append("| " + " | ".join(_cell(row[c]) for c in columns) + " |")
    return "\n".join(lines)


def _cell(value: Any) -> str:
    if isinstance(value, float | np.floating):
        return "" if math.isnan(value) else f"{value:.4g}"
    return str(value)


def _pivot(summary: pd.DataFrame, index: list[str], column: str, prefix: str) -> pd.DataFrame:
    """Success rates as a compact table: one row per ``index``, one column per ``column``."""
    cells = summary.assign(
        cell=[
            f"{_pct(r)} ({n})" if n else _pct(r)
            for r, n in zip(summary["success_rate"], summary["trials"], strict=True)
        ],
    )
    if "pipeline" in cells.columns:
        cells["pipeline"] = cells["pipeline"].map(pipeline_label)
    if not index:
        cells, index = cells.assign(curve="all"), ["curve"]
    wide = cells.pivot_table(index=index, columns=column, values="cell", aggfunc="first")
    order = pd.MultiIndex.from_frame(cells[index].drop_duplicates())
    wide = wide.reindex(order if len(index) > 1 else order.get_level_values(0)).fillna("")
    wide.columns = [
        f"{prefix}{c:g}" if isinstance(c, float) else f"{prefix}{c}" for c in wide.columns
    ]
    return wide.reset_index()


def _failures(summary: pd.DataFrame, labels: list[str]) -> str:
    """A sentence with the failed MPC solves per curve, or ``""`` when no curve has an MPC."""
    if "mpc_failures" not in summary.columns or not summary["mpc_failures"].notna().any():
        return ""
    shown = varying(summary, labels) if labels else []
    parts = []
    for key, rows in curves(summary, labels):
        count = rows["mpc_failures"].astype(float).sum(min_count=1)
        if np.isfinite(count):
            parts.append(f"{curve_label(key, shown)}: {int(count)}")
    return "Failed MPC solves (summed over the episodes): " + "; ".join(parts) + ".\n\n"


def _rename_ci(summary: pd.DataFrame) -> pd.DataFrame:
    return summary.rename(columns={"ci_low": "success_ci_low", "ci_high": "success_ci_high"})


def _render_tab_p(frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    labels = labels_of(frame)
    summary = success_summary(frame, labels, confidence=cfg.confidence)
    if "kind" in frame.columns and "row" in labels:  # reference rows: blind, oracle, ...
        summary["kind"] = summary["row"].map(frame.drop_duplicates("row").set_index("row")["kind"])
    shown = summary[labels].copy()
    if "pipeline" in shown.columns:
        shown["pipeline"] = shown["pipeline"].map(pipeline_label)
    shown["trials"] = summary["trials"]
    shown["success rate"] = [
        f"{_pct(r)} [{_pct(lo)}, {_pct(hi)}]" if n else _pct(r)
        for r, lo, hi, n in zip(
            summary["success_rate"],
            summary["ci_low"],
            summary["ci_high"],
            summary["trials"],
            strict=True,
        )
    ]
    if "mean_requested_reliability" in summary.columns:
        shown["average PDR"] = summary["mean_requested_reliability"].map(_pct)
    if "mpc_failures" in summary.columns and summary["mpc_failures"].notna().any():
        shown["MPC failures"] = [
            "" if math.isnan(v) else str(int(v)) for v in summary["mpc_failures"].astype(float)
        ]
    figure = table_pareto_plot.plot_pareto(
        _tab_p_points(summary, labels),
        out / "tab_p.png",
        title="Table I: success versus network use",
        reference=PAPER_TAB_P,
        reference_label="paper, Table I",
        dpi=cfg.dpi,
    )
    paper = PAPER_TAB_P.assign(
        **{
            "success rate": PAPER_TAB_P["success_rate"].map(_pct),
            "average PDR": PAPER_TAB_P["mean_requested_reliability"].map(_pct),
        }
    )[["policy", "success rate", "average PDR"]]
    text = (
        f"Success rate ({cfg.confidence:.0%} Wilson interval) and average PDR (mean requested "
        "reliability) per policy.\n\n"
        + _markdown_table(shown)
        + "\n\nThe paper's Table I (learned pipeline, 100 trials each):\n\n"
        + _markdown_table(paper)
        + f"\n\n![Table I](./{figure.name})\n"
    )
    return Section("tab_p", "Table I: policies compared (tab_p)", text, figure)


def _tab_p_points(summary: pd.DataFrame, labels: list[str]) -> pd.DataFrame:
    """The summary as :func:`~codesign_mb.studies.table_pareto_plot.plot_pareto`'s input."""
    keys = [c for c in labels if c != "plant"]
    shown = varying(summary, keys) if keys else []
    points = _rename_ci(summary).assign(
        row=[curve_label(key, shown) for key in summary[keys].to_dict("records")],
        plant=summary["plant"] if "plant" in labels else "",
    )
    if "mean_requested_reliability" not in points.columns:
        points["mean_requested_reliability"] = math.nan
    # Reference rows (blind, oracle, static, random) are drawn as such, never on the front.
    points["kind"] = summary["kind"].astype(str) if "kind" in summary.columns else "row"
    points["pareto"] = False
    for plant in points["plant"].unique():
        mask = ((points["plant"] == plant) & (points["kind"] == "row")).to_numpy()
        points.loc[mask, "pareto"] = pareto_front(
            points.loc[mask, "success_rate"], points.loc[mask, "mean_requested_reliability"]
        )
    return points


def _render_fig_cn(frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    if "belt_speed_mps" not in frame.columns:
        frame = frame.assign(belt_speed_mps=-1.0)  # one panel, no title
    labels = labels_of(frame)
    sweep = frame["sweep"].astype(str) if "sweep" in frame.columns else None
    parts = [
        (
            "delay",
            "latency_steps",
            "tau=",
            frame if sweep is None else frame[sweep != "reliability"],
        )
    ]
    if sweep is not None and "reliability" in frame.columns:
        parts.append(("reliability", "reliability", "q=", frame[sweep == "reliability"]))
    summaries, tables = [], []
    speeds = frame["belt_speed_mps"].nunique()
    for name, x_col, prefix, data in parts:
        if data.empty:
            continue
        by = [*labels, "belt_speed_mps", x_col]
        summary = success_summary(data, by, confidence=cfg.confidence).assign(sweep=name)
        summaries.append(summary)
        index = [*labels, "belt_speed_mps"] if speeds > 1 else labels
        tables.append(_pivot(summary, index, x_col, prefix))
    points = _rename_ci(pd.concat(summaries, ignore_index=True))
    figure = fig_cn.plot_fig_cn(points, out / "fig_cn.png", labels=labels, dpi=cfg.dpi)
    text = (
        "Success rate (trials) versus latency tau in control periods"
        + (" (and versus reliability q)" if len(tables) > 1 else "")
        + ", per estimator (solid: learned, dashed: model-based), one panel per belt speed.\n\n"
        + f"![Fig. 4](./{figure.name})\n\n"
        + _failures(points, labels)
        + "\n\n".join(_markdown_table(t) for t in tables)
        + "\n"
    )
    return Section("fig_cn", "Fig. 4: estimators under latency (fig_cn)", text, figure)


def _render_fig_lat(frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    labels = labels_of(frame)
    if "pipeline" in frame.columns:
        frame = sort_pipelines(frame)
    rng = np.random.default_rng(cfg.seed)
    panels, lines = [], []
    for key, data in curves(frame, labels):
        name = curve_label(key, labels)
        episode_note = ""
        if "episode" in data.columns and data["episode"].nunique() > 1:
            episodes = list(dict.fromkeys(data["episode"]))
            if "success" in data.columns:
                won = data.groupby("episode", sort=False)["success"].any()
                episodes = [e for e in episodes if won.get(e, False)] or episodes
            chosen = episodes[int(rng.integers(len(episodes)))]
            data = data[data["episode"] == chosen]
            episode_note = f", episode {chosen}"
        panels.append((f"{name}{episode_note}", data))
        mean_q = float(data["qos_reliability"].astype(float).mean())
        lines.append(f"- {name}{episode_note}: average PDR {_pct(mean_q)}")
    figure = table_figures.plot_timeline(panels, out / "fig_lat.png", dpi=cfg.dpi)
    text = (
        "Requested reliability over one episode (a successful one when the table holds "
        "several).\n\n" + "\n".join(lines) + f"\n\n![Fig. 5](./{figure.name})\n"
    )
    return Section("fig_lat", "Fig. 5: QoS adaptation over an episode (fig_lat)", text, figure)


def _render_fig_wifi(frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    labels = labels_of(frame)
    pooled = "successes" in frame.columns and "trials" not in frame.columns
    if pooled:  # ``codesign wifi capacity``'s trials: a trial counts N robot-episodes
        frame = frame.assign(trials=frame["n_robots"])
    summary = success_summary(frame, [*labels, "n_robots"], confidence=cfg.confidence)
    figure = fig_wifi_figures.plot_capacity(
        _capacity_points(summary, labels), out / "fig_wifi.png", dpi=cfg.dpi
    )
    table = _pivot(summary, labels, "n_robots", "N=")
    text = (
        "Success rate versus the number of robots N, with and without control-aware QoS "
        "adaptation."
        + (
            " A point pools its trials' robot-episodes (their number in brackets); the band is "
            f"its {cfg.confidence:.0%} Wilson interval."
            if pooled
            else ""
        )
        + "\n\n"
        f"![Fig. 6](./{figure.name})\n\n"
        + _failures(summary, labels)
        + _markdown_table(table)
        + "\n"
    )
    return Section("fig_wifi", "Fig. 6: robots sharing WiFi 6 (fig_wifi)", text, figure)


def _capacity_points(summary: pd.DataFrame, labels: list[str]) -> pd.DataFrame:
    """The summary as :func:`~codesign_mb.studies.fig_wifi_figures.plot_capacity`'s input.

    One panel per ``channel``, one line style per ``scheduler``; the other labels name the
    curve (its colour); the band is the Wilson interval.
    """
    keys = [c for c in labels if c not in ("channel", "scheduler")]
    shown = varying(summary, keys) if keys else []
    return pd.DataFrame(
        {
            "channel": summary["channel"].astype(str) if "channel" in labels else "",
            "scheduler": summary["scheduler"].astype(str) if "scheduler" in labels else "",
            "pipeline": [curve_label(k, shown) for k in summary[keys].to_dict("records")],
            "robots": summary["n_robots"],
            "success_rate": summary["success_rate"],
            "band_low": summary["ci_low"],
            "band_high": summary["ci_high"],
            "mean_reliability": summary.get("mean_requested_reliability", math.nan),
            "delivered_fraction": summary.get("delivered_fraction", math.nan),
        }
    )


def render_sweep(name: str, frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    """The section of the sweep table ``name``: ``cfg.metric`` versus the robot count."""
    try:
        summary = sweep_figures.sweep_summary(frame, cfg.metric)
    except ValueError:
        raise ValueError(f"sweep table {name!r} has no column {cfg.metric!r}") from None
    figure = sweep_figures.plot_sweep(summary, out / f"{name}.png", metric=cfg.metric, dpi=cfg.dpi)
    table = summary[["pipeline", "belt_speed_mps", "n_robots", "count", "mean", "sem"]].rename(
        columns={"count": "seeds", "mean": cfg.metric, "sem": "s.e."}
    )
    text = (
        f"Sweep `{name}`: `{cfg.metric}` averaged over seeds.\n\n![{name}](./{figure.name})\n\n"
        + _markdown_table(table)
        + "\n"
    )
    return Section(name, f"Sweep {name}", text, figure)


RENDERERS: dict[str, Callable[[pd.DataFrame, Path, ReportConfig], Section]] = {
    "tab_p": _render_tab_p,
    "fig_cn": _render_fig_cn,
    "fig_lat": _render_fig_lat,
    "fig_wifi": _render_fig_wifi,
}
"""Known table name -> its section (figure and Markdown)."""
