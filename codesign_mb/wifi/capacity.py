"""Fig. 6 (``fig_wifi``): task success versus number of robots sharing one WiFi 6 channel.

For each robot count ``N`` and each (pipeline, scheduler) pair, ``trials`` episodes run N
robots in lockstep on one :class:`~codesign_mb.wifi.cell.SharedChannel`; a trial's success
rate is the fraction of its robots whose task succeeded (``info["success"]`` at any step).
The *capacity* of a curve is the largest ``N`` whose mean success is at least
``success_target`` (95 %).

The pipelines are configuration: a plant (:class:`~codesign_mb.pipeline.plants.PlantSpec`)
and, per pipeline, a controller, an estimator and a QoS policy
(:class:`~codesign_mb.pipeline.components.ComponentSpec`). Besides the kinds of
:mod:`codesign_mb.pipeline.components`, the QoS kind ``"age_triggered"`` is a model-based
stand-in for the co-design policy: it asks for ``high`` reliability once the held state is
``max_age_steps`` old and ``low`` otherwise (``options``: ``low``, ``high``,
``max_age_steps``, ``latency_steps``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from codesign_mb.network.qos import QosRequest
from codesign_mb.wifi.channel import ChannelConfig
from codesign_mb.wifi.config import SCHEDULERS, WifiConfig
from codesign_mb.wifi.phy import MacTiming

__all__ = [
    "CHANNEL_PRESETS",
    "AgeTriggeredQos",
    "CapacityConfig",
    "PipelineConfig",
    "capacity_table",
    "run_capacity",
]


@dataclass(frozen=True)
class AgeTriggeredQos:
    """QoS rule: ``high`` reliability once ``age >= max_age_steps``, else ``low``."""

    low: float = 0.2
    high: float = 1.0
    max_age_steps: int = 3
    latency_steps: int = 1

    def __post_init__(self) -> None:
        QosRequest(self.low, self.latency_steps)
        QosRequest(self.high, self.latency_steps)
        if (
            isinstance(self.max_age_steps, bool)
            or not isinstance(self.max_age_steps, int)
            or (self.max_age_steps < 1)
        ):
            raise ValueError(f"max_age_steps must be an integer >= 1, got {self.max_age_steps!r}")

    def reset(self, *, seed: int | None = None) -> None:
        return None

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        q = self.high if age >= self.max_age_steps else self.low
        return QosRequest(q, self.latency_steps)


def _component(kind: str, options: Mapping[str, Any] | None = None) -> Any:
    from codesign_mb.pipeline.components import ComponentSpec

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
        from codesign_mb.config import from_mapping
        from codesign_mb.pipeline.components import ComponentSpec

        for name in ("controller", "estimator", "qos"):
            value = getattr(self, name)
            if isinstance(value, Mapping):
                object.__setattr__(self, name, from_mapping(ComponentSpec, value, where=name))
            elif not isinstance(value, ComponentSpec):
                raise ValueError(f"{name} must be a component table, got {value!r}")


def _default_pipelines() -> dict[str, PipelineConfig]:
    return {
        "static": PipelineConfig(),
        "codesign": PipelineConfig(
            qos=_component(
                "age_triggered", {"low": 0.3, "high": 1.0, "max_age_steps": 2, "latency_steps": 1}
            )
        ),
    }


CHANNEL_PRESETS: dict[str, WifiConfig] = {
    # Poor channel: every robot at MCS 1 (QPSK 1/2) with q0 = 0.9, basic-rate control frames
    # at 6 Mb/s; static QoS (q = 1, 2.7 Mb/s of camera frames per robot) runs out near 6 robots.
    "paper": WifiConfig(
        channel=ChannelConfig(fixed_mcs=1, q0=0.9, rician_k_db=math.inf),
        mac=MacTiming(legacy_rate_mbps=6.0),
    ),
    # Better channel: link adaptation on a TGax path loss, robots 5-20 m from the AP.
    "better": WifiConfig(channel=ChannelConfig(q0=0.95, distance_range_m=(5.0, 20.0))),
}
"""Named cells for ``codesign wifi capacity --channel``."""


@dataclass(frozen=True)
class CapacityConfig:
    """Settings of the capacity sweep (``codesign wifi capacity``).

    Parameters
    ----------
    robots:
        Robot counts ``N`` to simulate.
    channels:
        Names of :data:`CHANNEL_PRESETS` to sweep (each gives one panel).
    schedulers:
        Allocators to compare (``"greedy"``, ``"convex"``).
    pipelines:
        Robot stacks by name (default ``static`` and ``codesign``).
    plant:
        The plant every robot runs (``PlantSpec`` table; default the kinematic toy).
    trials:
        Episodes per point.
    max_steps:
        Episode length cap in control steps (``None``: the plant's horizon).
    success_target:
        Success rate that defines a curve's capacity.
    seed:
        Root seed; trial ``k`` of every point uses the same spawned seed (common numbers).
    """

    robots: tuple[int, ...] = (1, 2, 4, 6, 8, 10)
    channels: tuple[str, ...] = ("paper", "better")
    schedulers: tuple[str, ...] = ("greedy", "convex")
    pipelines: dict[str, PipelineConfig] = field(default_factory=_default_pipelines)
    plant: Any = None
    trials: int = 4
    max_steps: int | None = None
    success_target: float = 0.95
    seed: int = 0

    def __post_init__(self) -> None:
        from codesign_mb.config import from_mapping
        from codesign_mb.pipeline.plants import PlantSpec

        robots = tuple(int(n) for n in self.robots)
        if not robots or any(n < 1 for n in robots):
            raise ValueError(f"robots must be integers >= 1, got {self.robots!r}")
        object.__setattr__(self, "robots", robots)
        object.__setattr__(self, "channels", tuple(self.channels))
        object.__setattr__(self, "schedulers", tuple(self.schedulers))
        for c in self.channels:
            if c not in CHANNEL_PRESETS:
                raise ValueError(f"channels must be among {sorted(CHANNEL_PRESETS)}, got {c!r}")
        for s in self.schedulers:
            if s not in SCHEDULERS:
                raise ValueError(f"schedulers must be among {SCHEDULERS}, got {s!r}")
        pipelines = {}
        for name, value in dict(self.pipelines).items():
            pipelines[name] = (
                from_mapping(PipelineConfig, value, where=f"pipelines.{name}")
                if isinstance(value, Mapping)
                else value
            )
        object.__setattr__(self, "pipelines", pipelines)
        plant = self.plant
        if plant is None:
            plant = PlantSpec(name="toy")
        elif isinstance(plant, Mapping):
            plant = from_mapping(PlantSpec, plant, where="plant")
        object.__setattr__(self, "plant", plant)
        if isinstance(self.trials, bool) or not isinstance(self.trials, int) or self.trials < 1:
            raise ValueError(f"trials must be an integer >= 1, got {self.trials!r}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1 or None, got {self.max_steps!r}")
        if not 0.0 < self.success_target <= 1.0:
            raise ValueError(f"success_target must be in (0, 1], got {self.success_target!r}")


def _build(role: str, spec: Any, env: Any) -> Any:
    if role == "qos" and spec.kind == "age_triggered":
        return AgeTriggeredQos(**dict(spec.options))
    from codesign_mb.pipeline.components import build

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
    """One trial of one point: N robots, one episode; returns success and network figures."""
    from codesign_mb.network.wrapper import LinkObservationWrapper
    from codesign_mb.pipeline.plants import make_plant
    from codesign_mb.wifi.cell import SharedChannel, rollout_shared

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
    successes = [bool(t["success"].any()) if "success" in t else False for t in tables]
    summary = channel.summary()
    return {
        "channel": channel_name,
        "scheduler": scheduler,
        "pipeline": pipeline_name,
        "robots": n_robots,
        "trial": trial,
        "success_rate": float(np.mean(successes)),
        "mean_reliability": float(np.nanmean(summary["mean_reliability"])),
        "delivered_fraction": float(summary["delivered"].sum() / max(summary["steps"].sum(), 1)),
        "late_frames": int(summary["late"].sum()),
        "mean_latency_ms": float(np.nanmean(summary["mean_latency_ms"]))
        if summary["delivered"].sum()
        else float("nan"),
    }


def run_capacity(
    config: CapacityConfig,
    *,
    progress: Callable[[Any], Any] | None = None,
) -> pd.DataFrame:
    """Every trial of every point of the sweep, one row each (tidy)."""
    points = [
        (c, s, p, n, k)
        for c in config.channels
        for s in config.schedulers
        for p in config.pipelines
        for n in config.robots
        for k in range(config.trials)
    ]
    it = progress(points) if progress is not None else points
    rows = [
        run_point(config, channel_name=c, scheduler=s, pipeline_name=p, n_robots=n, trial=k)
        for c, s, p, n, k in it
    ]
    return pd.DataFrame(rows)


def capacity_table(results: pd.DataFrame, *, success_target: float = 0.95) -> pd.DataFrame:
    """Per curve: mean success per robot count and the capacity (largest N at the target)."""
    curves = (
        results.groupby(["channel", "scheduler", "pipeline", "robots"], as_index=False)
        .agg(success_rate=("success_rate", "mean"), mean_reliability=("mean_reliability", "mean"))
        .sort_values(["channel", "scheduler", "pipeline", "robots"])
    )
    caps = []
    for key, group in curves.groupby(["channel", "scheduler", "pipeline"]):
        ok = group[group["success_rate"] >= success_target]["robots"]
        caps.append((*key, int(ok.max()) if len(ok) else 0))
    cap = pd.DataFrame(caps, columns=["channel", "scheduler", "pipeline", "capacity_robots"])
    return curves.merge(cap, on=["channel", "scheduler", "pipeline"])
