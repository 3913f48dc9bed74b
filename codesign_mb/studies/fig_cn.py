"""The paper's Fig. 4 (``fig_cn``): task success under delay and loss, learned and model-based.

paper.tex Fig. ``fig_cn`` shows the success rate of the ideal controller versus a fixed
delay, at belt speeds 0.2 and 0.6 m/s, with and without a QoS-aware state estimator. The
model-based rows (``pipeline = "model_based"``): the ideal controller is the MPC
(:mod:`codesign_mb.control.mpc`), the estimator the delay-compensating predictor
(:mod:`codesign_mb.estimation.predictor`), "none" the stale observation used as is. The
learned rows (``pipeline = "learned"``, the paper's): the stage-A controller alone (stale
observation), with the stage-B MLP and with the LSTM estimator, when their checkpoints exist
and read the plant's observation layout (else skipped, :func:`learned_skip_reason` says
why). A second sweep varies the i.i.d. reliability ``q`` instead of the delay. Every point
is an :func:`~codesign_mb.evaluation.evaluate.evaluate` of ``trials`` seeded episodes (the
same episode seeds at every point, so the curves are paired), reported with its Wilson
interval. The plant is the default scenario's with each panel's belt speed as the episodes'
base speed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.core import registry
from codesign_mb.core.config import LATENCY_STEPS_CAP, check_range
from codesign_mb.core.records import RECORDS_DIR, RecordStore
from codesign_mb.core.registry import ComponentSpec, PlantSpec
from codesign_mb.core.results import write_results
from codesign_mb.evaluation.evaluate import (
    EvaluateConfig,
    rows_to_table,
    run_jobs,
    summarize,
)
from codesign_mb.plants.scenarios import get_scenario
from codesign_mb.studies.figures import (
    Styler,
    curve_label,
    curves,
    integer_ticks,
    new_figure,
    save_png,
    varying,
)

_ESTIMATORS = ("predictor", "none")
"""Model-based estimator kinds compared (no checkpoint needed)."""

_NOMINAL = {"nominal_velocity": True}
"""The learned controller alone reads the state layout: the packet, the nominal velocity."""

_PLOT_LABELS = ("pipeline", "estimator")
"""The curves' labels: colour per (pipeline, estimator), line style per pipeline."""

__all__ = [
    "FigCnConfig",
    "fig_cn_points",
    "learned_skip_reason",
    "plot_fig_cn",
    "run_fig_cn",
    "run_fig_cn_study",
]

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
        Model-based estimator kinds to compare (``predictor``, ``none``).
    learned:
        Add the learned rows: ``learned_controller`` alone (stale observation) and with each
        of ``learned_estimators``; skipped, with the reason, when a checkpoint is missing or
        was trained on another observation layout (:func:`learned_skip_reason`).
    learned_controller, learned_estimators:
        The stage-A controller and the stage-B estimators of the learned rows.
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
    learned: bool = True
    learned_controller: ComponentSpec = field(
        default_factory=lambda: ComponentSpec("sac", "checkpoints/stage_a/model.zip")
    )
    learned_estimators: tuple[ComponentSpec, ...] = (
        ComponentSpec("mlp", "checkpoints/stage_b/mlp.pt"),
        ComponentSpec("lstm", "checkpoints/stage_b/lstm.pt"),
    )
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
        object.__setattr__(
            self,
            "learned_estimators",
            tuple(_spec(e) for e in self.learned_estimators),
        )
        object.__setattr__(self, "learned_controller", _spec(self.learned_controller))
        kinds = [e.kind for e in self.learned_estimators]
        if len(set(kinds)) != len(kinds) or not set(kinds) <= {"mlp", "lstm"}:
            raise ValueError(f"learned_estimators must be distinct kinds of mlp, lstm, got {kinds}")
        check_range("delays", self.delays, cap=LATENCY_STEPS_CAP)
        check_range(
            "reliability_latency_steps",
            self.reliability_latency_steps,
            ge=0,
            cap=LATENCY_STEPS_CAP,
        )
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


def _spec(value: Any) -> ComponentSpec:
    return value if isinstance(value, ComponentSpec) else ComponentSpec(**value)


@dataclass(frozen=True)
class _Row:
    """One curve's components (what :func:`~codesign_mb.studies.table_cost` checks)."""

    controller: ComponentSpec
    estimator: ComponentSpec
    qos: ComponentSpec = field(default_factory=lambda: ComponentSpec("static"))


def _learned_rows(config: FigCnConfig) -> list[_Row]:
    """The learned curves: the controller alone (the stale packet; where it has no velocity,
    the nominal belt velocity in the state layout's slot), then with each learned estimator."""
    alone = _Row(config.learned_controller, ComponentSpec("none", options=_NOMINAL))
    return [alone, *(_Row(config.learned_controller, e) for e in config.learned_estimators)]


def learned_skip_reason(config: FigCnConfig) -> str | None:
    """Why the learned rows are left out (``None``: they are in): not asked for, a checkpoint
    missing, or one trained on another observation layout than the figure's plant."""
    from codesign_mb.studies.table_cost import incompatible_checkpoints, missing_checkpoints

    if not config.learned:
        return "not asked for (learned = false)"
    rows = _learned_rows(config)
    missing = [c for r in rows for c in missing_checkpoints(r)]
    if missing:
        return f"checkpoints missing: {', '.join(dict.fromkeys(missing))}"
    base = config.base()
    plant = PlantSpec("conveyor", {**get_scenario(base.scenario).options, **base.env})
    wrong = [c for r in rows for c in incompatible_checkpoints(r, plant)]
    if wrong:
        return (
            f"not for the {base.scenario} plant: {', '.join(dict.fromkeys(wrong))}; train "
            f"them with `codesign train a|b --scenario {base.scenario}`"
        )
    return None


def fig_cn_points(config: FigCnConfig) -> list[tuple[dict[str, Any], EvaluateConfig]]:
    """The figure's points: ``(labels, EvaluateConfig)`` for the delay and the loss sweeps.

    Labels: ``sweep``, ``belt_speed_mps``, ``pipeline`` and ``estimator``. A learned point's
    config keeps the model-based ``controller`` and ``estimator`` fields (they need no
    checkpoint); :func:`run_fig_cn` builds its components from the labels.
    """
    curves: list[tuple[str, str]] = [("model_based", e) for e in config.estimators]
    if learned_skip_reason(config) is None:
        curves += [("learned", r.estimator.kind) for r in _learned_rows(config)]
    base = config.base()
    points: list[tuple[dict[str, Any], EvaluateConfig]] = []
    for speed in config.belt_speeds_mps:
        for pipeline, est in curves:
            kind = est if pipeline == "model_based" else base.estimator
            predictor = dict(config.predictor) if kind == "predictor" else {}
            head = {"belt_speed_mps": speed, "pipeline": pipeline, "estimator": est}
            at = replace(base, estimator=kind, belt_speed_mps=speed, predictor=predictor)
            for d in config.delays:
                cfg = replace(at, reliability=1.0, latency_steps=int(d))
                points.append(({"sweep": "delay", **head}, cfg))
            for q in config.reliabilities:
                cfg = replace(
                    at, reliability=float(q), latency_steps=config.reliability_latency_steps
                )
                points.append(({"sweep": "reliability", **head}, cfg))
    return points


def _components(
    config: FigCnConfig, labels: dict[str, Any], cfg: EvaluateConfig
) -> tuple[Any, Any, Any]:
    """A point's ``(controller, estimator, qos)`` factories (learned ones from checkpoints)."""
    controller, estimator, qos = cfg.components()
    if labels.get("pipeline") != "learned":
        return controller, estimator, qos
    row = next(r for r in _learned_rows(config) if r.estimator.kind == labels["estimator"])
    return (
        registry.factory("controller", row.controller),
        registry.factory("estimator", row.estimator),
        qos,
    )


def run_fig_cn(
    config: FigCnConfig, *, progress: Progress | None = None, store: RecordStore | None = None
) -> pd.DataFrame:
    """Evaluate every point of the figure in one process pool; one row per point.

    ``store`` keeps every finished episode and gives back those of an earlier run
    (:func:`~codesign_mb.evaluation.evaluate.run_jobs`).

    Columns: ``sweep`` (``"delay"`` or ``"reliability"``), ``belt_speed_mps``, ``pipeline``
    (``"model_based"`` or ``"learned"``), ``estimator``,
    ``latency_steps``, ``reliability``, then :func:`~codesign_mb.evaluation.evaluate.summarize`'s
    (``trials``, ``successes``, ``success_rate``, ``success_ci_low``, ``success_ci_high``,
    ``mean_age``, ``delivered_fraction``, ..., and with an MPC ``mpc_failures``: its failed
    solves summed over the point's episodes).
    """
    points = fig_cn_points(config)
    jobs = []
    for labels, cfg in points:
        controller, estimator, qos = _components(config, labels, cfg)
        jobs.append((controller, estimator, qos, cfg.env_config(), cfg.trials, cfg.seed))
    total = sum(cfg.trials for _, cfg in points)
    stream: Iterator[tuple[int, dict[str, Any]]] = run_jobs(
        jobs, workers=config.workers, max_steps=config.max_steps, store=store
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


def run_fig_cn_study(
    config: FigCnConfig,
    out_dir: str | Path,
    *,
    progress: Progress | None = None,
    fresh: bool = False,
) -> tuple[pd.DataFrame, dict[str, Path]]:
    """Run Fig. 4 (:func:`run_fig_cn`) and write it into ``out_dir``.

    Writes ``fig_cn.{parquet,csv,json}`` (one row per point; the JSON also says why the
    learned rows were skipped, ``learned_rows_skipped``, ``None`` if they are in) and ``fig_cn.png``
    (:func:`plot_fig_cn`); returns the table and the files (``parquet``, ``csv``, ``json``,
    ``png``). Finished episodes are kept in ``<out_dir>/.records`` and reused by a rerun
    (``fresh``: none are).
    """
    store = RecordStore(Path(out_dir) / RECORDS_DIR, fresh=fresh)
    with store.on_interrupt():
        table = run_fig_cn(config, progress=progress, store=store)
    skipped = learned_skip_reason(config)
    files = dict(
        write_results(
            out_dir,
            table=table,
            config=config,
            name="fig_cn",
            extra={"learned_rows_skipped": skipped},
        )
    )
    files["png"] = plot_fig_cn(table, Path(out_dir) / "fig_cn.png", labels=_PLOT_LABELS)
    return table, files


def plot_fig_cn(
    table: pd.DataFrame,
    path: str | Path,
    *,
    labels: Sequence[str] = ("estimator",),
    dpi: int = 130,
) -> Path:
    """Fig. 4 (PNG): success rate with its interval; rows = sweeps, columns = belt speeds.

    ``table`` has one row per point: ``success_rate``, ``success_ci_low``,
    ``success_ci_high`` and the x value, ``latency_steps`` (delay sweep) or ``reliability``
    (rows whose ``sweep`` is ``"reliability"``; any other ``sweep``, or none, is the delay
    sweep); optional ``belt_speed_mps`` (one column of panels each; absent: one untitled
    panel). One curve per value of the ``labels`` present (colour; a ``pipeline`` label sets
    the line style: learned solid, model-based dashed). :func:`run_fig_cn`'s table fits, and
    ``codesign report`` draws any ``fig_cn`` table with this function.
    """
    sweep = table["sweep"].astype(str) if "sweep" in table else pd.Series("", index=table.index)
    table = table.assign(sweep=sweep.where(sweep == "reliability", "delay"))
    if "belt_speed_mps" not in table:
        table = table.assign(belt_speed_mps=-1.0)  # one panel, no title
    labels = [c for c in labels if c in table.columns]
    speeds = sorted(table["belt_speed_mps"].unique())
    sweeps = [s for s in ("delay", "reliability") if s in set(table["sweep"])]
    fig, axes = new_figure(len(sweeps), len(speeds), width=4.2, height=3.2)
    styler = Styler(labels)
    shown = varying(table, labels) if labels else []
    for r, name in enumerate(sweeps):
        xcol = "latency_steps" if name == "delay" else "reliability"
        for c, speed in enumerate(speeds):
            ax = axes[r, c]
            part = table[(table["sweep"] == name) & (table["belt_speed_mps"] == speed)]
            for key, group in curves(part, labels):
                group = group.sort_values(xcol)
                colour, style = styler(key)
                x = group[xcol].to_numpy(float)
                label = curve_label(key, shown)
                ax.plot(x, group["success_rate"], style, marker="o", color=colour, label=label)
                low, high = group["success_ci_low"], group["success_ci_high"]
                ax.fill_between(x, low, high, color=colour, alpha=0.15, linewidth=0)
            _axes(ax, name, part, speed)
    return save_png(fig, path, dpi=dpi)


def _axes(ax: Any, sweep: str, part: pd.DataFrame, speed: float) -> None:
    if sweep == "delay":
        integer_ticks(ax)
        ax.set_xlabel("fixed delay tau [steps of 40 ms]")
    else:
        ax.set_xscale("log")
        taus = sorted(set(part["latency_steps"])) if "latency_steps" in part else []
        fixed = f", tau = {', '.join(f'{t:g}' for t in taus)}" if taus else ""
        ax.set_xlabel(f"reliability q (i.i.d.{fixed})")
        ticks = sorted(set(part["reliability"]))
        ax.set_xticks(ticks, [f"{q:g}" for q in ticks])
        ax.minorticks_off()
        ax.invert_xaxis()
    ax.set_ylim(-0.02, 1.02)
    ax.set_ylabel("success rate")
    ax.set_title(f"belt {speed:g} m/s" if speed >= 0 else "")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left", fontsize="small")
