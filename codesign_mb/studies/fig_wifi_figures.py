"""Fig. 6 (``fig_wifi``) as a figure, and the files of ``codesign wifi capacity``.

:func:`plot_capacity` is the one renderer of Fig. 6: ``codesign wifi capacity`` draws it from
:func:`~codesign_mb.studies.fig_wifi.run_capacity`'s trials and ``codesign report`` from any
``fig_wifi`` table. :func:`run_capacity_study` runs the sweep and writes its files.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.core.config import to_mapping
from codesign_mb.core.records import RECORDS_DIR, RecordStore
from codesign_mb.core.results import write_results
from codesign_mb.studies.fig_wifi import (
    CHANNEL_PRESETS,
    CapacityConfig,
    capacity_ratios,
    capacity_table,
    describe_channel,
    run_capacity,
)
from codesign_mb.studies.figures import integer_ticks, new_figure, save_png

__all__ = ["capacity_curves", "curve_styles", "plot_capacity", "run_capacity_study"]

_SCHEDULER_STYLES = {"greedy": "-", "convex": "--", "convex-cvxpy": ":", "": "-"}
"""Line style per scheduler."""

_PIPELINE_MARKERS = ("o", "D", "^", "v", "s", "P")
"""Marker per pipeline: the first filled, the others hollow and larger, so that curves that
coincide (every pipeline at 100 % success) still show each pipeline."""

_DODGE = 0.012
"""Horizontal offset between the curves of one panel, as a share of its robot range."""


def curve_styles(pipelines: list[str], schedulers: list[str]) -> dict[tuple[str, str], dict]:
    """Matplotlib keywords of each (scheduler, pipeline) curve: colour and marker by
    pipeline, line style by scheduler, and a horizontal dodge (in units of the x range)."""
    styles = {}
    n = len(pipelines) * len(schedulers)
    for i, pipeline in enumerate(pipelines):
        for j, scheduler in enumerate(schedulers):
            k = i * len(schedulers) + j
            styles[(scheduler, pipeline)] = {
                "ls": _SCHEDULER_STYLES.get(scheduler, "-."),
                "marker": _PIPELINE_MARKERS[i % len(_PIPELINE_MARKERS)],
                "markersize": 5 + 2 * i,
                "markerfacecolor": None if i == 0 else "none",
                "color": f"C{i % 10}",
                "dodge": (k - (n - 1) / 2) * _DODGE,
            }
    return styles


def capacity_curves(
    results: pd.DataFrame, *, success_target: float = 0.95, stop_below: float = 0.0
) -> pd.DataFrame:
    """:func:`~codesign_mb.studies.fig_wifi.capacity_table` with the band of each point.

    ``band_low`` and ``band_high`` are the mean of the columns of that name when ``results``
    has them (a summary's interval per point), else the point's 95 % Wilson interval over
    its robot-episodes (``success_ci_low``, ``success_ci_high``).
    """
    keys = ["channel", "scheduler", "pipeline", "robots"]
    curves = capacity_table(results, success_target=success_target, stop_below=stop_below)
    if "band_low" in results and "band_high" in results:
        band = results.groupby(keys)[["band_low", "band_high"]].mean().reset_index()
        return curves.merge(band, on=keys)
    return curves.assign(band_low=curves["success_ci_low"], band_high=curves["success_ci_high"])


def plot_capacity(
    results: pd.DataFrame,
    path: str | Path,
    *,
    success_target: float = 0.95,
    stop_below: float = 0.0,
    dpi: int = 130,
) -> Path:
    """Fig. 6 as a PNG: per channel, success (top) and requested reliability (bottom) vs N.

    One colour and marker per pipeline (static QoS filled, co-design hollow and larger), one
    line style per scheduler (greedy solid, convex dashed), each curve shifted a little
    sideways so that coinciding curves stay visible; the band is each point's 95 % Wilson
    interval over its robot-episodes, or the given ``band_low`` and ``band_high``
    (:func:`capacity_curves`). The legend gives each curve's capacity (robots at
    ``success_target``) and, with ``stop_below``, where it stopped. ``results`` has
    :func:`~codesign_mb.studies.fig_wifi.run_capacity`'s columns ``channel``, ``scheduler``,
    ``pipeline``, ``robots`` and ``success_rate``; the bottom row of panels (requested
    ``mean_reliability``, ``delivered_fraction``) is drawn when one of them is given.
    """
    curves = capacity_curves(results, success_target=success_target, stop_below=stop_below)
    channels = list(dict.fromkeys(results["channel"]))
    pipelines = list(dict.fromkeys(results["pipeline"]))
    schedulers = list(dict.fromkeys(results["scheduler"]))
    styles = curve_styles(pipelines, [str(s) for s in schedulers])
    order = [(s, p) for p in pipelines for s in schedulers]
    bottom = any(
        c in results and results[c].notna().any()
        for c in ("mean_reliability", "delivered_fraction")
    )
    fig, axes = new_figure(2 if bottom else 1, len(channels), width=4.8, height=3.2, sharex="col")
    for c, channel in enumerate(channels):
        part = curves[curves["channel"] == channel]
        span = max(float(part["robots"].max() - part["robots"].min()), 1.0) if len(part) else 1.0
        for scheduler, pipeline in order:  # as run: the legend lists them so
            line = part[(part["scheduler"] == scheduler) & (part["pipeline"] == pipeline)]
            if not len(line):
                continue
            style = dict(styles[(str(scheduler), pipeline)])
            style["dodge"] *= span
            name = ", ".join(str(v) for v in (pipeline, scheduler) if str(v))
            _curve(axes[:, c], line.sort_values("robots"), name, style, success_target, stop_below)
        _channel_axes(axes[:, c], str(channel), success_target)
    fig.suptitle("Task success vs robots on one WiFi 6 channel (fig_wifi)", fontsize=10)
    return save_png(fig, path, dpi=dpi)


def _curve(
    axes: Any,
    line: pd.DataFrame,
    name: str,
    style: dict[str, Any],
    success_target: float,
    stop_below: float,
) -> None:
    """One (scheduler, pipeline) curve: success with its band on top, reliability below."""
    dodge = style.pop("dodge")
    colour = style["color"]
    cap = int(line["capacity_robots"].iloc[0])
    robots = f"{cap} robot{'' if cap == 1 else 's'}"
    reach = f">= {robots}" if line["capacity_censored"].iloc[0] else robots if cap else "none"
    label = f"{name} (at {success_target:.0%}: {reach}"
    if "capacity_interval_robots" in line:  # not significantly below the target
        more = ">= " if line["capacity_interval_censored"].iloc[0] else ""
        label += f", not below: {more}{int(line['capacity_interval_robots'].iloc[0])}"
    stopped = line["stopped_at_robots"].iloc[0]
    if stopped == stopped:  # not NaN: the sweep stopped this curve there
        label += f";\n< {stop_below:.0%} at {int(stopped)}: no larger N run"
    label += ")"
    x = line["robots"].to_numpy() + dodge
    axes[0].plot(x, line["success_rate"], label=label, **style)
    axes[0].fill_between(x, line["band_low"], line["band_high"], color=colour, alpha=0.08, lw=0)
    if len(axes) > 1:
        axes[1].plot(x, line["mean_reliability"], label=label, **style)
        axes[1].plot(x, line["delivered_fraction"], ":", color=colour, alpha=0.6)


def _channel_axes(axes: Any, channel: str, success_target: float) -> None:
    top = axes[0]
    top.axhline(success_target, color="0.5", lw=0.8, ls=":")
    top.set_ylim(-0.02, 1.05)
    top.set_ylabel("task success (95 % Wilson band)", fontsize=8)
    title = f"{channel}: {describe_channel(channel)}" if channel in CHANNEL_PRESETS else channel
    top.set_title(title, fontsize=8)
    top.grid(alpha=0.3)
    top.legend(fontsize=7, loc="lower left")
    if len(axes) > 1:
        bottom = axes[1]
        bottom.set_ylim(-0.02, 1.05)
        bottom.set_ylabel("requested q (solid/dashed), delivered (dotted)", fontsize=8)
        bottom.grid(alpha=0.3)
    axes[-1].set_xlabel("robots sharing the channel")
    integer_ticks(axes[-1])


def run_capacity_study(
    config: CapacityConfig,
    out_dir: str | Path,
    *,
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None,
    fresh: bool = False,
) -> tuple[pd.DataFrame, pd.DataFrame, dict[str, Path]]:
    """Run the capacity sweep and write Fig. 6 into ``out_dir``.

    Writes ``fig_wifi.{parquet,csv,json}`` (one row per trial; in the metadata the curves
    with their capacity, the co-design/static capacity ratio per cell and scheduler
    (:func:`~codesign_mb.studies.fig_wifi.capacity_ratios`) and the robot-episodes: at most
    ``planned``, ``run`` with the early stop) and ``fig_wifi.png`` (:func:`plot_capacity`).
    Returns the trials, the curves (:func:`~codesign_mb.studies.fig_wifi.capacity_table`)
    and the files (``parquet``, ``csv``, ``json``, ``png``). Finished trials are kept in
    ``<out_dir>/.records`` and reused by a rerun (``fresh``: none are).
    """
    store = RecordStore(Path(out_dir) / RECORDS_DIR, what="trial", fresh=fresh)
    with store.on_interrupt():
        results = run_capacity(config, progress=progress, store=store)
    target, stop = config.success_target, config.stop_below
    curves = capacity_table(results, success_target=target, stop_below=stop)
    files = dict(
        write_results(
            out_dir,
            table=results,
            config=to_mapping(config),
            name="fig_wifi",
            extra={
                "curves": curves.to_dict("records"),
                "capacity_ratios": capacity_ratios(curves).to_dict("records"),
                "robot_episodes": {
                    "planned": config.robot_episodes(),
                    "run": int(results["robots"].sum()) if len(results) else 0,
                },
                "computed": store.computed,
                "reused": store.reused,
            },
        )
    )
    files["png"] = plot_capacity(
        results, Path(out_dir) / "fig_wifi.png", success_target=target, stop_below=stop
    )
    return results, curves, files
