"""The demos of ``codesign demo``: MPC + predictor on the conveyor, and LQG over a lossy link.

The conveyor pick of paper.tex sec. 6 with the model-based pipeline: the MPC ideal controller
(:mod:`codesign_mb.control.mpc`) acts on the delay-compensating predictor's estimate
(:mod:`codesign_mb.estimation.predictor`) of an object whose position reaches the robot over
a :class:`~codesign_mb.network.BernoulliLink`; the same episodes without the predictor
("none": the stale observation used as is) show what the estimation buys. A short table:
success rate with its 95% Wilson interval, mean age, delivered fraction, estimation error.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.core.config import (
    EPISODES_CAP,
    LATENCY_STEPS_CAP,
    SEED_CAP,
    STEPS_CAP,
    WORKERS_CAP,
    check_range,
)
from codesign_mb.core.registry import ComponentSpec, factory
from codesign_mb.estimation.kalman import critical_arrival_lower_bound
from codesign_mb.evaluation.evaluate import rows_to_table, run_jobs, summarize
from codesign_mb.network import BernoulliLink, LinkObservationWrapper
from codesign_mb.network.qos import QosRequest
from codesign_mb.plants.conveyor import ConveyorConfig
from codesign_mb.plants.linear import LinearPlantEnv, make_linear_plant
from codesign_mb.rollout import rollout
from codesign_mb.rollout.compose import lqg, lqg_average_cost

_ESTIMATORS = ("predictor", "none")
"""Estimator kinds compared (no checkpoint needed)."""

__all__ = ["LqgDemoConfig", "RobotDemoConfig", "run_lqg_demo", "run_robot_demo"]

Progress = Callable[[int, int], None]
"""Called as ``progress(done, total)`` after each episode."""


def _check_episodes(cfg: Any) -> None:
    """Validate (and normalise) what both demos share: reliabilities, latency, episodes, seed."""
    qs = tuple(cfg.reliabilities)
    if not qs:
        raise ValueError("reliabilities must hold at least one value")
    for q in qs:
        try:
            QosRequest(q, 0)
        except (TypeError, ValueError):
            raise ValueError(f"reliabilities must be in [0, 1], got {q!r}") from None
    object.__setattr__(cfg, "reliabilities", tuple(float(q) for q in qs))
    for name in ("latency_steps", "episodes", "seed"):
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{name} must be an integer, got {value!r}")
    check_range("latency_steps", cfg.latency_steps, ge=0, cap=LATENCY_STEPS_CAP)
    check_range("episodes", cfg.episodes, ge=1, cap=EPISODES_CAP)
    check_range("seed", cfg.seed, ge=0, cap=SEED_CAP)


@dataclass(frozen=True)
class RobotDemoConfig:
    """Settings of ``codesign demo --scenario robot`` (config file table ``[robot_demo]``)."""

    reliabilities: tuple[float, ...] = (1.0, 0.3, 0.1)
    """Static link reliabilities ``q`` to compare, each in [0, 1]."""
    latency_steps: int = 1
    """Static link latency ``tau`` in control steps (>= 0); the paper's runs use 1."""
    belt_speed_mps: float = 0.6
    """Belt speed (m/s)."""
    episodes: int = 4
    """Seeded episodes per row (>= 1); every row uses the same episode seeds."""
    seed: int = 0
    """Root seed."""
    estimators: tuple[str, ...] = ("predictor", "none")
    """Estimators to compare: ``predictor`` and/or ``none``."""
    workers: int | None = None
    """Worker processes (default: up to 2)."""

    def __post_init__(self) -> None:
        _check_episodes(self)
        if not (math.isfinite(self.belt_speed_mps) and self.belt_speed_mps >= 0):
            raise ValueError(f"belt_speed_mps must be >= 0, got {self.belt_speed_mps}")
        ests = tuple(self.estimators)
        if not ests or any(e not in _ESTIMATORS for e in ests):
            raise ValueError(f"estimators must be among {', '.join(_ESTIMATORS)}, got {ests!r}")
        object.__setattr__(self, "estimators", ests)
        if self.workers is not None and (int(self.workers) != self.workers or self.workers < 1):
            raise ValueError(f"workers must be an integer >= 1, got {self.workers!r}")
        check_range("workers", self.workers, cap=WORKERS_CAP)


def run_robot_demo(cfg: RobotDemoConfig, *, progress: Progress | None = None) -> dict[str, Any]:
    """Run the robot scenario; pure in ``cfg`` (seeded) except the wall-time figures.

    Returns
    -------
    dict
        ``scenario``, the settings and ``rows``: one record per (estimator, reliability) with
        ``estimator``, ``reliability``, ``success_rate``, ``success_ci_low``,
        ``success_ci_high``, ``mean_age``, ``delivered_fraction``, ``estimation_error_cm`` and
        ``mpc_solve_ms_median``.
    """
    env = ConveyorConfig(belt_speed_mps=cfg.belt_speed_mps)
    points = [(e, q) for e in cfg.estimators for q in cfg.reliabilities]
    jobs = [
        (
            factory("controller", ComponentSpec("mpc")),
            factory("estimator", ComponentSpec(est)),
            StaticQos(q, cfg.latency_steps),
            env,
            cfg.episodes,
            cfg.seed,
        )
        for est, q in points
    ]
    workers = cfg.workers or min(2, os.cpu_count() or 1)
    stream = run_jobs(jobs, workers=workers)
    total = len(points) * cfg.episodes
    rows: list[list[dict[str, Any]]] = [[] for _ in points]
    for done, (j, row) in enumerate(stream):
        rows[j].append(row)
        if progress is not None:
            progress(done + 1, total)
    records = []
    for (est, q), episode_rows in zip(points, rows, strict=True):
        s = summarize(rows_to_table(episode_rows))
        records.append(
            {
                "estimator": est,
                "reliability": q,
                "success_rate": s["success_rate"],
                "success_ci_low": s["success_ci_low"],
                "success_ci_high": s["success_ci_high"],
                "mean_age": s["mean_age"],
                "delivered_fraction": s["delivered_fraction"],
                "estimation_error_cm": 100.0 * s["mean_estimation_error"],
                "mpc_solve_ms_median": s.get("mpc_solve_ms_median", math.nan),
            }
        )
    return {
        "scenario": "robot",
        "belt_speed_mps": cfg.belt_speed_mps,
        "latency_steps": cfg.latency_steps,
        "episodes": cfg.episodes,
        "seed": cfg.seed,
        "rows": records,
    }


LINEAR_DEMO_PLANTS = ("scalar", "double_integrator", "pendulum")


@dataclass(frozen=True)
class LqgDemoConfig:
    """Settings of ``codesign demo --scenario lqg`` (config file table ``[demo]``)."""

    plant: str = "pendulum"
    """Linear plant: ``scalar`` (a = 1.2), ``double_integrator`` or ``pendulum`` (cart-pole)."""
    reliabilities: tuple[float, ...] = (1.0, 0.9, 0.7, 0.5, 0.3)
    """Static link reliabilities ``q`` to compare, each in [0, 1]."""
    latency_steps: int = 0
    """Static link latency ``tau`` in control steps (>= 0)."""
    episodes: int = 8
    """Seeded episodes per reliability (>= 1)."""
    horizon: int = 250
    """Steps per episode (>= 1), 40 ms each."""
    seed: int = 0
    """Root seed; the episode seeds are spawned from it."""

    def __post_init__(self) -> None:
        if self.plant not in LINEAR_DEMO_PLANTS:
            raise ValueError(
                f"plant must be one of {', '.join(LINEAR_DEMO_PLANTS)}, got {self.plant!r}"
            )
        _check_episodes(self)
        if isinstance(self.horizon, bool) or not isinstance(self.horizon, int):
            raise ValueError(f"horizon must be an integer, got {self.horizon!r}")
        check_range("horizon", self.horizon, ge=1, cap=STEPS_CAP)


# Initial-state spread per plant (state units: m, rad, m/s, rad/s); costs are identities.
_X0_STD = {"scalar": 1.0, "double_integrator": 0.1, "pendulum": 0.1}


def run_lqg_demo(cfg: LqgDemoConfig, *, progress: Progress | None = None) -> dict[str, Any]:
    """Run the LQG-over-a-lossy-link scenario; pure in ``cfg`` (seeded).

    Returns
    -------
    dict
        ``scenario``, ``plant``, the settings, ``riccati_cost`` (expected cost per step at
        ``q = 1`` without delay), ``critical_reliability_lower_bound`` (``1 - 1/rho(A)^2``)
        and ``rows``: one record per reliability with ``reliability``, ``mean_cost``,
        ``cost_ci95`` (half-width), ``mean_age`` (steps) and ``delivered_fraction``.
    """

    plant = make_linear_plant(cfg.plant)
    n = plant.n_states
    base = LinearPlantEnv(plant, horizon=cfg.horizon, x0_cov=_X0_STD[cfg.plant] ** 2 * np.eye(n))
    seeds = [int(s) for s in np.random.SeedSequence(cfg.seed).generate_state(cfg.episodes)]
    jobs = [(q, s) for q in cfg.reliabilities for s in seeds]
    costs: dict[float, list[float]] = {q: [] for q in cfg.reliabilities}
    ages: dict[float, list[float]] = {q: [] for q in cfg.reliabilities}
    delivered: dict[float, list[float]] = {q: [] for q in cfg.reliabilities}
    for done, (q, seed) in enumerate(jobs):
        env = LinkObservationWrapper(
            base, BernoulliLink(), StaticQos(reliability=q, latency_steps=cfg.latency_steps)
        )
        estimator, controller = lqg(env)
        df = rollout(env, estimator, controller, seed=seed)
        costs[q].append(float(df["stage_cost"].mean()))
        ages[q].append(float(df["age"].mean()))
        delivered[q].append(float(df["delivered"].mean()))
        if progress is not None:
            progress(done + 1, len(jobs))
    rows = []
    for q in cfg.reliabilities:
        c = np.asarray(costs[q])
        half = 1.96 * float(c.std(ddof=1)) / math.sqrt(c.size) if c.size > 1 else math.nan
        rows.append(
            {
                "reliability": q,
                "mean_cost": float(c.mean()),
                "cost_ci95": half,
                "mean_age": float(np.mean(ages[q])),
                "delivered_fraction": float(np.mean(delivered[q])),
            }
        )
    theory = lqg_average_cost(plant, base.state_cost, base.input_cost)
    return {
        "scenario": "lqg",
        "plant": plant.name,
        "episodes": cfg.episodes,
        "horizon": cfg.horizon,
        "latency_steps": cfg.latency_steps,
        "seed": cfg.seed,
        "riccati_cost": theory.total,
        "critical_reliability_lower_bound": critical_arrival_lower_bound(plant.A),
        "rows": rows,
    }
