"""The ``conveyor`` sweep scenario: Table I's pipelines on the MuJoCo pick-and-place, in a grid.

One trial (``codesign sweep --scenario conveyor``) runs ``Params.episodes`` seeded episodes of
:class:`~codesign_mb.plants.conveyor.ConveyorPickPlace` at the grid's belt speed, with one
pipeline: a ``{controller, estimator, qos}`` row of :mod:`codesign_mb.studies.table_rows`, so the
components (options, checkpoints) are exactly those of ``codesign table``. A sweep pipeline
names its row by component kinds (:data:`PIPELINE_KINDS`), looked up in ``model_free_rows()``,
``model_based_rows()`` and ``all_rows()`` (row names change, kinds do not); :data:`PIPELINES`
holds those the table has. Episodes are evaluated by
:func:`codesign_mb.evaluation.evaluate.evaluate` (in the trial's process: the sweep
parallelises over trials); episode ``i`` of a trial of seed ``s`` gets
``episode_seeds(s, episodes)[i]``.

Robot count: how ``n`` robots share one channel is ``Params.link``:

``"bernoulli"`` (default)
    The paper's abstract link (``eq_d``) with the channel's capacity shared as in the
    ``linear`` scenario: the cell serves ``capacity_robots`` robots at the reliability they
    request and spreads the losses evenly beyond, so each packet is delivered with probability
    ``q_t * min(1, capacity_robots / n)`` (:func:`channel_share`). The default capacity, 6, is
    the WiFi simulator's ``"paper"`` cell (:data:`codesign_mb.studies.fig_wifi.CHANNEL_PRESETS`):
    at ``q = 1`` its greedy scheduler delivers every frame of 6 robots, 80 % of 7, 15 % of 8.
    Robots are then independent and exchangeable, so one robot is simulated per episode. The
    model ignores that robots asking for less (an adaptive QoS) leave airtime to the others:
    the requested ``q_t`` is capped, not the load; use ``"wifi"`` for that.
``"wifi"``
    ``n`` robots in lockstep on one simulated WiFi 6 cell (``channel`` preset, ``scheduler``),
    via :func:`codesign_mb.studies.fig_wifi.run_point`; success is the fraction of robots that
    succeeded. Costs ``n`` episodes per episode. The cell cannot deliver with ``tau = 0`` (a
    learned QoS policy that learned its latency may ask for it: the trial then fails).

Metrics (one row per trial): ``success_rate`` (fraction of episodes, or of robot-episodes on
``"wifi"``, whose object was lifted and held: the paper's ``J``), ``episodes``,
``mean_reliability`` (requested ``q``: the paper's "average PDR"), ``channel_share`` (the
``"bernoulli"`` cap, NaN on ``"wifi"``), ``delivered_fraction`` (packets delivered, on
``"wifi"`` frames arrived, per step), ``mean_age`` (steps), ``mean_estimation_error`` (m),
``steps`` (mean per episode), and the timings (:data:`TIMING_COLUMNS`, which vary from run to
run): ``mpc_solve_cpu_ms_median`` (median over episodes of the MPC's per-solve CPU time; NaN
without MPC) and the trial's ``cpu_time_s`` (this process's CPU time, so the first trial of a
worker includes building the solver) and ``wall_time_s``. Columns a link does not measure are
NaN.

Learned pipelines need their checkpoints (``models/checkpoints/...``); a missing one fails the
trial with a ``ValueError`` naming the pipeline and the file, before anything is simulated.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from numpy.typing import ArrayLike

from codesign_mb.core.config import EPISODES_CAP, check_range, from_mapping
from codesign_mb.core.registry import PlantSpec, factory, plant_factory
from codesign_mb.evaluation.evaluate import evaluate, summarize
from codesign_mb.network.link import BernoulliLink, Reception
from codesign_mb.network.qos import QosRequest
from codesign_mb.plants.conveyor import ConveyorConfig
from codesign_mb.plants.scenarios import SCENARIOS as CONVEYOR_SCENARIOS
from codesign_mb.plants.scenarios import scenario_options
from codesign_mb.studies.fig_wifi import CHANNEL_PRESETS, CapacityConfig, PipelineConfig, run_point
from codesign_mb.studies.table_rows import (
    HYBRID_CODESIGN_ROW,
    MODEL_FREE_CODESIGN_ROW,
    all_rows,
    model_based_rows,
    model_free_rows,
    row_for_plant,
)
from codesign_mb.wifi.config import SCHEDULERS

__all__ = [
    "DEFAULT_PIPELINES",
    "LINKS",
    "PIPELINES",
    "PIPELINE_KINDS",
    "TIMING_COLUMNS",
    "Params",
    "SharedBernoulliLink",
    "channel_share",
    "pipeline_row",
    "plant_options",
    "run_trial",
]

PIPELINE_KINDS: dict[str, tuple[str, str, str]] = {
    "model-based-static": ("mpc", "predictor", "static"),
    "model-based-rule": ("mpc", "predictor", "rule"),
    "model-based-learned-qos": ("mpc", "predictor", "learned"),
    "model-based-no-estimator": ("mpc", "none", "rule"),
    "model-free-static": ("sac", "lstm", "static"),
    "model-free-codesign": ("sac", "lstm", "learned"),
    "hybrid-codesign": ("sac", "mlp", "learned"),
    "sac-mlp-rule": ("sac", "mlp", "rule"),
    "model-free-no-estimator": ("sac", "none", "learned"),
    "sac-predictor-static": ("sac", "predictor", "static"),
    "sac-predictor-rule": ("sac", "predictor", "rule"),
    "mpc-mlp-static": ("mpc", "mlp", "static"),
    "mpc-mlp-rule": ("mpc", "mlp", "rule"),
}
"""Sweep pipeline name -> ``(controller, estimator, qos)`` kinds of its table row.
The covariance rule's threshold is the one tuned for the sweep's conveyor scenario at its own
belt speed (:func:`~codesign_mb.studies.table_rows.row_for_plant`, the default when it has
none), held fixed across the grid: a grid point is the same design on another plant.
``model-free-codesign`` is SAC (stage A) + LSTM + the learned QoS policy (stage D) that reads
``(y, zeta)`` and ``held_history``; ``hybrid-codesign`` the MLP one whose QoS policy
reads ``predictor_std`` (:data:`PIPELINE_ROW_NAMES`)."""

PIPELINE_ROW_NAMES: dict[str, str] = {
    "model-free-codesign": MODEL_FREE_CODESIGN_ROW,
    "hybrid-codesign": HYBRID_CODESIGN_ROW,
}
"""Pipelines whose kinds several table rows share: their row, by name."""


def _kinds(row: Any) -> tuple[str, str, str]:
    return (row.controller.kind, row.estimator.kind, row.qos.kind)


def _table_rows() -> tuple[Any, ...]:

    return (*model_free_rows(), *model_based_rows(), *all_rows())


PIPELINES: tuple[str, ...] = tuple(
    name
    for name, kinds in PIPELINE_KINDS.items()
    if any(_kinds(row) == kinds for row in _table_rows())
)
"""Pipelines this scenario accepts: those of :data:`PIPELINE_KINDS` the table has a row for."""

DEFAULT_PIPELINES: tuple[str, ...] = (
    "model-based-static",
    "model-based-rule",
    "model-free-static",
    "hybrid-codesign",
)
"""Pipelines swept when none are configured: both stacks, static QoS and co-design (the
learned one: the shipped hybrid until the model-free one is trained)."""

TIMING_COLUMNS: tuple[str, ...] = ("mpc_solve_cpu_ms_median", "cpu_time_s", "wall_time_s")
"""Columns that measure time: they vary from run to run, the rest is a function of the seed."""

LINKS: tuple[str, ...] = ("bernoulli", "wifi")
"""How robots share the channel (see the module docstring)."""

_GRID_PLANT_KEYS = ("belt_speed_mps", "horizon", "belt_profile")


@dataclass(frozen=True)
class Params:
    """Settings of the conveyor scenario (``[sweep.params]``, or ``--param key=value``).

    Attributes
    ----------
    episodes:
        Seeded episodes per trial (>= 1).
    horizon:
        Episode length ``T`` in control steps; ``None`` keeps the plant's (100).
    belt_profile:
        ``""`` (the conveyor scenario's), ``"constant"`` or ``"variable"``
        (:class:`~codesign_mb.plants.conveyor.ConveyorConfig`): the grid's belt speed is then
        the nominal one.
    plant_options:
        Other :class:`~codesign_mb.plants.conveyor.ConveyorConfig` fields (e.g. ``object``,
        ``perception_noise_std_m``), checked strictly; not the three above.
    link:
        ``"bernoulli"`` (capacity share of an abstract link) or ``"wifi"`` (the simulated
        WiFi 6 cell).
    capacity_robots:
        ``"bernoulli"``: robots the channel serves at their requested reliability (> 0).
    channel, scheduler:
        ``"wifi"``: a :data:`codesign_mb.studies.fig_wifi.CHANNEL_PRESETS` cell and a scheduler
        of :data:`codesign_mb.wifi.config.SCHEDULERS`.
    """

    episodes: int = 1
    horizon: int | None = None
    belt_profile: str = ""
    plant_options: dict[str, Any] = field(default_factory=dict)
    link: str = "bernoulli"
    capacity_robots: float = 6.0
    channel: str = "paper"
    scheduler: str = "greedy"

    def __post_init__(self) -> None:

        if isinstance(self.episodes, bool) or not isinstance(self.episodes, int):
            raise ValueError(f"episodes must be an integer, got {self.episodes!r}")
        check_range("episodes", self.episodes, ge=1, cap=EPISODES_CAP)
        if self.link not in LINKS:
            raise ValueError(f"link must be one of {', '.join(LINKS)}, got {self.link!r}")
        cap = self.capacity_robots
        if isinstance(cap, bool) or not isinstance(cap, int | float) or not math.isfinite(cap):
            raise ValueError(f"capacity_robots must be a number, got {cap!r}")
        if cap <= 0:
            raise ValueError(f"capacity_robots must be > 0, got {cap!r}")
        if not isinstance(self.plant_options, Mapping):
            raise ValueError(f"plant_options must be a table, got {self.plant_options!r}")
        reserved = [k for k in _GRID_PLANT_KEYS if k in self.plant_options]
        if reserved:
            raise ValueError(
                f"plant_options must not set {', '.join(map(repr, reserved))}: the belt speed "
                "is the sweep grid's, horizon and belt_profile are params of their own"
            )
        object.__setattr__(self, "plant_options", dict(self.plant_options))
        # Validates horizon, belt_profile and every plant option (at a belt speed of 0).
        from_mapping(ConveyorConfig, self.plant_options_at(0.0), where="params.plant_options")

        if self.channel not in CHANNEL_PRESETS:
            raise ValueError(
                f"channel must be one of {', '.join(CHANNEL_PRESETS)}, got {self.channel!r}"
            )
        if self.scheduler not in SCHEDULERS:
            raise ValueError(
                f"scheduler must be one of {', '.join(SCHEDULERS)}, got {self.scheduler!r}"
            )

    def plant_options_at(self, belt_speed_mps: float) -> dict[str, Any]:
        """The :class:`~codesign_mb.plants.conveyor.ConveyorConfig` fields of a grid point."""
        options: dict[str, Any] = {**self.plant_options, "belt_speed_mps": float(belt_speed_mps)}
        if self.belt_profile:
            options["belt_profile"] = self.belt_profile
        if self.horizon is not None:
            options["horizon"] = self.horizon
        return options


def plant_options(scenario: str, params: Params, belt_speed_mps: float) -> dict[str, Any]:
    """The conveyor's options at a grid point: the sweep scenario's preset, then ``params``.

    ``scenario`` is the sweep's: a conveyor scenario name
    (:data:`~codesign_mb.plants.scenarios.SCENARIOS`) or ``"conveyor"`` (= ``"paper"``). With
    a belt speed range (``realistic``) the grid's belt speed is the nominal one, what the robot
    assumes; the episode's speed is drawn from the range.
    """
    return {**scenario_options(_preset(scenario)), **params.plant_options_at(belt_speed_mps)}


def _preset(scenario: str) -> str:
    """The conveyor scenario of a sweep scenario name (``"conveyor"`` is ``"paper"``)."""
    return scenario if scenario in CONVEYOR_SCENARIOS else "paper"


def channel_share(params: Params, n_robots: int) -> float:
    """``min(1, capacity_robots / n)``: the fraction of its requested ``q`` each robot gets."""
    return min(1.0, params.capacity_robots / n_robots)


@dataclass
class SharedBernoulliLink:
    """A robot's :class:`~codesign_mb.network.link.BernoulliLink` on a shared channel.

    The packet sent with ``(q_t, tau_t)`` is delivered with probability ``share * q_t``
    (``eq_d`` with the capacity share of :func:`channel_share`), one uniform draw per step.

    Parameters
    ----------
    share:
        Fraction in [0, 1] of the requested reliability the channel delivers.
    """

    share: float = 1.0
    link: BernoulliLink = field(default_factory=BernoulliLink)

    def __post_init__(self) -> None:
        if not 0.0 <= self.share <= 1.0:
            raise ValueError(f"share must be in [0, 1], got {self.share!r}")

    def reset(self, *, seed: int | None = None, prior: ArrayLike | None = None) -> None:
        self.link.reset(seed=seed, prior=prior)

    def step(self, state: ArrayLike, qos: QosRequest) -> Reception:
        return self.link.step(state, QosRequest(self.share * qos.reliability, qos.latency_steps))


def pipeline_row(pipeline: str) -> Any:
    """The :class:`~codesign_mb.studies.table_rows.TableRow` of a sweep pipeline name.

    The row named in :data:`PIPELINE_ROW_NAMES`, else the first table row with the pipeline's
    kinds (other rows with the same kinds have the same components: the tests check it).
    """
    if pipeline not in PIPELINES:
        raise ValueError(f"pipeline must be one of {', '.join(PIPELINES)}, got {pipeline!r}")
    if pipeline in PIPELINE_ROW_NAMES:
        return next(row for row in _table_rows() if row.name == PIPELINE_ROW_NAMES[pipeline])
    kinds = PIPELINE_KINDS[pipeline]
    return next(row for row in _table_rows() if _kinds(row) == kinds)


def _factories(pipeline: str, row: Any) -> tuple[Any, Any, Any]:
    """``(controller, estimator, qos)`` factories; a missing checkpoint names the pipeline."""

    try:
        return (
            factory("controller", row.controller),
            factory("estimator", row.estimator),
            factory("qos", row.qos),
        )
    except ValueError as exc:
        raise ValueError(f"pipeline {pipeline!r} ({row.name}): {exc}") from None


def run_trial(config: Any, seed: int) -> dict[str, float | int]:
    """One trial of the conveyor scenario (see the module docstring); pure in ``seed``.

    ``config`` is a :class:`~codesign_mb.studies.sweep.TrialConfig` whose ``params`` is a
    :class:`Params`.
    """

    params: Params = config.params if config.params is not None else Params()
    preset = _preset(config.scenario)
    row = row_for_plant(
        pipeline_row(config.pipeline),
        PlantSpec("conveyor", scenario_options(preset)),
        scenario=preset,
    )
    components = _factories(config.pipeline, row)
    plant = PlantSpec("conveyor", plant_options(config.scenario, params, config.belt_speed_mps))
    cpu, wall = time.process_time(), time.perf_counter()
    if params.link == "bernoulli":
        metrics = _bernoulli_trial(params, plant, components, config.n_robots, seed)
    else:
        metrics = _wifi_trial(params, plant, row, config.pipeline, config.n_robots, seed)
    metrics["cpu_time_s"] = time.process_time() - cpu
    metrics["wall_time_s"] = time.perf_counter() - wall
    return metrics


def _bernoulli_trial(
    params: Params, plant: Any, components: tuple[Any, Any, Any], n_robots: int, seed: int
) -> dict[str, float | int]:

    share = channel_share(params, n_robots)
    controller, estimator, qos = components
    table = evaluate(
        controller,
        estimator,
        qos,
        plant_factory(plant),
        params.episodes,
        seed,
        link=SharedBernoulliLink(share),
        workers=1,
    )
    summary = summarize(table)
    return {
        "success_rate": float(summary["success_rate"]),
        "episodes": int(summary["trials"]),
        "mean_reliability": float(summary["mean_requested_reliability"]),
        "channel_share": share,
        "delivered_fraction": float(summary["delivered_fraction"]),
        "mean_age": float(summary["mean_age"]),
        "mean_estimation_error": float(summary["mean_estimation_error"]),
        "steps": float(summary["steps"]),
        "mpc_solve_cpu_ms_median": float(summary.get("mpc_solve_cpu_ms_median", math.nan)),
    }


def _wifi_trial(
    params: Params, plant: Any, row: Any, pipeline: str, n_robots: int, seed: int
) -> dict[str, float | int]:
    import numpy as np

    cfg = CapacityConfig(
        robots=(n_robots,),
        channels=(params.channel,),
        schedulers=(params.scheduler,),
        pipelines={pipeline: PipelineConfig(row.controller, row.estimator, row.qos)},
        plant=plant,
        trials=params.episodes,
        seed=seed,
    )
    points = [
        run_point(
            cfg,
            channel_name=params.channel,
            scheduler=params.scheduler,
            pipeline_name=pipeline,
            n_robots=n_robots,
            trial=k,
        )
        for k in range(params.episodes)
    ]

    def mean(key: str) -> float:
        return float(np.mean([p[key] for p in points]))

    return {
        "success_rate": mean("success_rate"),
        "episodes": params.episodes,
        "mean_reliability": mean("mean_reliability"),
        "channel_share": math.nan,
        "delivered_fraction": mean("delivered_fraction"),
        "mean_age": mean("mean_age"),
        "mean_estimation_error": math.nan,
        "steps": math.nan,
        "mpc_solve_cpu_ms_median": math.nan,
    }
