"""The figure of a sweep: a metric's mean over replicates versus the robot count.

One panel per belt speed, one line per pipeline (:func:`plot_sweep`); ``codesign report``
draws every sweep table of a results folder with it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from codesign_mb.studies.figures import integer_ticks, new_figure, save_png

__all__ = ["plot_sweep", "sweep_summary"]


def sweep_summary(table: pd.DataFrame, metric: str = "success_rate") -> pd.DataFrame:
    """Mean, standard deviation, count and standard error of ``metric`` over replicates.

    One row per (``pipeline``, ``belt_speed_mps``, ``n_robots``); ``ValueError`` when the
    table has no column ``metric``.
    """
    if metric not in table.columns:
        raise ValueError(f"sweep table has no column {metric!r}")
    by = ["pipeline", "belt_speed_mps", "n_robots"]
    summary = table.groupby(by, sort=False)[metric].agg(["mean", "std", "count"]).reset_index()
    summary["sem"] = summary["std"].fillna(0.0) / np.sqrt(summary["count"])
    return summary


def plot_sweep(summary: pd.DataFrame, path: str | Path, *, metric: str, dpi: int = 120) -> Path:
    """A sweep as a PNG: :func:`sweep_summary`'s mean +- s.e. versus the robot count.

    One panel per belt speed, one line per pipeline.
    """
    speeds = sorted(summary["belt_speed_mps"].unique())
    fig, axes = new_figure(1, len(speeds), width=4.2, height=3.4)
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
        integer_ticks(ax)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0, 0].set_ylabel(f"{metric} (mean +- s.e. over seeds)")
    return save_png(fig, path, dpi=dpi)
