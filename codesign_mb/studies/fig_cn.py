"""The paper's Fig. 4 (``fig_cn``), model-based: task success under delay and loss.

paper.tex Fig. ``fig_cn`` shows the success rate of the ideal controller versus a fixed
delay, at belt speeds 0.2 and 0.6 m/s, with and without a QoS-aware state estimator. Here the
ideal controller is the MPC (:mod:`codesign_mb.control.mpc`), the estimator the
delay-compensating predictor (:mod:`codesign_mb.estimation.predictor`), "none" the stale
observation used as is; a second sweep varies the i.i.d. reliability ``q`` instead of the
delay. Every point is an :func:`~codesign_mb.evaluation.evaluate.evaluate` of ``trials``
seeded episodes (the same episode seeds at every point, so the curves are paired), reported
with its Wilson interval.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.core.results import atomic_write
from codesign_mb.evaluation.evaluate import (
    EvaluateConfig,
    rows_to_table,
    run_jobs,
    summarize,
)

_ESTIMATORS = ("predictor", "none")
"""Estimator kinds compared (no checkpoint needed)."""

__all__ = ["FigCnConfig", "fig_cn_points", "plot_fig_cn", "run_fig_cn"]

Progress = Callable[[Iterable[Any], int], Iterable[Any]]


@dataclass(frozen=True)
class FigCnConfig:
    """The grid of Fig. 4 (config file table ``[fig_cn]``).

    Parameters
    ----------
    trials, seed, workers, max_steps:
        Episodes per point, root seed (the same for every point), worker processes, cap on
        an episode's steps (default: the plant's horizon).
    delays:
        Fixed delays ``tau`` in steps for the delay sweep (reliability 1).
    belt_speeds_mps:
        Belt speeds; one panel each.
    reliabilities:
        I.i.d. reliabilities ``q`` for the loss sweep.
    reliability_latency_steps:
        The latency of the loss sweep (the paper's robotics runs use one step).
    estimators:
        Names in ``FIG_CN__ESTIMATORS`` to compare.
    controller, env, mpc, predictor:
        As in :class:`~codesign_mb.evaluation.evaluate.EvaluateConfig`. ``env`` defaults to
        ``terminate_on_success=True``: success is latched, so ending an episode at its success
        changes no point of the figure and saves most of the simulation (the other columns,
        e.g. the mean age, are then averaged over the steps up to the success).
    """

    trials: int = 100
    seed: int = 0
    workers: int | None = None
    max_steps: int | None = None
    delays: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7, 8)
    belt_speeds_mps: tuple[float, ...] = (0.2, 0.6)
    reliabilities: tuple[float, ...] = (1.0, 0.8, 0.5, 0.3, 0.2, 0.1, 0.05)
    reliability_latency_steps: int = 1
    estimators: tuple[str, ...] = ("predictor", "none")
    controller: str = "mpc"
    env: dict[str, Any] = field(default_factory=lambda: {"terminate_on_success": True})
    mpc: dict[str, Any] = field(default_factory=dict)
    predictor: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("delays", "belt_speeds_mps", "reliabilities", "estimators"):
            value = tuple(getattr(self, name))
            object.__setattr__(self, name, value)
            if name != "reliabilities" and not value:
                raise ValueError(f"{name} must not be empty")
        for d in self.delays:
            if isinstance(d, bool) or int(d) != d or d < 0:
                raise ValueError(f"delays must be integers >= 0, got {d!r}")
        for v in self.belt_speeds_mps:
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"belt_speeds_mps must be >= 0, got {v!r}")
        for q in self.reliabilities:
            if not (math.isfinite(q) and 0.0 <= q <= 1.0):
                raise ValueError(f"reliabilities must be in [0, 1], got {q!r}")
        for e in self.estimators:
            if e not in _ESTIMATORS:
                raise ValueError(f"estimators must be in {', '.join(_ESTIMATORS)}, got {e!r}")
        self.base()  # validates the shared fields (controller, trials, seed, workers)

    def base(self) -> EvaluateConfig:
        """The :class:`EvaluateConfig` every point starts from."""
        return EvaluateConfig(
            controller=self.controller,
            trials=self.trials,
            seed=self.seed,
            workers=self.workers,
            max_steps=self.max_steps,
            env=dict(self.env),
            mpc=dict(self.mpc),
            predictor=dict(self.predictor),
        )


def fig_cn_points(config: FigCnConfig) -> list[tuple[dict[str, Any], EvaluateConfig]]:
    """The figure's points: ``(labels, EvaluateConfig)`` for the delay and the loss sweeps."""
    base = config.base()
    points: list[tuple[dict[str, Any], EvaluateConfig]] = []
    for speed in config.belt_speeds_mps:
        for est in config.estimators:
            predictor = dict(config.predictor) if est == "predictor" else {}
            for d in config.delays:
                labels = {"sweep": "delay", "belt_speed_mps": speed, "estimator": est}
                cfg = replace(
                    base,
                    estimator=est,
                    belt_speed_mps=speed,
                    reliability=1.0,
                    latency_steps=int(d),
                    predictor=predictor,
                )
                points.append((labels, cfg))
            for q in config.reliabilities:
                labels = {"sweep": "reliability", "belt_speed_mps": speed, "estimator": est}
                cfg = replace(
                    base,
                    estimator=est,
                    belt_speed_mps=speed,
                    reliability=float(q),
                    latency_steps=config.reliability_latency_steps,
                    predictor=predictor,
                )
                points.append((labels, cfg))
    return points


def run_fig_cn(config: FigCnConfig, *, progress: Progress | None = None) -> pd.DataFrame:
    """Evaluate every point of the figure in one process pool; one row per point.

    Columns: ``sweep`` (``"delay"`` or ``"reliability"``), ``belt_speed_mps``, ``estimator``,
    ``latency_steps``, ``reliability``, then :func:`~codesign_mb.evaluation.evaluate.summarize`'s
    (``trials``, ``successes``, ``success_rate``, ``success_ci_low``, ``success_ci_high``,
    ``mean_age``, ``delivered_fraction``, ...).
    """
    points = fig_cn_points(config)
    jobs = []
    for _, cfg in points:
        controller, estimator, qos = cfg.components()
        jobs.append((controller, estimator, qos, cfg.env_config(), cfg.trials, cfg.seed))
    total = sum(cfg.trials for _, cfg in points)
    stream: Iterator[tuple[int, dict[str, Any]]] = run_jobs(
        jobs, workers=config.workers, max_steps=config.max_steps
    )
    if progress is not None:
        stream = iter(progress(stream, total))
    rows: list[list[dict[str, Any]]] = [[] for _ in points]
    for j, row in stream:
        rows[j].append(row)
    records = []
    for (labels, cfg), episode_rows in zip(points, rows, strict=True):
        summary = summarize(rows_to_table(episode_rows))
        records.append(
            {
                **labels,
                "latency_steps": cfg.latency_steps,
                "reliability": cfg.reliability,
                **summary,
            }
        )
    return pd.DataFrame(records)


def plot_fig_cn(table: pd.DataFrame, path: str | Path) -> Path:
    """Plot the figure (PNG): rows = sweeps (delay, reliability), columns = belt speeds."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    path = Path(path)
    speeds = sorted(table["belt_speed_mps"].unique())
    sweeps = [s for s in ("delay", "reliability") if s in set(table["sweep"])]
    fig, axes = plt.subplots(
        len(sweeps), len(speeds), figsize=(4.2 * len(speeds), 3.2 * len(sweeps)), squeeze=False
    )
    styles = {"predictor": ("C0", "o", "MPC + predictor"), "none": ("C3", "s", "MPC, no estimator")}
    try:
        for r, sweep in enumerate(sweeps):
            for c, speed in enumerate(speeds):
                ax = axes[r][c]
                part = table[(table["sweep"] == sweep) & (table["belt_speed_mps"] == speed)]
                xcol = "latency_steps" if sweep == "delay" else "reliability"
                for est, group in part.groupby("estimator", sort=False):
                    group = group.sort_values(xcol)
                    color, marker, label = styles.get(str(est), ("C2", "^", str(est)))
                    x = group[xcol].to_numpy()
                    ax.plot(x, group["success_rate"], marker=marker, color=color, label=label)
                    ax.fill_between(
                        x,
                        group["success_ci_low"],
                        group["success_ci_high"],
                        color=color,
                        alpha=0.15,
                        linewidth=0,
                    )
                if sweep == "delay":
                    ax.set_xlabel("fixed delay [steps of 40 ms]")
                else:
                    ax.set_xscale("log")
                    taus = sorted(set(part["latency_steps"]))
                    ax.set_xlabel(f"reliability q (i.i.d., tau = {', '.join(map(str, taus))})")
                    ticks = sorted(set(part[xcol]))
                    ax.set_xticks(ticks, [f"{q:g}" for q in ticks])
                    ax.minorticks_off()
                    ax.invert_xaxis()
                ax.set_ylim(-0.02, 1.02)
                ax.set_ylabel("success rate")
                ax.set_title(f"belt {speed:g} m/s")
                ax.grid(True, alpha=0.3)
                ax.legend(loc="lower left", fontsize="small")
        fig.tight_layout()
        with atomic_write(path, "wb") as fh:
            fig.savefig(fh, format="png", dpi=130)
    finally:
        plt.close(fig)
    return path
