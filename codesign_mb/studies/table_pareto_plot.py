"""Table I's Pareto plot: success versus average requested reliability, one panel per plant.

:func:`plot_pareto` is the figure's one renderer: ``codesign table`` draws it from
:func:`~codesign_mb.studies.table.run_table`'s summary
(:func:`~codesign_mb.studies.table_figures.write_table_outputs`) and ``codesign report`` from
whatever ``tab_p`` table a results folder holds. It is kept apart from the table's other
outputs (:mod:`codesign_mb.studies.table_figures`: Fig. 5, the Markdown table, the files), with
the point styles and legend only it uses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.studies.figures import new_figure, save_png
from codesign_mb.studies.table_refs import ROW_KIND, draw_references, reference_legend

__all__ = ["plot_pareto"]

_QOS_COLOURS = {"static": "tab:blue", "rule": "tab:green", "learned": "tab:red"}
_SPARE_COLOURS = ("tab:purple", "tab:orange", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
_PAIR_MARKERS = {
    ("sac", "mlp"): "o",
    ("sac", "lstm"): "o",
    ("sac", "none"): "v",
    ("mpc", "predictor"): "s",
    ("mpc", "none"): "D",
    ("sac", "predictor"): "^",
    ("mpc", "mlp"): "P",
    ("mpc", "lstm"): "P",
    ("learned",): "o",
    ("model_based",): "s",
}
_SPARE_MARKERS = ("X", "*", "h", "<", ">", "p", "d")


class _PointStyle:
    """Marker per controller and estimator (else pipeline, else row), colour per QoS (else row)."""

    def __init__(self, columns: Sequence[str]) -> None:
        if "controller" in columns and "estimator" in columns:
            self.pair: tuple[str, ...] = ("controller", "estimator")
        else:
            self.pair = ("pipeline",) if "pipeline" in columns else ("row",)
        self.colour_by = "qos" if "qos" in columns else "row"
        self.markers = dict(_PAIR_MARKERS)
        self.colours = dict(_QOS_COLOURS)
        self.handles: dict[str, Any] = {}
        self.reference_kinds: set[str] = set()
        self.stack_greys: dict[tuple[str, ...], str] = {}

    def __call__(self, r: pd.Series) -> tuple[str, str]:
        from matplotlib.lines import Line2D

        pair = tuple(str(r[c]) for c in self.pair)
        if pair not in self.markers:
            self.markers[pair] = _SPARE_MARKERS[len(self.markers) % len(_SPARE_MARKERS)]
        key = str(r[self.colour_by])
        if key not in self.colours:
            spare = len(self.colours) - len(_QOS_COLOURS)
            self.colours[key] = _SPARE_COLOURS[spare] if spare < len(_SPARE_COLOURS) else "tab:gray"
        marker, colour = self.markers[pair], self.colours[key]
        self.handles.setdefault(
            str(r["row"]), Line2D([], [], ls="", marker=marker, color=colour, mfc="white")
        )
        return marker, colour


def plot_pareto(
    summary: pd.DataFrame,
    path: str | Path,
    *,
    title: str = "",
    reference: pd.DataFrame | None = None,
    reference_label: str = "paper",
    dpi: int = 120,
) -> Path:
    """Success versus average requested reliability, one panel per plant (PNG).

    Every evaluated row is a point with its 95 % Wilson interval: the colour is its QoS policy
    (static blue, rule green, SAC red), the marker its controller and estimator (the same in
    every panel); the Pareto-optimal ones (column ``pareto``) are ringed and joined by the
    front (dashed).

    ``summary`` has :func:`~codesign_mb.studies.table.run_table`'s columns ``row``,
    ``success_rate``, ``success_ci_low``, ``success_ci_high``, ``mean_requested_reliability``
    and ``pareto``; optional: ``plant`` (one panel each), ``status`` (rows not ``"ok"`` are
    counted in the panel's title), ``kind`` (reference rows), ``controller`` and
    ``estimator`` (the marker; else
    ``pipeline``, else the row), ``qos`` (the colour; else the row). ``reference`` points
    (columns ``success_rate`` and ``mean_requested_reliability``, e.g. the paper's Table I)
    are black crosses in every panel.

    Reference rows (column ``kind`` other than ``"row"``,
    :mod:`~codesign_mb.studies.table_refs`) are grey: ``blind`` a down triangle, ``oracle``
    a star, ``static`` a hollow diamond, ``random`` a cross; per stack (controller and
    estimator) a dotted line runs from ``blind`` through the ``random`` points (at their
    ``p``) to ``static``: what sending at random gives for each budget, the line a co-design
    row has to beat. They are never on the front.
    """
    from matplotlib.lines import Line2D

    summary = summary.assign(
        plant=summary.get("plant", ""),
        status=summary.get("status", "ok"),
        kind=summary.get("kind", ROW_KIND),
    )
    plants = list(dict.fromkeys(summary["plant"])) or [""]
    style = _PointStyle(list(summary.columns))
    fig, axes = new_figure(1, len(plants), width=4.6, height=4.6, sharey=True)
    for ax, plant in zip(axes[0], plants, strict=True):
        _pareto_panel(ax, summary[summary["plant"] == plant], style, plant)
        if reference is not None:
            ax.plot(
                reference["mean_requested_reliability"],
                reference["success_rate"],
                "x",
                color="black",
            )
    if reference is not None:
        style.handles[reference_label] = Line2D([], [], ls="", marker="x", color="black")
    axes[0, 0].set_ylabel("success rate (95 % Wilson interval)")
    ring = Line2D([], [], ls="", marker="o", ms=10, mfc="none", mec="black")
    handles = {**style.handles, **reference_legend(style.reference_kinds, style.stack_greys)}
    entries = len(handles) + 1
    ncols = min(4, 2 * len(plants), entries) if len(plants) > 1 else 1 if entries <= 12 else 2
    # The legend goes below the panels: grow the figure by its height (and, for one panel
    # with two columns, its width) so that the panels keep their size.
    width = 4.6 * len(plants) if len(plants) > 1 else max(4.6, 3.3 * ncols)
    fig.set_size_inches(width, 4.6 + 0.16 * math.ceil(entries / ncols))
    fig.legend(
        [*handles.values(), ring],
        [*handles.keys(), "Pareto-optimal (filled and ringed; dashed: the front)"],
        loc="outside lower center",
        ncols=ncols,
        fontsize=7,
    )
    if title:
        fig.suptitle(title, fontsize=10)
    return save_png(fig, path, dpi=dpi)


def _pareto_panel(ax: Any, rows: pd.DataFrame, style: _PointStyle, plant: str) -> None:
    ok = rows[rows["status"] == "ok"]
    draw_references(ax, ok[ok["kind"] != ROW_KIND], style.stack_greys, style.reference_kinds)
    ok = ok[ok["kind"] == ROW_KIND]
    x_all = ok["mean_requested_reliability"].astype(float)
    drawn = ok[np.isfinite(x_all) & np.isfinite(ok["success_rate"].astype(float))]
    for _, r in drawn.iterrows():
        marker, colour = style(r)
        x, y = r["mean_requested_reliability"], r["success_rate"]
        low, high = r["success_ci_low"], r["success_ci_high"]
        ax.errorbar(
            x,
            y,
            yerr=[[y - low], [high - y]] if np.isfinite([low, high]).all() else None,
            fmt=marker,
            color=colour,
            mfc=colour if r["pareto"] else "white",
            ms=7,
            capsize=2,
            lw=0.8,
            alpha=0.9,
        )
        if bool(r["pareto"]):
            ax.plot(x, y, "o", ms=15, mfc="none", mec="black", mew=1.0)
    front = drawn[drawn["pareto"].astype(bool)].sort_values("mean_requested_reliability")
    if len(front):
        ax.step(
            front["mean_requested_reliability"],
            front["success_rate"],
            where="post",
            color="black",
            lw=0.8,
            ls="--",
        )
    notes = []
    if (rows["status"] != "ok").any():
        notes.append(f"{int((rows['status'] != 'ok').sum())} rows not run")
    if len(ok) > len(drawn):
        notes.append(f"{len(ok) - len(drawn)} rows without an average reliability")
    ax.set_title(f"{plant}" + (f" ({'; '.join(notes)})" if notes else ""), fontsize=9)
    ax.set_xlabel("average requested reliability (PDR)")
    ax.set_xlim(-0.03, 1.05)
    ax.set_ylim(-0.03, 1.05)
    ax.grid(alpha=0.3)
