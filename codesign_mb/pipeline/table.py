"""Table I (``tab_p``) and Fig. 5 (``fig_lat``) of paper.tex on our env, for any pipeline.

A table is a list of :class:`TableRow` — a name and a ``{controller, estimator, qos}`` triple
of :class:`~codesign_mb.pipeline.components.ComponentSpec` — evaluated with
:func:`codesign_mb.evaluation.evaluate.evaluate` on the same seeded episodes: success with a
95 % Wilson interval and the average requested reliability (the paper's "average PDR").
:data:`PIPELINES` maps a pipeline name to its default rows (``model-free``: the paper's three
rows from the shipped checkpoints); more pipelines are added there, or rows are given in a
config file (``[[rows]]`` tables).

Fig. 5 is the requested reliability along one successful episode of the ``timeline_row``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.pipeline.components import ComponentSpec, build, factory
from codesign_mb.pipeline.plants import PlantSpec, make_plant, plant_factory

__all__ = [
    "PIPELINES",
    "TableConfig",
    "TableRow",
    "all_rows",
    "model_based_rows",
    "model_free_rows",
    "plot_timeline",
    "qos_timeline",
    "run_table",
]


@dataclass(frozen=True)
class TableRow:
    """One row: a name, the three components, and the paper's figures for it (if any)."""

    name: str
    controller: ComponentSpec
    estimator: ComponentSpec
    qos: ComponentSpec
    paper_success_rate: float | None = None
    paper_mean_reliability: float | None = None

    def __post_init__(self) -> None:
        for role in ("controller", "estimator", "qos"):
            value = getattr(self, role)
            if isinstance(value, dict):
                object.__setattr__(self, role, ComponentSpec(**value))


def model_free_rows() -> tuple[TableRow, ...]:
    """The paper's Table I rows, from the shipped checkpoints (latency fixed at one step)."""
    sac = ComponentSpec("sac", "checkpoints/stage_a/model.zip")
    mlp = ComponentSpec("mlp", "checkpoints/stage_d/mlp.pt")
    return (
        TableRow(
            "MLP estimator, static QoS",
            sac,
            mlp,
            ComponentSpec("static", options={"reliability": 1.0, "latency_steps": 1}),
            1.00,
            1.00,
        ),
        TableRow(
            "no estimator, dynamic QoS",
            sac,
            ComponentSpec("none"),
            ComponentSpec("learned", "checkpoints/stage_c_none"),
            0.78,
            0.52,
        ),
        TableRow(
            "MLP estimator, dynamic QoS (co-design)",
            sac,
            mlp,
            ComponentSpec("learned", "checkpoints/stage_d/qos"),
            0.98,
            0.13,
        ),
    )


MPC_RULE_THRESHOLD_M = 0.08
"""Trigger of the model-based co-design rule: tuned by bisection for >= 98 % success at
0.2 m/s (`tune_threshold`; see the note in README.md)."""


def model_based_rows() -> tuple[TableRow, ...]:
    """The model-based counterparts of Table I: MPC, the predictor, the covariance rule."""
    mpc = ComponentSpec("mpc")
    predictor = ComponentSpec("predictor")
    static = ComponentSpec("static", options={"reliability": 1.0, "latency_steps": 1})
    rule = ComponentSpec("rule", options={"threshold_m": MPC_RULE_THRESHOLD_M, "low": 0.0})
    return (
        TableRow("MPC + predictor, static QoS", mpc, predictor, static),
        TableRow("MPC, no estimator, rule QoS", mpc, ComponentSpec("plain"), rule),
        TableRow("MPC + predictor, rule QoS (co-design)", mpc, predictor, rule),
    )


def all_rows() -> tuple[TableRow, ...]:
    """Both pipelines and the mixed pairs (SAC + predictor, MPC + MLP estimator)."""
    sac = ComponentSpec("sac", "checkpoints/stage_a/model.zip")
    mlp = ComponentSpec("mlp", "checkpoints/stage_d/mlp.pt")
    static = ComponentSpec("static", options={"reliability": 1.0, "latency_steps": 1})
    return (
        *model_free_rows(),
        *model_based_rows(),
        TableRow("SAC + predictor, static QoS", sac, ComponentSpec("predictor"), static),
        TableRow("MPC + MLP estimator, static QoS", ComponentSpec("mpc"), mlp, static),
    )


PIPELINES: dict[str, Callable[[], tuple[TableRow, ...]]] = {
    "model-free": model_free_rows,
    "model-based": model_based_rows,
    "all": all_rows,
}
"""Pipeline name -> its default rows."""


@dataclass(frozen=True)
class TableConfig:
    """What ``codesign table`` evaluates.

    Parameters
    ----------
    plant:
        The plant (the conveyor at 0.2 m/s by default).
    rows:
        The rows; empty means the default rows of ``pipeline``.
    pipeline:
        A key of :data:`PIPELINES`.
    trials:
        Episodes per row (the same seeds for every row).
    seed:
        Root seed of the episodes.
    workers:
        Worker processes of the evaluation.
    timeline_row:
        Row whose successful episode is plotted (Fig. 5); ``""``: the last row.
    """

    plant: PlantSpec = field(default_factory=PlantSpec)
    rows: tuple[TableRow, ...] = ()
    pipeline: str = "model-free"
    trials: int = 100
    seed: int = 0
    workers: int = 1
    timeline_row: str = ""

    def __post_init__(self) -> None:
        if self.pipeline not in PIPELINES:
            raise ValueError(
                f"pipeline must be one of {', '.join(PIPELINES)}, got {self.pipeline!r}"
            )
        if self.trials < 1:
            raise ValueError(f"trials must be >= 1, got {self.trials}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        rows = tuple(r if isinstance(r, TableRow) else TableRow(**r) for r in self.rows)
        object.__setattr__(self, "rows", rows)
        names = [r.name for r in self.table_rows()]
        if len(set(names)) != len(names):
            raise ValueError(f"row names must be unique, got {names}")
        if self.timeline_row and self.timeline_row not in names:
            raise ValueError(f"timeline_row {self.timeline_row!r} is not a row: {names}")

    def table_rows(self) -> tuple[TableRow, ...]:
        return self.rows or PIPELINES[self.pipeline]()


def run_table(
    config: TableConfig, *, progress: Callable[..., Any] | None = None
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Evaluate every row; return the summary (one row per table row) and all episodes."""
    from codesign_mb.evaluation.evaluate import evaluate, summarize

    rows = config.table_rows()
    env_factory = plant_factory(config.plant)
    summaries, episodes = [], []
    iterator = range(len(rows))
    if progress is not None:
        iterator = progress(iterator, total=len(rows), description="table rows")
    for i in iterator:
        row = rows[i]
        started = time.perf_counter()
        table = evaluate(
            factory("controller", row.controller),
            factory("estimator", row.estimator),
            factory("qos", row.qos),
            env_factory,
            config.trials,
            config.seed,
            workers=config.workers,
        )
        summary = summarize(table)
        summaries.append(
            {
                "row": row.name,
                "controller": row.controller.kind,
                "estimator": row.estimator.kind,
                "qos": row.qos.kind,
                "success_rate": summary["success_rate"],
                "success_ci_low": summary["success_ci_low"],
                "success_ci_high": summary["success_ci_high"],
                "mean_requested_reliability": summary["mean_requested_reliability"],
                "delivered_fraction": summary["delivered_fraction"],
                "mean_age": summary["mean_age"],
                "mean_estimation_error": summary["mean_estimation_error"],
                "trials": summary["trials"],
                "paper_success_rate": row.paper_success_rate,
                "paper_mean_reliability": row.paper_mean_reliability,
                "wall_time_s": time.perf_counter() - started,
            }
        )
        episodes.append(table.assign(row=row.name))
    return pd.DataFrame(summaries), pd.concat(episodes, ignore_index=True)


def qos_timeline(
    plant: PlantSpec, row: TableRow, episodes: pd.DataFrame
) -> tuple[pd.DataFrame, int] | None:
    """The per-step record of the row's first successful episode (and its seed), or ``None``."""
    from codesign_mb.evaluation.rollout import rollout
    from codesign_mb.network.link import BernoulliLink
    from codesign_mb.network.wrapper import LinkObservationWrapper

    mine = episodes[(episodes["row"] == row.name) & episodes["success"].astype(bool)]
    if mine.empty:
        return None
    seed = int(mine.sort_values("episode").iloc[0]["seed"])
    probe = make_plant(plant)
    env = LinkObservationWrapper(probe, BernoulliLink(), build("qos", row.qos, probe))
    steps = rollout(
        env,
        build("estimator", row.estimator, probe),
        build("controller", row.controller, probe),
        seed=seed,
    )
    env.close()
    return steps, seed


def plot_timeline(steps: pd.DataFrame, path: str | Path, *, title: str) -> Path:
    """Fig. 5: requested reliability per step, deliveries, and the lift (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from codesign_mb.evaluation.results import atomic_write

    fig, ax = plt.subplots(figsize=(7.0, 3.2))
    t = steps["t"].to_numpy()
    q = steps["qos_reliability"].to_numpy()
    ax.step(t, q, where="post", color="tab:blue", label="requested reliability $q_t$")
    delivered = steps["delivered"].astype(bool).to_numpy()
    ax.plot(t[delivered], q[delivered], "o", ms=3, color="tab:green", label="packet delivered")
    for column, label, style in (("lifted", "object lifted", "--"), ("success", "success", ":")):
        if column in steps and steps[column].astype(bool).any():
            first = int(np.argmax(steps[column].astype(bool).to_numpy()))
            ax.axvline(t[first], color="tab:red", ls=style, lw=1, label=f"{label} (t={t[first]})")
    ax.set_xlabel("step t (40 ms)")
    ax.set_ylabel("reliability (PDR)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"{title}: average {q.mean():.0%}")
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    path = Path(path)
    with atomic_write(path) as fh:
        fig.savefig(fh, format="png", dpi=120)
    plt.close(fig)
    return path
