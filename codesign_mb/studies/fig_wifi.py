"""Fig. 6 (``fig_wifi``): task success versus number of robots sharing one WiFi 6 channel.

For each robot count ``N`` and each (pipeline, scheduler) pair, ``trials`` episodes run N
robots in lockstep on one :class:`~codesign_mb.wifi.cell.SharedChannel`; a trial's success
rate is the fraction of its robots whose task succeeded (``info["success"]`` at any step).
The *capacity* of a curve is the largest ``N`` up to which every simulated count has a mean
success of at least ``success_target`` (95 %).

The pipelines are configuration: a plant (:class:`~codesign_mb.core.registry.PlantSpec`)
and, per pipeline, a controller, an estimator and a QoS policy
(:class:`~codesign_mb.core.registry.ComponentSpec`), so learned pipelines (SAC, MLP
estimator, learned QoS) plug in by naming their kinds and checkpoints. Besides the kinds of
:mod:`codesign_mb.core.registry`, two model-based QoS rules of
:mod:`codesign_mb.adaptation.rules` are known here: ``"age_triggered"`` (``options``:
``low``, ``high``, ``max_age_steps``, ``latency_steps``) and ``"covariance_triggered"``
(``options``: ``threshold_m``, ``low``, ``high``, ``latency_steps``, ``lift_margin_m``,
``predictor_options``).

Named stacks (:data:`STACKS`) give the plant and the two pipelines of the figure:

``"conveyor"`` (default)
    The MuJoCo conveyor pick (:class:`~codesign_mb.plants.conveyor.ConveyorPickPlace`, belt
    at 0.6 m/s), MPC (:class:`~codesign_mb.control.mpc.MpcController`) and the
    delay-compensating predictor; ``static`` asks for ``q = 1, tau = 1`` always, ``codesign``
    uses the covariance-triggered rule (threshold 2 cm, ``q`` 0.1 or 1). Over the abstract
    link (48 episodes each) this stack succeeds 100 % at ``q = 1``, 81 % at ``q = 0.1`` and
    100 % with the rule, which asks for ``q = 0.17`` on average.
``"toy"``
    The kinematic toy conveyor (seconds per point, for tests and quick looks) with a static
    and an age-triggered QoS.

Channels (:data:`CHANNEL_PRESETS`): ``"paper"`` is a poor 40 MHz cell (every robot at MCS 1
with ``q0 = 0.9``, 3.2 us guard interval, Trigger and BlockAck frames at the 6 Mb/s basic
rate) in which one camera frame of 13,500 bytes takes about 5.5 ms of the whole channel and
its state frame's DL exchange about 0.4 ms more, so about 6 robots at ``q = 1`` fill the 40
ms period (the greedy scheduler delivers every frame to 6 robots, 80 % to 7, 15 % to 8);
``"better"`` uses link adaptation (MCS 0-11 for ``q0 = 0.95``,
0.8 us guard interval) with robots 5-20 m from the AP and 24 Mb/s control frames.

The figure and the files of ``codesign wifi capacity`` are in
:mod:`codesign_mb.studies.fig_wifi_figures`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.adaptation.rules import AgeTriggeredQos
from codesign_mb.core.config import (
    EPISODES_CAP,
    ROBOTS_CAP,
    STEPS_CAP,
    WORKERS_CAP,
    check_range,
    from_mapping,
)
from codesign_mb.core.records import RecordStore, digest
from codesign_mb.core.registry import (
    ComponentSpec,
    PlantSpec,
    build,
    check_options,
    factory,
    make_plant,
)
from codesign_mb.evaluation import pool
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.scenarios import scenario_options
from codesign_mb.rollout import rollout_shared
from codesign_mb.rollout.compose import covariance_rule
from codesign_mb.wifi.cell import SharedChannel
from codesign_mb.wifi.channel import ChannelConfig
from codesign_mb.wifi.config import SCHEDULERS, WifiConfig
from codesign_mb.wifi.mac import MacTiming
from codesign_mb.wifi.phy import PhyConfig

__all__ = [
    "CHANNEL_PRESETS",
    "QOS_RULES",
    "STACKS",
    "AgeTriggeredQos",
    "CapacityConfig",
    "PipelineConfig",
    "capacity_table",
    "describe_channel",
    "run_capacity",
    "run_point",
]


def _component(kind: str, options: Mapping[str, Any] | None = None) -> Any:

    return ComponentSpec(kind=kind, options=dict(options or {}))


@dataclass(frozen=True)
class PipelineConfig:
    """One robot stack: controller, estimator and QoS policy (``ComponentSpec`` tables)."""

    controller: Any = field(default_factory=lambda: _component("toy_pick"))
    estimator: Any = field(default_factory=lambda: _component("none"))
    qos: Any = field(
        default_factory=lambda: _component("static", {"reliability": 1.0, "latency_steps": 1})
    )

    def __post_init__(self) -> None:

        for name in ("controller", "estimator", "qos"):
            value = getattr(self, name)
            if isinstance(value, Mapping):
                object.__setattr__(self, name, from_mapping(ComponentSpec, value, where=name))
            elif not isinstance(value, ComponentSpec):
                raise ValueError(f"{name} must be a component table, got {value!r}")


_STATIC = {"kind": "static", "options": {"reliability": 1.0, "latency_steps": 1}}

STACKS: dict[str, dict[str, Any]] = {
    "conveyor": {
        "plant": {
            "name": "conveyor",
            "options": {"belt_speed_mps": 0.6},
        },
        "pipelines": {
            "static": {
                "controller": {"kind": "mpc"},
                "estimator": {"kind": "predictor"},
                "qos": _STATIC,
            },
            "codesign": {
                "controller": {"kind": "mpc"},
                "estimator": {"kind": "predictor"},
                "qos": {
                    "kind": "covariance_triggered",
                    "options": {"threshold_m": 0.02, "low": 0.1, "high": 1.0, "latency_steps": 1},
                },
            },
        },
    },
    "toy": {
        "plant": {"name": "toy"},
        "pipelines": {
            "static": {
                "controller": {"kind": "toy_pick"},
                "estimator": {"kind": "none"},
                "qos": _STATIC,
            },
            "codesign": {
                "controller": {"kind": "toy_pick"},
                "estimator": {"kind": "none"},
                "qos": {
                    "kind": "age_triggered",
                    "options": {"low": 0.3, "high": 1.0, "max_age_steps": 2, "latency_steps": 1},
                },
            },
        },
    },
}
"""Named (plant, pipelines) pairs for ``codesign wifi capacity --stack``."""

QOS_RULES: dict[str, Callable[..., Any]] = {
    "age_triggered": lambda env, **options: AgeTriggeredQos(**options),
    "covariance_triggered": covariance_rule,
}
"""QoS kinds known to the capacity study on top of ``pipeline.components.QOS_KINDS``."""

_RULE_SIGNATURES: dict[str, tuple[Callable[..., Any], bool]] = {
    "age_triggered": (AgeTriggeredQos, False),
    "covariance_triggered": (covariance_rule, True),
}
"""What each of :data:`QOS_RULES` calls, and whether with the plant: its options' schema."""

CHANNEL_PRESETS: dict[str, WifiConfig] = {
    # Poor channel: every robot at MCS 1 (QPSK 1/2) with q0 = 0.9, the long 3.2 us guard
    # interval (a factory hall's delay spread), basic-rate control frames at 6 Mb/s: a camera
    # frame takes ~5.5 ticks of the whole band and its DL exchange ~0.4, so static QoS (q = 1)
    # fills the 40 ms period with about 6 robots, as in the paper.
    "paper": WifiConfig(
        phy=PhyConfig(guard_interval_us=3.2, ul_guard_interval_us=3.2),
        channel=ChannelConfig(fixed_mcs=1, q0=0.9, rician_k_db=math.inf),
        mac=MacTiming(legacy_rate_mbps=6.0),
    ),
    # Better channel: link adaptation on a TGax path loss, robots 5-20 m from the AP.
    "better": WifiConfig(channel=ChannelConfig(q0=0.95, distance_range_m=(5.0, 20.0))),
}
"""Named cells for ``codesign wifi capacity --channels``."""


def describe_channel(name: str) -> str:
    """One line of PHY/MAC assumptions of a :data:`CHANNEL_PRESETS` cell (for figures)."""
    cfg = CHANNEL_PRESETS[name]
    ch, mac, phy = cfg.channel, cfg.mac, cfg.phy
    mcs = f"MCS {ch.fixed_mcs}" if ch.fixed_mcs is not None else f"MCS 0-{ch.max_mcs} adaptive"
    return (
        f"{phy.bandwidth_mhz} MHz, {mcs}, q0 = {ch.q0:g}, GI {phy.guard_interval_us:g} us, "
        f"control frames {mac.legacy_rate_mbps:g} Mb/s"
    )


@dataclass(frozen=True)
class CapacityConfig:
    """Settings of the capacity sweep (``codesign wifi capacity``).

    Parameters
    ----------
    robots:
        Robot counts ``N`` to simulate.
    robots_by_channel:
        Robot counts for some channels instead of ``robots`` (a better channel holds many
        more robots), e.g. ``{"better": [8, 16, 24, 32]}``.
    channels:
        Names of :data:`CHANNEL_PRESETS` to sweep (each gives one panel).
    schedulers:
        Allocators to compare (``"greedy"``, ``"convex"``).
    stack:
        Name of a :data:`STACKS` entry: the default plant and pipelines.
    pipelines:
        Robot stacks by name (``PipelineConfig`` tables); empty: the stack's.
    plant:
        The plant every robot runs (``PlantSpec`` table); ``None``: the stack's.
    scenario:
        A conveyor scenario (:data:`~codesign_mb.plants.scenarios.SCENARIOS`) every robot's
        conveyor runs instead of ``plant`` (stack ``conveyor`` only); ``""``: the stack's
        plant (``conveyor``: 0.6 m/s, otherwise the ``paper`` scenario).
    trials:
        Episodes per point.
    max_steps:
        Episode length cap in control steps (``None``: the plant's horizon).
    success_target:
        Success rate that defines a curve's capacity.
    seed:
        Root seed; trial ``k`` of every point uses the same spawned seed (common numbers).
    workers:
        Processes running points in parallel (1: in this process). The table does not depend
        on it.
    """

    robots: tuple[int, ...] = (1, 2, 4, 6, 8, 10)
    robots_by_channel: dict[str, tuple[int, ...]] = field(default_factory=dict)
    channels: tuple[str, ...] = ("paper", "better")
    schedulers: tuple[str, ...] = ("greedy", "convex")
    stack: str = "conveyor"
    pipelines: dict[str, PipelineConfig] = field(default_factory=dict)
    plant: Any = None
    scenario: str = ""
    trials: int = 4
    max_steps: int | None = None
    success_target: float = 0.95
    seed: int = 0
    workers: int = 1

    def __post_init__(self) -> None:

        def counts(name: str, value: Any) -> tuple[int, ...]:
            out = tuple(int(n) for n in value)
            if not out or any(n < 1 for n in out):
                raise ValueError(f"{name} must be integers >= 1, got {value!r}")
            check_range(name, out, cap=ROBOTS_CAP)
            return out

        object.__setattr__(self, "robots", counts("robots", self.robots))
        by_channel = {
            str(c): counts(f"robots_by_channel.{c}", v)
            for c, v in dict(self.robots_by_channel).items()
        }
        object.__setattr__(self, "robots_by_channel", by_channel)
        object.__setattr__(self, "channels", tuple(self.channels))
        object.__setattr__(self, "schedulers", tuple(self.schedulers))
        for name in ("channels", "schedulers"):
            if not getattr(self, name):
                raise ValueError(f"{name} must name at least one, got none")
        for c in (*self.channels, *by_channel):
            if c not in CHANNEL_PRESETS:
                raise ValueError(f"channels must be among {sorted(CHANNEL_PRESETS)}, got {c!r}")
        for s in self.schedulers:
            if s not in SCHEDULERS:
                raise ValueError(f"schedulers must be among {SCHEDULERS}, got {s!r}")
        if self.stack not in STACKS:
            raise ValueError(f"stack must be one of {sorted(STACKS)}, got {self.stack!r}")
        stack = STACKS[self.stack]
        pipelines = {}
        for name, value in (dict(self.pipelines) or stack["pipelines"]).items():
            pipelines[name] = (
                from_mapping(PipelineConfig, value, where=f"pipelines.{name}")
                if isinstance(value, Mapping)
                else value
            )
        object.__setattr__(self, "pipelines", pipelines)
        plant = self.plant if self.plant is not None else stack["plant"]
        if self.scenario:
            if self.plant is not None or self.stack != "conveyor":
                raise ValueError(
                    "scenario sets the conveyor's plant: give no plant, and stack conveyor"
                )
            plant = PlantSpec("conveyor", scenario_options(self.scenario))
        if isinstance(plant, Mapping):
            plant = from_mapping(PlantSpec, plant, where="plant")
        if not isinstance(plant, PlantSpec):
            raise ValueError(f"plant must be a table (name, options), got {plant!r}")
        object.__setattr__(self, "plant", plant)
        for name in ("trials", "workers"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1 or None, got {self.max_steps!r}")
        if not 0.0 < self.success_target <= 1.0:
            raise ValueError(f"success_target must be in (0, 1], got {self.success_target!r}")
        check_range("trials", self.trials, cap=EPISODES_CAP)
        check_range("workers", self.workers, cap=WORKERS_CAP)
        check_range("max_steps", self.max_steps, cap=STEPS_CAP)
        robots = sum(len(self.robots_of(c)) for c in self.channels)
        n_trials = robots * len(self.schedulers) * len(pipelines) * self.trials
        check_range("the number of trials of the sweep", n_trials, cap=EPISODES_CAP)
        for pipeline in pipelines.values():  # kinds, checkpoints and options, checked now
            for role in ("controller", "estimator", "qos"):
                spec = getattr(pipeline, role)
                if role == "qos" and spec.kind in QOS_RULES:
                    rule, takes_env = _RULE_SIGNATURES[spec.kind]
                    check_options(
                        f"qos kind {spec.kind!r}", rule, spec.options, takes_env=takes_env
                    )
                else:
                    factory(role, spec)

    def robots_of(self, channel: str) -> tuple[int, ...]:
        """Robot counts simulated on ``channel``."""
        return self.robots_by_channel.get(channel, self.robots)

    def points(self) -> list[dict[str, Any]]:
        """Every (channel, scheduler, pipeline, robots, trial) of the sweep, in grid order."""
        return [
            {"channel_name": c, "scheduler": s, "pipeline_name": p, "n_robots": n, "trial": k}
            for c in self.channels
            for s in self.schedulers
            for p in self.pipelines
            for n in self.robots_of(c)
            for k in range(self.trials)
        ]


def _build(role: str, spec: Any, env: Any) -> Any:
    if role == "qos" and spec.kind in QOS_RULES:
        return QOS_RULES[spec.kind](env, **dict(spec.options))

    return build(role, spec, env)


def run_point(
    config: CapacityConfig,
    *,
    channel_name: str,
    scheduler: str,
    pipeline_name: str,
    n_robots: int,
    trial: int,
) -> dict[str, Any]:
    """One trial of one point: N robots, one episode; returns success and network figures.

    With an MPC, ``mpc_failures`` is its failed solves summed over the N robots.
    """

    pipeline = config.pipelines[pipeline_name]
    channel = SharedChannel(CHANNEL_PRESETS[channel_name], n_robots, scheduler=scheduler)
    envs, estimators, controllers = [], [], []
    for i in range(n_robots):
        plant = make_plant(config.plant)
        qos = _build("qos", pipeline.qos, plant)
        envs.append(LinkObservationWrapper(plant, channel.links[i], qos))
        estimators.append(_build("estimator", pipeline.estimator, plant))
        controllers.append(_build("controller", pipeline.controller, plant))
    seed = int(np.random.SeedSequence([config.seed, trial]).generate_state(1)[0])
    tables = rollout_shared(
        envs, estimators, controllers, channel=channel, seed=seed, max_steps=config.max_steps
    )
    for env in envs:
        env.close()
    successes = [bool(t["success"].any()) if "success" in t else False for t in tables]
    summary = channel.summary()
    ages = [float(t["age"].mean()) for t in tables if len(t)]
    row = {
        "channel": channel_name,
        "scheduler": scheduler,
        "pipeline": pipeline_name,
        "robots": n_robots,
        "trial": trial,
        "success_rate": float(np.mean(successes)),
        "mean_reliability": float(np.nanmean(summary["mean_reliability"])),
        "delivered_fraction": float(summary["delivered"].sum() / max(summary["steps"].sum(), 1)),
        "late_frames": int(summary["late"].sum()),
        "mean_age": float(np.mean(ages)) if ages else float("nan"),
        "mean_latency_ms": float(np.nanmean(summary["mean_latency_ms"]))
        if summary["delivered"].sum()
        else float("nan"),
        # ticks whose convex QP failed and were rounded from zero service (never silent)
        "allocator_fallbacks": int(channel.fallbacks.total),
    }
    failures = [
        m["mpc_failures"] for m in map(_episode_metrics, controllers) if "mpc_failures" in m
    ]
    if failures:  # an MPC: its failed solves, summed over the robots
        row["mpc_failures"] = int(sum(failures))
    return row


def _episode_metrics(component: Any) -> dict[str, Any]:
    metrics = getattr(component, "episode_metrics", None)
    return dict(metrics()) if callable(metrics) else {}


def _run_point_kwargs(args: tuple[CapacityConfig, dict[str, Any]]) -> dict[str, Any]:
    config, kwargs = args
    return run_point(config, **kwargs)


def run_capacity(
    config: CapacityConfig,
    *,
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None,
    store: RecordStore | None = None,
) -> pd.DataFrame:
    """Every trial of every point of the sweep, one row each (tidy), in grid order.

    ``store`` keeps every finished trial and gives back those of an earlier run
    (:mod:`codesign_mb.core.records`), keyed by the plant, root seed and step cap, and by the
    point: its channel's cell, scheduler, pipeline stack, robot count and trial.
    """
    points = config.points()
    rows: list[dict[str, Any] | None] = [None] * len(points)
    group, items = "", [""] * len(points)
    if store is not None:
        group = digest(
            {"trials of": config.plant, "seed": config.seed, "max_steps": config.max_steps}
        )
        items = [_point_key(config, point) for point in points]
        kept = store.take(group, items)
        rows = [kept.get(item) for item in items]

    def finished() -> Iterator[dict[str, Any]]:
        yield from (row for row in list(rows) if row is not None)
        todo = [k for k, row in enumerate(rows) if row is None]
        for k, row in _compute(config, points, todo):
            done = row if store is None else store.add(group, items[k], row)
            rows[k] = done
            yield done

    for _ in progress(finished()) if progress is not None else finished():
        pass
    return pd.DataFrame(rows)


def _point_key(config: CapacityConfig, point: Mapping[str, Any]) -> str:
    """The key of one trial of one point: the point and what its names stand for."""
    cell = CHANNEL_PRESETS[point["channel_name"]]
    return digest(
        {"point": point, "cell": cell, "pipeline": config.pipelines[point["pipeline_name"]]}
    )


def _compute(
    config: CapacityConfig, points: list[dict[str, Any]], todo: list[int]
) -> Iterator[tuple[int, dict[str, Any]]]:
    """``(point index, row)`` of the points ``todo``, as each finishes."""
    if config.workers == 1:
        for k in todo:
            yield k, run_point(config, **points[k])
        return
    # Largest points first keeps both workers busy to the end.
    order = sorted(todo, key=lambda k: -points[k]["n_robots"])
    stream = pool.imap(
        _run_point_kwargs, [((config, points[k]),) for k in order], workers=config.workers
    )
    for i, row in stream:
        yield order[i], row


def capacity_table(results: pd.DataFrame, *, success_target: float = 0.95) -> pd.DataFrame:
    """Per curve: mean success per robot count and the capacity.

    A curve's capacity is the largest robot count up to which every simulated count reaches
    ``success_target`` (0 if the smallest does not). ``mean_reliability`` and
    ``delivered_fraction`` are NaN when ``results`` has no such column; ``mpc_failures`` (the
    trials' sum) is there when ``results`` has it, and so is ``allocator_fallbacks``.
    """
    keys = ["channel", "scheduler", "pipeline", "robots"]
    results = results.assign(
        **{c: math.nan for c in ("mean_reliability", "delivered_fraction") if c not in results}
    )
    sums = {c: (c, _sum_or_nan) for c in ("mpc_failures", "allocator_fallbacks") if c in results}
    curves = (
        results.groupby(keys, as_index=False)
        .agg(
            success_rate=("success_rate", "mean"),
            mean_reliability=("mean_reliability", "mean"),
            delivered_fraction=("delivered_fraction", "mean"),
            trials=("success_rate", "size"),
            **sums,
        )
        .sort_values(keys)
    )
    caps = []
    for key, group in curves.groupby(keys[:3]):
        capacity = 0
        for n, rate in zip(group["robots"], group["success_rate"], strict=True):
            if rate < success_target - 1e-12:
                break
            capacity = int(n)
        caps.append((*key, capacity))
    cap = pd.DataFrame(caps, columns=[*keys[:3], "capacity_robots"])
    return curves.merge(cap, on=keys[:3])


def _sum_or_nan(values: pd.Series) -> float:
    return float(values.sum(min_count=1))
