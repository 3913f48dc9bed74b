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
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.core.results import ResultsDir, atomic_write, package_version
from codesign_mb.core.stats import wilson_interval

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

PIPELINE_ALIASES: dict[str, str] = {
    "model-free": "learned",
    "model_free": "learned",
    "model-based": "model_based",
}
"""Other spellings of the two pipelines."""

_NEEDS_SUCCESS = ("tab_p", "fig_cn", "fig_wifi")
_SUCCESS_COLUMNS = ("success", "successes", "success_rate")

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
_PIPELINE_LABEL = {"learned": "learned", "model_based": "model-based"}
_PIPELINE_STYLE = {"learned": "-", "model_based": "--"}


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
        if not (isinstance(self.confidence, float | int) and 0.0 < self.confidence < 1.0):
            raise ValueError(f"confidence must be in (0, 1), got {self.confidence!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        if not isinstance(self.metric, str) or not self.metric:
            raise ValueError(f"metric must be a column name, got {self.metric!r}")


@dataclass(frozen=True)
class Section:
    """One rendered part of the report."""

    name: str
    title: str
    markdown: str
    figure: Path | None = None


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


def labels_of(frame: pd.DataFrame, *, exclude: Sequence[str] = ()) -> list[str]:
    """The :data:`LABEL_COLUMNS` present in ``frame`` (minus ``exclude``), in order."""
    return [c for c in LABEL_COLUMNS if c in frame.columns and c not in exclude]


def success_summary(
    frame: pd.DataFrame, by: Sequence[str], *, confidence: float = 0.95
) -> pd.DataFrame:
    """Success rate with Wilson interval per group, plus the mean of the optional metrics.

    ``frame`` has a per-episode ``success`` column, or ``successes`` and ``trials``, or an
    aggregated ``success_rate`` (with optional ``trials``). Output columns: ``by``,
    ``trials``, ``success_rate``, ``ci_low``, ``ci_high`` and the means of
    ``mean_requested_reliability``,
    ``delivered_fraction``, ``mean_age`` when present.
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
        rows.append(row)
    out = pd.DataFrame(rows).drop(columns="_all", errors="ignore")
    return _sort_pipelines(out) if "pipeline" in out.columns else out


def _sort_pipelines(frame: pd.DataFrame) -> pd.DataFrame:
    order = frame["pipeline"].map(lambda p: _PIPELINE_ORDER.get(p, 9))
    return (
        frame.assign(_order=order)
        .sort_values("_order", kind="stable")
        .drop(columns="_order")
        .reset_index(drop=True)
    )


def _check(frame: pd.DataFrame, name: str) -> str | None:
    """Why ``frame`` cannot be rendered as ``name`` (``None`` if it can)."""
    missing = [c for c in REPORT_TABLES[name] if c not in frame.columns]
    if name in _NEEDS_SUCCESS and not set(_SUCCESS_COLUMNS) & set(frame.columns):
        missing.append("success | successes | success_rate")
    if name == "tab_p" and not labels_of(frame):
        missing.append(" | ".join(LABEL_COLUMNS))
    if missing:
        return f"missing column{'s' if len(missing) > 1 else ''} {', '.join(missing)}"
    if frame.empty:
        return "the table is empty"
    return None


# ----------------------------------------------------------------------------- rendering


def _figure(nrows: int = 1, ncols: int = 1, *, width: float = 5.0, height: float = 3.4) -> Any:
    from matplotlib.figure import Figure  # no pyplot: no global figure state

    fig = Figure(figsize=(width * ncols, height * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def _integer_ticks(ax: Any) -> None:
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def _save(fig: Any, path: Path, dpi: int) -> Path:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, metadata={"Software": None})
    with atomic_write(path, "wb") as fh:
        fh.write(buffer.getvalue())
    return path


def _pct(x: float) -> str:
    return "" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.0f}%"


def _markdown_table(frame: pd.DataFrame, formats: dict[str, Callable[[Any], str]]) -> str:
    columns = list(frame.columns)
    lines = [
        "| " + " | ".join(columns) + " |",
        "|" + "|".join("---" for _ in columns) + "|",
    ]
    for _, row in frame.iterrows():
        cells = [formats.get(c, _default_cell)(row[c]) for c in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _default_cell(value: Any) -> str:
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
        cells["pipeline"] = cells["pipeline"].map(_label)
    if not index:
        cells, index = cells.assign(curve="all"), ["curve"]
    wide = cells.pivot_table(index=index, columns=column, values="cell", aggfunc="first")
    order = pd.MultiIndex.from_frame(cells[index].drop_duplicates())
    wide = wide.reindex(order if len(index) > 1 else order.get_level_values(0)).fillna("")
    wide.columns = [
        f"{prefix}{c:g}" if isinstance(c, float) else f"{prefix}{c}" for c in wide.columns
    ]
    return wide.reset_index()


def _label(pipeline: Any) -> str:
    return _PIPELINE_LABEL.get(str(pipeline), str(pipeline))


def _curve_label(key: dict[str, Any], varying: Sequence[str]) -> str:
    parts = [_label(key[c]) if c == "pipeline" else str(key[c]) for c in varying]
    return ", ".join(parts) if parts else "all"


def _curves(summary: pd.DataFrame, labels: list[str]) -> list[tuple[dict[str, Any], pd.DataFrame]]:
    """Group ``summary`` by ``labels`` (keeping the order of first appearance)."""
    if not labels:
        return [({}, summary)]
    out = []
    for key, group in summary.groupby(labels, sort=False):
        key = key if isinstance(key, tuple) else (key,)
        out.append((dict(zip(labels, key, strict=True)), group))
    return out


def _varying(frame: pd.DataFrame, labels: list[str]) -> list[str]:
    return [c for c in labels if frame[c].nunique(dropna=False) > 1] or labels[:1]


class _Styler:
    """Colour per curve (ignoring the pipeline), line style per pipeline."""

    def __init__(self, labels: list[str]) -> None:
        self.keys = [c for c in labels if c != "pipeline"]
        self.colors: dict[tuple[Any, ...], str] = {}

    def __call__(self, key: dict[str, Any]) -> tuple[str, str]:
        ident = tuple(key.get(c) for c in self.keys)
        color = self.colors.setdefault(ident, f"C{len(self.colors) % 10}")
        return color, _PIPELINE_STYLE.get(str(key.get("pipeline")), "-")


def _render_tab_p(frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    labels = labels_of(frame)
    summary = success_summary(frame, labels, confidence=cfg.confidence)
    shown = summary[labels].copy()
    if "pipeline" in shown.columns:
        shown["pipeline"] = shown["pipeline"].map(_label)
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
    has_pdr = "mean_requested_reliability" in summary.columns
    if has_pdr:
        shown["average PDR"] = summary["mean_requested_reliability"].map(_pct)
    fig, axes = _figure(width=6.0, height=4.2)
    ax = axes[0, 0]
    markers = {"learned": "o", "model_based": "s"}
    varying = _varying(summary, labels)
    if has_pdr:
        for _, row in summary.iterrows():
            x, y = row["mean_requested_reliability"], row["success_rate"]
            yerr = [[y - row["ci_low"]], [row["ci_high"] - y]] if row["trials"] else None
            ax.errorbar(
                x,
                y,
                yerr=yerr,
                fmt=markers.get(str(row.get("pipeline")), "^"),
                capsize=3,
                label=_curve_label(row.to_dict(), varying),
            )
        ax.scatter(
            PAPER_TAB_P["mean_requested_reliability"],
            PAPER_TAB_P["success_rate"],
            marker="x",
            color="black",
            label="paper, Table I",
        )
        ax.set_xlabel("average PDR (mean requested reliability q)")
        ax.set_xlim(-0.02, 1.05)
    else:
        names = [_curve_label(r.to_dict(), varying) for _, r in summary.iterrows()]
        ax.bar(range(len(summary)), summary["success_rate"])
        ax.set_xticks(range(len(summary)), names, rotation=20, ha="right", fontsize=7)
    ax.set_ylabel("success rate")
    ax.set_ylim(-0.02, 1.05)
    ax.grid(alpha=0.3)
    if has_pdr:
        ax.legend(fontsize=7, loc="lower right")
    ax.set_title("Table I: success versus network use")
    figure = _save(fig, out / "tab_p.png", cfg.dpi)
    paper = PAPER_TAB_P.assign(
        **{
            "success rate": PAPER_TAB_P["success_rate"].map(_pct),
            "average PDR": PAPER_TAB_P["mean_requested_reliability"].map(_pct),
        }
    )[["policy", "success rate", "average PDR"]]
    text = (
        f"Success rate ({cfg.confidence:.0%} Wilson interval) and average PDR (mean requested "
        "reliability) per policy.\n\n"
        + _markdown_table(shown, {})
        + "\n\nThe paper's Table I (learned pipeline, 100 trials each):\n\n"
        + _markdown_table(paper, {})
        + f"\n\n![Table I](./{figure.name})\n"
    )
    return Section("tab_p", "Table I: policies compared (tab_p)", text, figure)


def _render_fig_cn(frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    if "belt_speed_mps" not in frame.columns:
        frame = frame.assign(belt_speed_mps=-1.0)  # one panel, no title
    labels = labels_of(frame)
    rows: list[tuple[str, str, pd.DataFrame]] = []
    if "sweep" in frame.columns:
        by_latency = frame[frame["sweep"].astype(str) != "reliability"]
        by_reliability = frame[frame["sweep"].astype(str) == "reliability"]
        if "reliability" in frame.columns and not by_reliability.empty:
            rows = [("latency_steps", "tau=", by_latency), ("reliability", "q=", by_reliability)]
        else:
            rows = [("latency_steps", "tau=", by_latency)]
    else:
        rows = [("latency_steps", "tau=", frame)]
    rows = [r for r in rows if not r[2].empty]
    speeds = sorted(frame["belt_speed_mps"].unique())
    fig, axes = _figure(len(rows), len(speeds), width=4.6, height=3.2)
    styler = _Styler(labels)
    tables = []
    for i, (x_col, prefix, data) in enumerate(rows):
        summary = success_summary(
            data, [*labels, "belt_speed_mps", x_col], confidence=cfg.confidence
        )
        varying = _varying(summary, labels) if labels else []
        for j, speed in enumerate(speeds):
            ax = axes[i, j]
            at_speed = summary[summary["belt_speed_mps"] == speed]
            for key, line in _curves(at_speed, labels):
                line = line.sort_values(x_col)
                x = line[x_col].to_numpy(float)
                color, style = styler(key)
                ax.plot(
                    x,
                    line["success_rate"],
                    style,
                    marker="o",
                    color=color,
                    label=_curve_label(key, varying),
                )
                if line["trials"].gt(0).all():
                    ax.fill_between(x, line["ci_low"], line["ci_high"], color=color, alpha=0.12)
            ax.set_title(f"belt speed {speed:g} m/s" if speed >= 0 else "")
            ax.set_ylim(-0.02, 1.05)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
            if x_col == "latency_steps":
                _integer_ticks(ax)
                ax.set_xlabel("latency tau (control periods of 40 ms)")
            else:
                ax.set_xlabel("reliability q (latency fixed)")
            if j == 0:
                ax.set_ylabel("success rate")
        index = [*labels, "belt_speed_mps"] if len(speeds) > 1 else labels
        tables.append(_pivot(summary, index, x_col, prefix))
    figure = _save(fig, out / "fig_cn.png", cfg.dpi)
    text = (
        "Success rate (trials) versus latency tau in control periods"
        + (" (and versus reliability q)" if len(rows) > 1 else "")
        + ", per estimator (solid: learned, dashed: model-based), one panel per belt speed.\n\n"
        + f"![Fig. 4](./{figure.name})\n\n"
        + "\n\n".join(_markdown_table(t, {}) for t in tables)
        + "\n"
    )
    return Section("fig_cn", "Fig. 4: estimators under latency (fig_cn)", text, figure)


def _render_fig_lat(frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    labels = labels_of(frame)
    if "pipeline" in frame.columns:
        frame = _sort_pipelines(frame)
    panels = _curves(frame, labels)
    fig, axes = _figure(len(panels), 1, width=7.0, height=2.6)
    rng = np.random.default_rng(cfg.seed)
    lines = []
    for ax, (key, data) in zip(axes[:, 0], panels, strict=True):
        name = _curve_label(key, labels)
        episode_note = ""
        if "episode" in data.columns and data["episode"].nunique() > 1:
            episodes = list(dict.fromkeys(data["episode"]))
            if "success" in data.columns:
                won = data.groupby("episode", sort=False)["success"].any()
                episodes = [e for e in episodes if won.get(e, False)] or episodes
            chosen = episodes[int(rng.integers(len(episodes)))]
            data = data[data["episode"] == chosen]
            episode_note = f", episode {chosen}"
        data = data.sort_values("t")
        t = data["t"].to_numpy()
        q = data["qos_reliability"].to_numpy(float)
        ax.step(t, q, where="post", label="requested reliability q_t")
        if "delivered" in data.columns:
            hit = data["delivered"].astype(bool).to_numpy()
            ax.plot(t[hit], np.full(int(hit.sum()), 1.0), "|", ms=8, color="C2", label="delivered")
        if "lifted" in data.columns and data["lifted"].astype(bool).any():
            first = t[data["lifted"].astype(bool).to_numpy()][0]
            ax.axvline(first, color="C3", linestyle="--", label=f"lifted at t = {first}")
        mean_q = float(np.mean(q))
        ax.set_title(f"{name}{episode_note}: average PDR {_pct(mean_q)}")
        ax.set_ylabel("q")
        ax.set_ylim(-0.02, 1.08)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
        lines.append(f"- {name}{episode_note}: average PDR {_pct(mean_q)}")
    axes[-1, 0].set_xlabel("step t (40 ms)")
    figure = _save(fig, out / "fig_lat.png", cfg.dpi)
    text = (
        "Requested reliability over one episode (a successful one when the table holds "
        "several).\n\n" + "\n".join(lines) + f"\n\n![Fig. 5](./{figure.name})\n"
    )
    return Section("fig_lat", "Fig. 5: QoS adaptation over an episode (fig_lat)", text, figure)


def _render_fig_wifi(frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    labels = labels_of(frame)
    summary = success_summary(frame, [*labels, "n_robots"], confidence=cfg.confidence)
    second = "delivered_fraction" if "delivered_fraction" in summary.columns else None
    fig, axes = _figure(1, 2 if second else 1, width=5.0, height=3.6)
    styler = _Styler(labels)
    varying = _varying(summary, labels) if labels else []
    for key, line in _curves(summary, labels):
        line = line.sort_values("n_robots")
        x = line["n_robots"].to_numpy(float)
        color, style = styler(key)
        label = _curve_label(key, varying)
        axes[0, 0].plot(x, line["success_rate"], style, marker="o", color=color, label=label)
        if line["trials"].gt(0).all():
            axes[0, 0].fill_between(x, line["ci_low"], line["ci_high"], color=color, alpha=0.12)
        if second:
            axes[0, 1].plot(x, line[second], style, marker="o", color=color, label=label)
    axes[0, 0].set_ylabel("success rate")
    axes[0, 0].set_title("task success in a WiFi 6 cell")
    if second:
        axes[0, 1].set_ylabel("delivered fraction")
        axes[0, 1].set_title("state packets delivered")
    for ax in axes[0]:
        ax.set_xlabel("robots sharing the channel")
        _integer_ticks(ax)
        ax.set_ylim(-0.02, 1.05)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    figure = _save(fig, out / "fig_wifi.png", cfg.dpi)
    table = _pivot(summary, labels, "n_robots", "N=")
    text = (
        "Success rate versus the number of robots N, with and without control-aware QoS "
        "adaptation (solid: learned, dashed: model-based).\n\n"
        f"![Fig. 6](./{figure.name})\n\n" + _markdown_table(table, {}) + "\n"
    )
    return Section("fig_wifi", "Fig. 6: robots sharing WiFi 6 (fig_wifi)", text, figure)


def _render_sweep(name: str, frame: pd.DataFrame, out: Path, cfg: ReportConfig) -> Section:
    metric = cfg.metric
    if metric not in frame.columns:
        raise ValueError(f"sweep table {name!r} has no column {metric!r}")
    by = ["pipeline", "belt_speed_mps", "n_robots"]
    grouped = frame.groupby(by, sort=False)[metric]
    summary = grouped.agg(["mean", "std", "count"]).reset_index()
    summary["sem"] = summary["std"].fillna(0.0) / np.sqrt(summary["count"])
    speeds = sorted(summary["belt_speed_mps"].unique())
    fig, axes = _figure(1, len(speeds), width=4.2, height=3.4)
    for ax, speed in zip(axes[0], speeds, strict=True):
        at_speed = summary[summary["belt_speed_mps"] == speed]
        for i, (pipeline, line) in enumerate(at_speed.groupby("pipeline", sort=False)):
            line = line.sort_values("n_robots")
            ax.errorbar(
                line["n_robots"],
                line["mean"],
                yerr=line["sem"],
                marker="o",
                capsize=3,
                color=f"C{i}",
                label=str(pipeline),
            )
        ax.set_title(f"belt speed {speed:g} m/s")
        ax.set_xlabel("robots")
        _integer_ticks(ax)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0, 0].set_ylabel(f"{metric} (mean +- s.e. over seeds)")
    figure = _save(fig, out / f"{name}.png", cfg.dpi)
    table = summary[[*by, "count", "mean", "sem"]].rename(
        columns={"count": "seeds", "mean": metric, "sem": "s.e."}
    )
    text = (
        f"Sweep `{name}`: `{metric}` averaged over seeds.\n\n![{name}](./{figure.name})\n\n"
        + _markdown_table(table, {})
        + "\n"
    )
    return Section(name, f"Sweep {name}", text, figure)


_RENDERERS: dict[str, Callable[[pd.DataFrame, Path, ReportConfig], Section]] = {
    "tab_p": _render_tab_p,
    "fig_cn": _render_fig_cn,
    "fig_lat": _render_fig_lat,
    "fig_wifi": _render_fig_wifi,
}


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
        The sections rendered and the tables skipped, with the reason.
    """
    cfg = config or ReportConfig()
    results = ResultsDir(results_dir)
    out = Path(out_dir) if out_dir is not None else results.path / "report"
    out.mkdir(parents=True, exist_ok=True)
    sweeps = [n for n in results.names if results.meta(n).get("extra", {}).get("kind") == "sweep"]
    todo = [*REPORT_TABLES, *sweeps]
    sections: list[Section] = []
    skipped: dict[str, str] = {}
    for name in progress(todo) if progress is not None else todo:
        if name in REPORT_TABLES:
            frame = collect(results, name)
            if frame is None:
                skipped[name] = "no such table in the results folder"
                continue
            problem = _check(frame, name)
            if problem:
                skipped[name] = problem
                continue
            sections.append(_RENDERERS[name](frame, out, cfg))
        else:
            try:
                sections.append(_render_sweep(name, results.table(name), out, cfg))
            except (KeyError, ValueError) as exc:
                skipped[name] = str(exc)
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
