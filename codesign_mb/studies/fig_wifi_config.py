"""Fig. 6's (``fig_wifi``) configuration: robot stacks, WiFi 6 cells and their assumptions, sweep.

:class:`CapacityConfig` is the sweep (``codesign wifi capacity``): which cells, schedulers and
robot counts, which stack, how many trials; :mod:`codesign_mb.studies.fig_wifi` runs it.

Stacks (:data:`STACKS`)
-----------------------
A stack is a plant (:class:`~codesign_mb.core.registry.PlantSpec` table) and its pipelines
(:class:`PipelineConfig`: a controller, an estimator and a QoS policy, each a
:class:`~codesign_mb.core.registry.ComponentSpec` table), so learned pipelines (SAC, MLP
estimator, learned QoS) plug in by naming their kinds and checkpoints. Besides the kinds of
:mod:`codesign_mb.core.registry`, two model-based QoS rules of
:mod:`codesign_mb.adaptation.rules` are known here (:data:`QOS_RULES`): ``"age_triggered"``
(``options``: ``low``, ``high``, ``max_age_steps``, ``latency_steps``) and
``"covariance_triggered"`` (``options``: ``threshold_m``, ``low``, ``high``,
``latency_steps``, ``lift_margin_m``, ``predictor_options``). Every stack has a ``static``
pipeline (``q = 1, tau = 1`` always: the paper's "estimation-only" policy) and a
``codesign`` one.

``"realistic"`` (Fig. 6)
    The ``realistic`` scenario's conveyor (belt 0.1-0.6 m/s per episode with steps and stops,
    perceived position only, with noise, bias and missed detections) and the best
    model-based stack of the head-to-head table
    (:data:`~codesign_mb.studies.table_rows.PLANNER_ROW`, its components taken from
    :func:`~codesign_mb.studies.table_rows.model_based_rows`): the uncertainty-gated MPC and
    the belt IMM predictor; ``static`` asks for every packet, ``codesign`` is the QoS
    planner at the table's dev-chosen tolerances.
``"conveyor"``
    The MuJoCo conveyor at a constant 0.6 m/s, MPC and the delay-compensating predictor;
    ``codesign`` uses the covariance-triggered rule (threshold 2 cm, ``q`` 0.1 or 1).
``"toy"``
    The kinematic toy conveyor (seconds per point, for tests and quick looks) with a static
    and an age-triggered QoS.

Cells (:data:`CHANNEL_PRESETS`) and their assumptions
-----------------------------------------------------
From the paper (``sec_wifi``, ``tab_network``, ``sec_scheduling``): one 40 MHz WiFi 6
channel; per robot and 40 ms control step one uplink camera frame of 13,500 bytes and one
downlink state frame of 32 bytes; the schedule updated every 1 ms; the QoS-aware greedy
earliest-deadline scheduler; probabilistic frame dropping (``eq_drop``); the latency fixed at
one step for every robot; and the static-QoS capacity, "exceeded with 6 robotic conveyor belt
tasks" (the caption of ``fig_wifi``). These are :class:`~codesign_mb.wifi.WifiConfig`'s
defaults. ``eq_drop``'s ``q0`` is each station's own link-level delivery in the current
coherence block (:attr:`~codesign_mb.wifi.cell.ChannelProcess.delivery`), as the paper
defines it ("a fixed link-level PDR achievable under current channel conditions"), not a
configured number.

Chosen here (the paper does not give them):

``"paper"``
    A poor cell in which static QoS fills the channel at about the paper's 6 robots: every
    robot at MCS 1 (QPSK 1/2, no link adaptation), the long 3.2 us guard interval on both
    links (a factory hall's delay spread), and the Trigger and multi-STA BlockAck frames at
    the 6 Mb/s basic rate. One camera frame then takes about 5.5 ms of the whole channel and
    its state frame's DL exchange about 0.4 ms more, so about 6 robots at ``q = 1`` fill the
    40 ms period (every frame requested, staggered captures, no loss: the greedy scheduler
    delivers every frame to 6 robots, 57 % to 7, none to 8; the convex one 100, 95 and 78 %;
    :func:`~codesign_mb.wifi.crosscheck.ours_delivered_fraction`, 8 periods). No fading
    (Rician ``K = inf``) and :class:`~codesign_mb.wifi.channel.ChannelConfig`'s link budget
    (TGax indoor path loss at 5.5 GHz with 10 dB of walls and clutter, AP 20 dBm, stations
    17 dBm, noise figure 7 dB, robots 5-30 m from the AP): MCS 1 then delivers 99.4-100 % of
    the frames, so the cell's limit is airtime, not loss.
``"paper-scheduled"``
    The ``paper`` cell whose AP knows every camera frame it admitted from its capture
    (:attr:`~codesign_mb.wifi.mac.MacTiming.scheduled_uplink`: the edge decided the request,
    so it triggers the station in a TWT service period at the capture) and polls no one;
    ``paper`` learns of frames from buffer status reports only. Not in Fig. 6's default grid.
``"better"``
    What a well-planned cell gives: link adaptation (MCS 0-11, the highest whose delivery
    reaches ``sqrt(0.95)`` per hop), the default 0.8 us (DL) and 1.6 us (UL) guard intervals,
    control frames at 24 Mb/s, robots 5-20 m from the AP, Rician block fading with ``K = 6``
    dB per 40 ms.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from codesign_mb.adaptation.rules import AgeTriggeredQos
from codesign_mb.core.config import (
    EPISODES_CAP,
    ROBOTS_CAP,
    SEED_CAP,
    STEPS_CAP,
    WORKERS_CAP,
    check_range,
    from_mapping,
)
from codesign_mb.core.registry import ComponentSpec, PlantSpec, check_options, factory
from codesign_mb.plants.scenarios import scenario_options
from codesign_mb.rollout.compose import covariance_rule
from codesign_mb.studies.table_rows import PLANNER_ROW, model_based_rows
from codesign_mb.wifi.config import SCHEDULERS
from codesign_mb.wifi.presets import CHANNEL_PRESETS

__all__ = [
    "CHANNEL_PRESETS",
    "QOS_RULES",
    "RULE_SIGNATURES",
    "STACKS",
    "AgeTriggeredQos",
    "CapacityConfig",
    "PipelineConfig",
    "describe_channel",
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


def _table(spec: ComponentSpec) -> dict[str, Any]:
    """A component as the table a config file gives."""
    table: dict[str, Any] = {"kind": spec.kind, "options": dict(spec.options)}
    if spec.checkpoint:
        table["checkpoint"] = spec.checkpoint
    return table


def _planner_pipelines() -> dict[str, dict[str, Any]]:
    """``static`` and ``codesign`` on the components of the table's planner row."""
    row = next(r for r in model_based_rows() if r.name == PLANNER_ROW)
    stack = {"controller": _table(row.controller), "estimator": _table(row.estimator)}
    return {"static": {**stack, "qos": _STATIC}, "codesign": {**stack, "qos": _table(row.qos)}}


STACKS: dict[str, dict[str, Any]] = {
    "realistic": {
        "plant": {"name": "conveyor", "options": scenario_options("realistic")},
        "pipelines": _planner_pipelines(),
    },
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

RULE_SIGNATURES: dict[str, tuple[Callable[..., Any], bool]] = {
    "age_triggered": (AgeTriggeredQos, False),
    "covariance_triggered": (covariance_rule, True),
}
"""What each of :data:`QOS_RULES` calls, and whether with the plant: its options' schema."""


def describe_channel(name: str) -> str:
    """One line of PHY/MAC assumptions of a :data:`CHANNEL_PRESETS` cell (for figures)."""
    cfg = CHANNEL_PRESETS[name]
    ch, mac, phy = cfg.channel, cfg.mac, cfg.phy
    mcs = (
        f"MCS {ch.fixed_mcs}"
        if ch.fixed_mcs is not None
        else f"MCS 0-{ch.max_mcs} for delivery >= {ch.q0:g}"
    )
    return (
        f"{phy.bandwidth_mhz} MHz, {mcs}, GI {phy.guard_interval_us:g} us, "
        f"control frames {mac.legacy_rate_mbps:g} Mb/s"
        + (", UL triggered at capture (no BSR polls)" if mac.scheduled_uplink else "")
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
        conveyor runs instead of ``plant`` (a stack whose plant is the conveyor: ``conveyor``
        or ``realistic``); ``""``: the stack's plant.
    trials:
        Episodes (trials of N robots) per point.
    max_steps:
        Episode length cap in control steps (``None``: the plant's horizon).
    episodes_per_robot, warmup_episodes:
        Continuous operation (:func:`~codesign_mb.rollout.rollout_shared`): each robot of a
        trial runs ``warmup_episodes`` uncounted episodes, then ``episodes_per_robot``
        counted ones, back to back, and keeps working until every robot is done, so the
        channel always carries N robots whose pick cycles drift apart as in a running cell.
        ``1, 0`` (one episode, begun together; a robot leaves when done) is the old protocol,
        which synchronises the robots' phases: every robot's object arrives within the same
        few steps, a burst of requests no running cell sees.
    success_target:
        Success rate that defines a curve's capacity.
    stop_below:
        Early stop, in ``[0, success_target]``: once a curve's mean success at a robot count
        is below it, its larger counts are not run (0: every count runs).
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
    episodes_per_robot: int = 1
    warmup_episodes: int = 0
    success_target: float = 0.95
    stop_below: float = 0.0
    seed: int = 0
    workers: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        check_range("seed", self.seed, cap=SEED_CAP)

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
            if self.plant is not None or stack["plant"]["name"] != "conveyor":
                conveyors = sorted(k for k, v in STACKS.items() if v["plant"]["name"] == "conveyor")
                raise ValueError(
                    "scenario sets the conveyor's plant: give no plant, and a conveyor stack "
                    f"({', '.join(conveyors)}), got stack {self.stack!r}"
                )
            plant = PlantSpec("conveyor", scenario_options(self.scenario))
        if isinstance(plant, Mapping):
            plant = from_mapping(PlantSpec, plant, where="plant")
        if not isinstance(plant, PlantSpec):
            raise ValueError(f"plant must be a table (name, options), got {plant!r}")
        object.__setattr__(self, "plant", plant)
        for name in ("trials", "workers", "episodes_per_robot"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        check_range("warmup_episodes", self.warmup_episodes, ge=0, cap=EPISODES_CAP)
        check_range("episodes_per_robot", self.episodes_per_robot, cap=EPISODES_CAP)
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1 or None, got {self.max_steps!r}")
        if not 0.0 < self.success_target <= 1.0:
            raise ValueError(f"success_target must be in (0, 1], got {self.success_target!r}")
        if not 0.0 <= self.stop_below <= self.success_target:
            raise ValueError(
                f"stop_below must be in [0, success_target = {self.success_target:g}] (a "
                f"stop above the target could hide a capacity), got {self.stop_below!r}"
            )
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
                    rule, takes_env = RULE_SIGNATURES[spec.kind]
                    check_options(
                        f"qos kind {spec.kind!r}", rule, spec.options, takes_env=takes_env
                    )
                else:
                    factory(role, spec)

    def robots_of(self, channel: str) -> tuple[int, ...]:
        """Robot counts simulated on ``channel``."""
        return self.robots_by_channel.get(channel, self.robots)

    def robot_episodes(self) -> int:
        """Robot-episodes of the whole sweep (a trial at N robots is N per episode, warm-up
        included): the cost with no early stop (with continuous operation, a few more: the
        robots that finish first keep working until the last does)."""
        per_robot = self.warmup_episodes + self.episodes_per_robot
        return per_robot * sum(point["n_robots"] for point in self.points())

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
