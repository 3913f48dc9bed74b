"""Table I (``tab_p``), the head-to-head table and Fig. 5 (``fig_lat``) of paper.tex, any pipeline.

A table is a list of :class:`TableRow` — a name and a ``{controller, estimator, qos}`` triple
of :class:`~codesign_mb.core.registry.ComponentSpec` — evaluated on one or more plants
(:class:`TablePlant`, e.g. the conveyor at 0.2 and 0.6 m/s and with a variable belt) on the
same seeded episodes (every row and plant gets the episode seeds of ``seed``). All episodes of
all rows and plants share one pool of worker processes
(:func:`~codesign_mb.evaluation.evaluate.run_jobs`).

Columns of the summary (one row per table row and plant):

``success_rate``, ``success_ci_low``, ``success_ci_high``
    Success with its 95 % Wilson interval.
``mean_requested_reliability``, ``delivered_fraction``
    The paper's "average PDR" and the fraction of packets delivered.
``train_env_steps``, ``train_wall_time_s``, ``train_sources``
    Training cost of the row (:func:`training_cost`): the ``training.json`` next to every
    learned checkpoint the row uses, followed through what each was trained from (a stage-D
    estimator continues stage B's under stage C's policy; a stage-D QoS policy is warm-started
    from stage C; a stage-B estimator is trained on the stage-A controller's episodes), each
    file counted once. Model-based components (MPC, predictor, the covariance rule) count 0:
    the rule's threshold was tuned by bisection offline and that cost is not recorded.
``controller_cpu_ms``, ``estimator_cpu_ms``, ``qos_cpu_ms``, ``cpu_ms_per_step``
    CPU time (``time.process_time``, ms) per control step of ``act``, ``estimate`` and
    ``request`` (the QoS policy runs at the edge), and their sum.
``status``
    ``"ok"``, or why the row was not evaluated (``"missing checkpoint: ..."``): a row whose
    checkpoint is absent is kept in the table with no figures (``on_missing="skip"``, the
    default) or stops the run before any episode (``on_missing="error"``). A missing
    checkpoint is never replaced by another one.
``pareto``
    Whether the row is on the Pareto front of its plant (no other row has at least its
    success with at most its average reliability, one of them strictly; :func:`pareto_front`).

:data:`PIPELINES` maps a pipeline name to its default rows and :data:`PIPELINE_PLANTS` to its
default plants (``model-free``: the paper's Table I, at 0.2 m/s only; ``all``: the
head-to-head rows at both belt speeds and on the variable belt). Rows and plants can be given
in a config file (``[[rows]]``, ``plants``).

Fig. 5 is the requested reliability along one successful episode, on the first plant, of the
co-design row of the ``model-free`` or ``model-based`` pipeline (as in the paper), or of the
best row of other tables (:func:`best_row`: the least average reliability among rows with
>= 98 % success, else the most successful row).
"""

from __future__ import annotations

import json
import math
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from codesign_mb.core.config import from_mapping
from codesign_mb.core.registry import (
    ComponentSpec,
    PlantSpec,
    build,
    factory,
    make_plant,
    models_dir,
    plant_factory,
    resolve_checkpoint,
)
from codesign_mb.core.results import atomic_write
from codesign_mb.evaluation.evaluate import Factory, rows_to_table, run_jobs, summarize
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.conveyor import ConveyorConfig
from codesign_mb.rollout import rollout

__all__ = [
    "CPU_COLUMNS",
    "MPC_RULE_THRESHOLD_M",
    "PIPELINES",
    "PIPELINE_PLANTS",
    "PIPELINE_TIMELINE",
    "PLANT_PRESETS",
    "TableConfig",
    "TablePlant",
    "TableRow",
    "TrainingCost",
    "all_rows",
    "best_row",
    "markdown_table",
    "missing_checkpoints",
    "model_based_rows",
    "model_free_rows",
    "pareto_front",
    "plot_pareto",
    "plot_timeline",
    "qos_timeline",
    "run_table",
    "stack_of",
    "timeline_row_name",
    "training_cost",
]

CPU_COLUMNS = ("controller_cpu_ms", "estimator_cpu_ms", "qos_cpu_ms")
"""Per-episode columns: CPU ms per call of ``act``, ``estimate`` and ``request``."""


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
            if isinstance(value, Mapping):
                object.__setattr__(
                    self, role, from_mapping(ComponentSpec, value, where=f"rows.{role}")
                )


@dataclass(frozen=True)
class TablePlant:
    """A plant of the table, with the label of its ``plant`` column.

    Parameters
    ----------
    label:
        Shown in the ``plant`` column and the figures, e.g. ``"0.2 m/s"``.
    name, options:
        The :class:`~codesign_mb.core.registry.PlantSpec`.
    """

    label: str
    name: str = "conveyor"
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.label, str) or not self.label:
            raise ValueError(f"plant label must be a non-empty string, got {self.label!r}")
        self.spec  # validates name and options  # noqa: B018

    @property
    def spec(self) -> PlantSpec:
        return PlantSpec(self.name, dict(self.options))

    @classmethod
    def of(cls, spec: PlantSpec) -> TablePlant:
        """A plant labelled from its spec: ``"0.2 m/s"``, ``"variable (0.6 m/s)"``, ``"toy"``."""
        options = dict(spec.options)
        label = spec.name
        if spec.name == "conveyor":
            config = from_mapping(ConveyorConfig, options, where="plant.options")
            label = f"{config.belt_speed_mps:g} m/s"
            if config.belt_profile != "constant":
                label = f"{config.belt_profile} ({label})"
        return cls(label, spec.name, options)


PLANT_PRESETS: dict[str, TablePlant] = {
    "0.2": TablePlant("0.2 m/s", options={"belt_speed_mps": 0.2}),
    "0.6": TablePlant("0.6 m/s", options={"belt_speed_mps": 0.6}),
    "variable": TablePlant(
        "variable (0.6 m/s)", options={"belt_speed_mps": 0.6, "belt_profile": "variable"}
    ),
}
"""The conveyor plants of the tables, by the name ``--plant`` and ``plants`` take: both belt
speeds of the paper and the variable belt (seeded speed steps and stops around 0.6 m/s)."""


# -- rows -------------------------------------------------------------------------------------
_SAC = ComponentSpec("sac", "checkpoints/stage_a/model.zip")
_MLP = ComponentSpec("mlp", "checkpoints/stage_d/mlp.pt")
_MPC = ComponentSpec("mpc")
_PREDICTOR = ComponentSpec("predictor")
_STATIC = ComponentSpec("static", options={"reliability": 1.0, "latency_steps": 1})

MPC_RULE_THRESHOLD_M = 0.08
"""Trigger of the model-based co-design rule: tuned by bisection for >= 98 % success at
0.2 m/s (`tune_threshold`; see the note in README.md)."""


def _rule() -> ComponentSpec:
    return ComponentSpec("rule", options={"threshold_m": MPC_RULE_THRESHOLD_M, "low": 0.0})


def model_free_rows() -> tuple[TableRow, ...]:
    """The paper's Table I rows, from the shipped checkpoints (latency fixed at one step)."""
    return (
        TableRow("MLP estimator, static QoS", _SAC, _MLP, _STATIC, 1.00, 1.00),
        TableRow(
            "no estimator, dynamic QoS",
            _SAC,
            ComponentSpec("none"),
            ComponentSpec("learned", "checkpoints/stage_c_none"),
            0.78,
            0.52,
        ),
        TableRow(
            "MLP estimator, dynamic QoS (co-design)",
            _SAC,
            _MLP,
            ComponentSpec("learned", "checkpoints/stage_d/qos"),
            0.98,
            0.13,
        ),
    )


def model_based_rows() -> tuple[TableRow, ...]:
    """The model-based counterparts of Table I: MPC, the predictor, the covariance rule."""
    return (
        TableRow("MPC + predictor, static QoS", _MPC, _PREDICTOR, _STATIC),
        TableRow("MPC, no estimator, rule QoS", _MPC, ComponentSpec("none"), _rule()),
        TableRow("MPC + predictor, rule QoS (co-design)", _MPC, _PREDICTOR, _rule()),
    )


def all_rows() -> tuple[TableRow, ...]:
    """The head-to-head rows: {static, rule, SAC} QoS x {SAC + MLP, MPC + predictor}, ...

    ... the mixed pairs with the QoS policies that do not depend on who they serve (SAC +
    predictor and MPC + MLP, static and rule QoS; a SAC QoS policy is trained for one
    controller and estimator), and the no-estimator rows (the paper's "no estimator, dynamic
    QoS" and its model-based counterpart). The model-free stack uses stage D's estimator and
    QoS policy (the paper's final synthesis), the model-based SAC QoS is stage C on MPC +
    predictor (``checkpoints/stage_c_mpc``, features ``predictor_std``).
    """
    rule = _rule()
    return (
        TableRow("SAC + MLP, static QoS", _SAC, _MLP, _STATIC, 1.00, 1.00),
        TableRow("SAC + MLP, rule QoS", _SAC, _MLP, rule),
        TableRow(
            "SAC + MLP, SAC QoS",
            _SAC,
            _MLP,
            ComponentSpec("learned", "checkpoints/stage_d/qos"),
            0.98,
            0.13,
        ),
        TableRow(
            "SAC, no estimator, SAC QoS",
            _SAC,
            ComponentSpec("none"),
            ComponentSpec("learned", "checkpoints/stage_c_none"),
            0.78,
            0.52,
        ),
        TableRow("MPC + predictor, static QoS", _MPC, _PREDICTOR, _STATIC),
        TableRow("MPC + predictor, rule QoS", _MPC, _PREDICTOR, rule),
        TableRow(
            "MPC + predictor, SAC QoS",
            _MPC,
            _PREDICTOR,
            ComponentSpec("learned", "checkpoints/stage_c_mpc"),
        ),
        TableRow("MPC, no estimator, rule QoS", _MPC, ComponentSpec("none"), rule),
        TableRow("SAC + predictor, static QoS", _SAC, _PREDICTOR, _STATIC),
        TableRow("SAC + predictor, rule QoS", _SAC, _PREDICTOR, rule),
        TableRow("MPC + MLP, static QoS", _MPC, _MLP, _STATIC),
        TableRow("MPC + MLP, rule QoS", _MPC, _MLP, rule),
    )


PIPELINES: dict[str, Callable[[], tuple[TableRow, ...]]] = {
    "model-free": model_free_rows,
    "model-based": model_based_rows,
    "all": all_rows,
}
"""Pipeline name -> its default rows."""

PIPELINE_PLANTS: dict[str, tuple[str, ...]] = {
    "model-free": ("0.2",),
    "model-based": ("0.2",),
    "all": ("0.2", "0.6", "variable"),
}
"""Pipeline name -> its default plants (keys of :data:`PLANT_PRESETS`); the paper's Table I
is at 0.2 m/s."""

_LEARNED_CONTROLLERS = ("sac",)
_LEARNED_ESTIMATORS = ("mlp", "lstm")
_MODEL_BASED = ("mpc", "predictor", "scripted", "toy_pick")


def stack_of(row: TableRow) -> str:
    """``"model-free"`` (learned controller, learned or no estimator), ``"model-based"`` (a
    model-based controller with a model-based or no estimator) or ``"mixed"``."""
    c, e = row.controller.kind, row.estimator.kind
    no_estimator = e == "none"
    if c in _LEARNED_CONTROLLERS and (e in _LEARNED_ESTIMATORS or no_estimator):
        return "model-free"
    if c in _MODEL_BASED and (e in _MODEL_BASED or no_estimator):
        return "model-based"
    return "mixed"


# -- config -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class TableConfig:
    """What ``codesign table`` evaluates.

    Parameters
    ----------
    plants:
        The plants: names of :data:`PLANT_PRESETS` (``"0.2"``, ``"0.6"``, ``"variable"``) or
        :class:`TablePlant` tables; empty means the pipeline's (:data:`PIPELINE_PLANTS`).
    plant:
        One plant instead of ``plants`` (labelled from its options; kept for older configs).
    rows:
        The rows; empty means the default rows of ``pipeline``.
    pipeline:
        A key of :data:`PIPELINES`.
    trials:
        Episodes per row and plant (the same seeds for every row and plant).
    seed:
        Root seed of the episodes.
    workers:
        Worker processes, shared by all rows and plants.
    timeline_row:
        Row whose successful episode is plotted (Fig. 5); ``""``: see
        :func:`timeline_row_name`.
    best_min_success:
        Success rate a row needs to be the best one (:func:`best_row`).
    on_missing:
        ``"skip"``: a row with a missing checkpoint is listed with its ``status`` and no
        figures; ``"error"``: the run stops before any episode, naming every missing one.
    """

    plants: tuple[TablePlant | str, ...] = ()
    plant: PlantSpec | None = None
    rows: tuple[TableRow, ...] = ()
    pipeline: str = "model-free"
    trials: int = 100
    seed: int = 0
    workers: int = 1
    timeline_row: str = ""
    best_min_success: float = 0.98
    on_missing: str = "skip"

    def __post_init__(self) -> None:
        if self.pipeline not in PIPELINES:
            raise ValueError(
                f"pipeline must be one of {', '.join(PIPELINES)}, got {self.pipeline!r}"
            )
        if self.trials < 1:
            raise ValueError(f"trials must be >= 1, got {self.trials}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if not 0.0 <= self.best_min_success <= 1.0:
            raise ValueError(f"best_min_success must be in [0, 1], got {self.best_min_success}")
        if self.on_missing not in ("skip", "error"):
            raise ValueError(f"on_missing must be 'skip' or 'error', got {self.on_missing!r}")
        if self.plant is not None and self.plants:
            raise ValueError("give plants or plant, not both")
        if isinstance(self.plant, Mapping):
            object.__setattr__(self, "plant", from_mapping(PlantSpec, self.plant, where="plant"))
        object.__setattr__(self, "plants", tuple(_plant(p, i) for i, p in enumerate(self.plants)))
        rows = tuple(
            r if isinstance(r, TableRow) else from_mapping(TableRow, r, where=f"rows[{i}]")
            for i, r in enumerate(self.rows)
        )
        object.__setattr__(self, "rows", rows)
        names = [r.name for r in self.table_rows()]
        if len(set(names)) != len(names):
            raise ValueError(f"row names must be unique, got {names}")
        if self.timeline_row and self.timeline_row not in names:
            raise ValueError(f"timeline_row {self.timeline_row!r} is not a row: {names}")
        labels = [p.label for p in self.table_plants()]
        if len(set(labels)) != len(labels):
            raise ValueError(f"plant labels must be unique, got {labels}")

    def table_rows(self) -> tuple[TableRow, ...]:
        return self.rows or PIPELINES[self.pipeline]()

    def table_plants(self) -> tuple[TablePlant, ...]:
        if self.plant is not None:
            return (TablePlant.of(self.plant),)
        if self.plants:
            return self.plants  # type: ignore[return-value]  # normalised in __post_init__
        return tuple(PLANT_PRESETS[k] for k in PIPELINE_PLANTS[self.pipeline])


def _plant(value: Any, index: int) -> TablePlant:
    if isinstance(value, TablePlant):
        return value
    if isinstance(value, str):
        if value not in PLANT_PRESETS:
            raise ValueError(
                f"plants[{index}] must be one of {', '.join(PLANT_PRESETS)} or a table with a "
                f"label, got {value!r}"
            )
        return PLANT_PRESETS[value]
    if isinstance(value, Mapping):
        return from_mapping(TablePlant, value, where=f"plants[{index}]")
    raise ValueError(f"plants[{index}] must be a name or a table, got {value!r}")


# -- checkpoints and training cost ------------------------------------------------------------
def _specs(row: TableRow) -> tuple[tuple[str, ComponentSpec], ...]:
    return (("controller", row.controller), ("estimator", row.estimator), ("qos", row.qos))


def missing_checkpoints(row: TableRow) -> list[str]:
    """The checkpoints ``row`` names that do not exist (a QoS folder needs its policy files)."""
    missing = []
    for _, spec in _specs(row):
        if not spec.checkpoint:
            continue
        try:
            path = resolve_checkpoint(spec.checkpoint)
        except ValueError:
            missing.append(spec.checkpoint)
            continue
        if spec.kind == "learned" and not all(
            (path / f).is_file() for f in ("model.zip", "qos_policy.json")
        ):
            missing.append(f"{spec.checkpoint} (no model.zip + qos_policy.json)")
    return missing


@dataclass(frozen=True)
class TrainingCost:
    """What it took to train a row's learned components (see :func:`training_cost`)."""

    env_steps: int
    wall_time_s: float
    sources: tuple[str, ...]
    unknown: tuple[str, ...] = ()


def _display(path: Path) -> str:
    try:
        return str(path.relative_to(models_dir()))
    except ValueError:
        return str(path)


def training_cost(row: TableRow) -> TrainingCost:
    """Env steps and wall time of every training run behind ``row``'s learned components.

    For each learned checkpoint (file: its folder's ``training.json``; folder: its own), the
    ``env_steps`` (plus the ``demonstrations.demo_steps`` of stage A) and ``wall_time_s``
    recorded there are counted, then the checkpoints its ``config`` names (``controller``,
    ``estimator``, ``warm_start``, ``qos_policy``), recursively; every file is counted once.
    The estimator of a stage-D folder counts the folder's ``estimator`` section only (its QoS
    policy has its own ``qos/training.json``). Model-based components count 0; the covariance
    rule's threshold was tuned by bisection offline, which is not recorded and counts 0 (named
    in ``sources``). Checkpoints without a ``training.json`` are listed in ``unknown`` (the
    sums are then lower bounds).
    """
    todo = [(role, spec.checkpoint) for role, spec in _specs(row) if spec.checkpoint]
    seen: dict[tuple[str, str], tuple[int, float, str]] = {}
    unknown: list[str] = []
    while todo:
        role, checkpoint = todo.pop(0)
        try:
            path = resolve_checkpoint(checkpoint)
        except ValueError:
            unknown.append(str(checkpoint))
            continue
        meta_path = path / "training.json" if path.is_dir() else path.parent / "training.json"
        if not meta_path.is_file():
            unknown.append(str(checkpoint))
            continue
        meta = json.loads(meta_path.read_text())
        section, part, label = meta, "", _display(meta_path.parent)
        sub = meta.get("estimator")
        if role == "estimator" and isinstance(sub, Mapping) and "env_steps" in sub:
            section, part, label = sub, "estimator", f"{label} (estimator)"
        key = (str(meta_path), part)
        if key in seen:
            continue
        steps = int(section.get("env_steps") or 0)
        if section is meta and isinstance(meta.get("demonstrations"), Mapping):
            steps += int(meta["demonstrations"].get("demo_steps") or 0)
        wall = section.get("wall_time_s")
        seen[key] = (steps, math.nan if wall is None else float(wall), label)
        config = meta.get("config")
        if not isinstance(config, Mapping):
            continue
        for sub_role in ("controller", "estimator"):
            ref = config.get(sub_role)
            if isinstance(ref, Mapping) and ref.get("checkpoint"):
                todo.append((sub_role, str(ref["checkpoint"])))
        for ref_key in ("warm_start", "qos_policy"):
            ref = config.get(ref_key)
            if isinstance(ref, str) and ref:
                todo.append(("qos", ref))
    sources = [label for _, _, label in seen.values()]
    if any(spec.kind == "rule" for _, spec in _specs(row)):
        sources.append("rule threshold (bisection offline, not counted)")
    return TrainingCost(
        env_steps=sum(s for s, _, _ in seen.values()),
        wall_time_s=float(sum(w for _, w, _ in seen.values())),
        sources=tuple(sources),
        unknown=tuple(dict.fromkeys(unknown)),
    )


# -- CPU time per step ------------------------------------------------------------------------
class _Timed:
    """Forwards to a component, summing the CPU time of its per-step method."""

    method = ""
    role = ""

    def __init__(self, inner: Any) -> None:
        self._inner = inner
        self._ns = 0
        self._calls = 0

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._inner, name)

    def reset(self, *args: Any, **kwargs: Any) -> Any:
        self._ns = self._calls = 0
        return self._inner.reset(*args, **kwargs)

    def _call(self, *args: Any) -> Any:
        start = time.process_time_ns()
        out = getattr(self._inner, self.method)(*args)
        self._ns += time.process_time_ns() - start
        self._calls += 1
        return out

    def episode_metrics(self) -> dict[str, float]:
        inner = getattr(self._inner, "episode_metrics", None)
        out = dict(inner()) if callable(inner) else {}
        out[f"{self.role}_cpu_ms"] = self._ns / 1e6 / self._calls if self._calls else math.nan
        return out


class _TimedController(_Timed):
    method, role = "act", "controller"

    def act(self, *args: Any) -> Any:
        return self._call(*args)


class _TimedEstimator(_Timed):
    method, role = "estimate", "estimator"

    def estimate(self, *args: Any) -> Any:
        return self._call(*args)


class _TimedQos(_Timed):
    method, role = "request", "qos"

    def request(self, *args: Any) -> Any:
        return self._call(*args)


_TIMED = {"controller": _TimedController, "estimator": _TimedEstimator, "qos": _TimedQos}


def _timed_component(env: Any, *, role: str, inner: Any) -> Any:
    """Build ``inner`` (a factory) for ``env`` and time its per-step method (a Factory target)."""
    return _TIMED[role](inner(env))


def _timed_factory(role: str, spec: ComponentSpec) -> Any:

    return Factory(
        "codesign_mb.studies.table:_timed_component",
        {"role": role, "inner": factory(role, spec)},
        takes_env=True,
    )


# -- the run ----------------------------------------------------------------------------------
def pareto_front(success: ArrayLike, reliability: ArrayLike) -> NDArray[np.bool_]:
    """Which points no other point dominates (more success for no more network, or less).

    ``j`` dominates ``i`` when ``success[j] >= success[i]`` and ``reliability[j] <=
    reliability[i]``, one of them strictly; equal points do not dominate each other. NaN
    points are never on the front and dominate nothing.
    """
    s = np.asarray(success, dtype=float)
    r = np.asarray(reliability, dtype=float)
    if s.shape != r.shape or s.ndim != 1:
        raise ValueError(
            f"success and reliability must be 1-D of one length, got {s.shape}, {r.shape}"
        )
    front = np.zeros(s.shape, dtype=bool)
    valid = np.flatnonzero(np.isfinite(s) & np.isfinite(r))
    best_below = -np.inf  # best success among strictly smaller reliabilities
    for level in np.unique(r[valid]):
        group = valid[r[valid] == level]
        top = s[group].max()
        front[group] = (s[group] == top) & (top > best_below)
        best_below = max(best_below, top)
    return front


def best_row(summary: pd.DataFrame, plant: str, *, min_success: float = 0.98) -> str | None:
    """The row of ``plant`` with the least average reliability among those with at least
    ``min_success``; if none, the most successful (ties: less reliability). ``None`` if no row
    of ``plant`` was evaluated."""
    mine = summary[(summary["plant"] == plant) & (summary["status"] == "ok")]
    if mine.empty:
        return None
    good = mine[mine["success_rate"] >= min_success - 1e-12]
    if not good.empty:
        pick = good.sort_values(
            ["mean_requested_reliability", "success_rate"], ascending=[True, False], kind="stable"
        )
    else:
        pick = mine.sort_values(
            ["success_rate", "mean_requested_reliability"], ascending=[False, True], kind="stable"
        )
    return str(pick.iloc[0]["row"])


PIPELINE_TIMELINE: dict[str, str] = {
    "model-free": "MLP estimator, dynamic QoS (co-design)",
    "model-based": "MPC + predictor, rule QoS (co-design)",
}
"""Pipeline name -> the row of its Fig. 5 (the co-design, as in the paper) with its default
rows; other tables plot :func:`best_row`."""


def timeline_row_name(config: TableConfig, summary: pd.DataFrame) -> str | None:
    """The row Fig. 5 shows: ``config.timeline_row``, else the pipeline's co-design row
    (:data:`PIPELINE_TIMELINE`, default rows only), else :func:`best_row` on the first plant."""
    if config.timeline_row:
        return config.timeline_row
    if not config.rows and config.pipeline in PIPELINE_TIMELINE:
        return PIPELINE_TIMELINE[config.pipeline]
    first = config.table_plants()[0].label
    return best_row(summary, first, min_success=config.best_min_success)


def run_table(
    config: TableConfig, *, progress: Callable[..., Any] | None = None
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Evaluate every row on every plant; return the summary and all episodes.

    Rows with a missing checkpoint are skipped with a ``RuntimeWarning`` and a ``status``
    (``on_missing="skip"``) or raise ``ValueError`` naming them all (``"error"``). The
    summary has one row per (plant, row) in the config's order (see the module docstring);
    the episodes table one row per episode, with ``plant`` and ``row``.
    """

    rows, plants = config.table_rows(), config.table_plants()
    missing = {row.name: missing_checkpoints(row) for row in rows}
    missing = {name: paths for name, paths in missing.items() if paths}
    if missing and config.on_missing == "error":
        listed = "; ".join(f"{name!r}: {', '.join(paths)}" for name, paths in missing.items())
        raise ValueError(
            f"missing checkpoints ({listed}); train them with `codesign train`, or run with "
            "--on-missing skip"
        )
    for name, paths in missing.items():
        warnings.warn(
            f"row {name!r} skipped: missing checkpoint {', '.join(paths)}",
            RuntimeWarning,
            stacklevel=2,
        )
    ready = [row for row in rows if row.name not in missing]
    costs = {row.name: training_cost(row) for row in ready}
    cells = [(plant, row) for plant in plants for row in ready]
    jobs = [
        (
            _timed_factory("controller", row.controller),
            _timed_factory("estimator", row.estimator),
            _timed_factory("qos", row.qos),
            plant_factory(plant.spec),
            config.trials,
            config.seed,
        )
        for plant, row in cells
    ]
    results: list[list[dict[str, Any]]] = [[] for _ in cells]
    if jobs:
        done = run_jobs(jobs, workers=config.workers)
        if progress is not None:
            done = progress(done, total=len(jobs) * config.trials, description="table episodes")
        for j, episode in done:
            results[j].append(episode)

    summaries, episodes = [], []
    by_cell = {(p.label, r.name): i for i, (p, r) in enumerate(cells)}
    for plant in plants:
        for row in rows:
            record: dict[str, Any] = {
                "row": row.name,
                "plant": plant.label,
                "pipeline": stack_of(row),
                "controller": row.controller.kind,
                "estimator": row.estimator.kind,
                "qos": row.qos.kind,
                "status": "ok",
            }
            i = by_cell.get((plant.label, row.name))
            if i is None:
                record["status"] = f"missing checkpoint: {', '.join(missing[row.name])}"
                record.update(trials=0, successes=0)
                record.update({c: math.nan for c in _NUMBERS})
                record.update(train_env_steps=math.nan, train_wall_time_s=math.nan)
                record.update(train_sources="")
            else:
                table = rows_to_table(results[i])
                summary = summarize(table)
                cost = costs[row.name]
                record.update(
                    {
                        "trials": summary["trials"],
                        "successes": summary["successes"],
                        **{c: summary.get(c, math.nan) for c in _SUMMARY},
                        "train_env_steps": cost.env_steps,
                        "train_wall_time_s": cost.wall_time_s,
                        "train_sources": ", ".join(cost.sources)
                        + (f" (unknown: {', '.join(cost.unknown)})" if cost.unknown else ""),
                        **{c: float(table[c].mean()) for c in CPU_COLUMNS},
                        "eval_wall_time_s": float(table["wall_time_s"].sum()),
                    }
                )
                record["cpu_ms_per_step"] = float(sum(record[c] for c in CPU_COLUMNS))
                episodes.append(table.assign(plant=plant.label, row=row.name))
            record["paper_success_rate"] = row.paper_success_rate
            record["paper_mean_reliability"] = row.paper_mean_reliability
            summaries.append(record)
    summary_frame = pd.DataFrame(summaries)
    summary_frame["pareto"] = False
    for label in summary_frame["plant"].unique():
        mask = (summary_frame["plant"] == label).to_numpy()
        summary_frame.loc[mask, "pareto"] = pareto_front(
            summary_frame.loc[mask, "success_rate"],
            summary_frame.loc[mask, "mean_requested_reliability"],
        )
    episode_frame = (
        pd.concat(episodes, ignore_index=True)
        if episodes
        else pd.DataFrame(columns=["plant", "row"])
    )
    return summary_frame, episode_frame


_SUMMARY = (
    "success_rate",
    "success_ci_low",
    "success_ci_high",
    "mean_requested_reliability",
    "delivered_fraction",
    "mean_age",
    "mean_estimation_error",
)
_NUMBERS = (*_SUMMARY, *CPU_COLUMNS, "cpu_ms_per_step", "eval_wall_time_s")


# -- figures ----------------------------------------------------------------------------------
def qos_timeline(
    plant: TablePlant | PlantSpec, row: TableRow, episodes: pd.DataFrame
) -> tuple[pd.DataFrame, int] | None:
    """The per-step record of the row's first successful episode (and its seed), or ``None``.

    With a :class:`TablePlant`, only the episodes of that plant (column ``plant``) count.
    """

    if episodes.empty:
        return None
    mask = episodes["row"] == row.name
    spec = plant
    if isinstance(plant, TablePlant):
        spec = plant.spec
        if "plant" in episodes:
            mask &= episodes["plant"] == plant.label
    mine = episodes[mask & episodes["success"].astype(bool)]
    if mine.empty:
        return None
    seed = int(mine.sort_values("episode").iloc[0]["seed"])
    probe = make_plant(spec)
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
    from matplotlib.figure import Figure  # no pyplot: no global figure state

    fig = Figure(figsize=(7.0, 3.2), layout="constrained")
    ax = fig.subplots()
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
    return _save(fig, path)


_QOS_COLOURS = {"static": "tab:blue", "rule": "tab:green", "learned": "tab:red"}
_PAIR_MARKERS = {
    ("sac", "mlp"): "o",
    ("sac", "lstm"): "o",
    ("sac", "none"): "v",
    ("mpc", "predictor"): "s",
    ("mpc", "none"): "D",
    ("sac", "predictor"): "^",
    ("mpc", "mlp"): "P",
    ("mpc", "lstm"): "P",
}
_SPARE_MARKERS = ("X", "*", "h", "<", ">", "p", "d")


def plot_pareto(summary: pd.DataFrame, path: str | Path, *, title: str = "") -> Path:
    """Success versus average requested reliability, one panel per plant (PNG).

    Every evaluated row is a point with its 95 % Wilson interval: the colour is its QoS policy
    (static blue, rule green, SAC red), the marker its controller and estimator (the same in
    every panel); the Pareto-optimal ones (column ``pareto``) are ringed and joined by the
    front (dashed).
    """
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    plants = list(dict.fromkeys(summary["plant"]))
    markers = dict(_PAIR_MARKERS)
    other_colours = iter(("tab:purple", "tab:orange", "tab:brown", "tab:pink", "tab:olive"))
    colours = dict(_QOS_COLOURS)
    fig = Figure(figsize=(4.6 * max(len(plants), 1), 4.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, max(len(plants), 1), sharey=True))
    handles: dict[str, Any] = {}
    for ax, plant in zip(axes, plants, strict=False):
        mine = summary[(summary["plant"] == plant) & (summary["status"] == "ok")]
        for _, r in mine.iterrows():
            pair = (str(r["controller"]), str(r["estimator"]))
            if pair not in markers:
                markers[pair] = _SPARE_MARKERS[len(markers) % len(_SPARE_MARKERS)]
            if r["qos"] not in colours:
                colours[r["qos"]] = next(other_colours, "tab:gray")
            x, y = r["mean_requested_reliability"], r["success_rate"]
            ax.errorbar(
                x,
                y,
                yerr=[[y - r["success_ci_low"]], [r["success_ci_high"] - y]],
                fmt=markers[pair],
                color=colours[r["qos"]],
                mfc=colours[r["qos"]] if r["pareto"] else "white",
                ms=7,
                capsize=2,
                lw=0.8,
                alpha=0.9,
            )
            handles.setdefault(
                str(r["row"]),
                Line2D([], [], ls="", marker=markers[pair], color=colours[r["qos"]], mfc="white"),
            )
            if bool(r["pareto"]):
                ax.plot(x, y, "o", ms=15, mfc="none", mec="black", mew=1.0)
        front = mine[mine["pareto"].astype(bool)].sort_values("mean_requested_reliability")
        if len(front):
            ax.step(
                front["mean_requested_reliability"],
                front["success_rate"],
                where="post",
                color="black",
                lw=0.8,
                ls="--",
            )
        skipped = int((summary["plant"] == plant).sum() - len(mine))
        ax.set_title(f"{plant}" + (f" ({skipped} rows not run)" if skipped else ""), fontsize=9)
        ax.set_xlabel("average requested reliability (PDR)")
        ax.set_xlim(-0.03, 1.05)
        ax.set_ylim(-0.03, 1.05)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate (95 % Wilson interval)")
    ring = Line2D([], [], ls="", marker="o", ms=10, mfc="none", mec="black")
    fig.legend(
        [*handles.values(), ring],
        [*handles.keys(), "Pareto-optimal (filled and ringed; dashed: the front)"],
        loc="outside lower center",
        ncols=min(4, len(handles) + 1),
        fontsize=7,
    )
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def _save(fig: Any, path: str | Path) -> Path:

    path = Path(path)
    with atomic_write(path) as fh:
        fig.savefig(fh, format="png", dpi=120)
    return path


def markdown_table(summary: pd.DataFrame) -> str:
    """The summary as a Markdown table (percentages, interval, training cost, CPU per step)."""

    def pct(v: float) -> str:
        return "" if not np.isfinite(v) else f"{100 * v:.0f} %"

    lines = [
        "| plant | row | success (95 % CI) | avg. requested reliability | delivered | "
        "training (env steps, wall) | CPU ms/step | Pareto | paper (success / PDR) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for _, r in summary.iterrows():
        paper = ""
        if r["paper_success_rate"] is not None and np.isfinite(r["paper_success_rate"]):
            paper = f"{pct(r['paper_success_rate'])} / {pct(r['paper_mean_reliability'])}"
        if r["status"] != "ok":
            lines.append(f"| {r['plant']} | {r['row']} | {r['status']} | | | | | | {paper} |")
            continue
        steps, wall = r["train_env_steps"], r["train_wall_time_s"]
        cost = "0" if steps == 0 else f"{int(steps):,} steps, {wall / 60:.0f} min"
        lines.append(
            f"| {r['plant']} | {r['row']} | {pct(r['success_rate'])} "
            f"[{100 * r['success_ci_low']:.1f}, {100 * r['success_ci_high']:.1f}] | "
            f"{pct(r['mean_requested_reliability'])} | {pct(r['delivered_fraction'])} | {cost} | "
            f"{r['cpu_ms_per_step']:.2f} | {'yes' if r['pareto'] else ''} | {paper} |"
        )
    return "\n".join(lines) + "\n"
