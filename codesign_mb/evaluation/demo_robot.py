"""``codesign demo`` (default scenario ``robot``): MPC + predictor picking off a lossy link.

The conveyor pick of paper.tex sec. 6 with the model-based pipeline: the MPC ideal controller
(:mod:`codesign_mb.control.mpc`) acts on the delay-compensating predictor's estimate
(:mod:`codesign_mb.estimation.predictor`) of an object whose position reaches the robot over
a :class:`~codesign_mb.network.BernoulliLink`; the same episodes without the predictor
("plain": the stale observation used as is) show what the estimation buys. A short table:
success rate with its 95% Wilson interval, mean age, delivered fraction, estimation error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

__all__ = ["RobotDemoConfig", "run_robot_demo"]


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
    estimators: tuple[str, ...] = ("predictor", "plain")
    """Estimators to compare: ``predictor`` and/or ``plain``."""
    workers: int | None = None
    """Worker processes (default: up to 2)."""

    def __post_init__(self) -> None:
        from codesign_mb.evaluation.evaluate import ESTIMATORS
        from codesign_mb.network.qos import QosRequest

        qs = tuple(self.reliabilities)
        if not qs:
            raise ValueError("reliabilities must hold at least one value")
        for q in qs:
            try:
                QosRequest(q, 0)
            except (TypeError, ValueError):
                raise ValueError(f"reliabilities must be in [0, 1], got {q!r}") from None
        object.__setattr__(self, "reliabilities", tuple(float(q) for q in qs))
        for name in ("latency_steps", "episodes", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{name} must be an integer, got {value!r}")
        if self.latency_steps < 0:
            raise ValueError(f"latency_steps must be >= 0, got {self.latency_steps}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if not (math.isfinite(self.belt_speed_mps) and self.belt_speed_mps >= 0):
            raise ValueError(f"belt_speed_mps must be >= 0, got {self.belt_speed_mps}")
        ests = tuple(self.estimators)
        if not ests or any(e not in ESTIMATORS for e in ests):
            raise ValueError(f"estimators must be among {', '.join(ESTIMATORS)}, got {ests!r}")
        object.__setattr__(self, "estimators", ests)
        if self.workers is not None and (int(self.workers) != self.workers or self.workers < 1):
            raise ValueError(f"workers must be an integer >= 1, got {self.workers!r}")


def run_robot_demo(cfg: RobotDemoConfig, *, progress: bool = False) -> dict[str, Any]:
    """Run the robot scenario; pure in ``cfg`` (seeded) except the wall-time figures.

    Returns
    -------
    dict
        ``scenario``, the settings and ``rows``: one record per (estimator, reliability) with
        ``estimator``, ``reliability``, ``success_rate``, ``success_ci_low``,
        ``success_ci_high``, ``mean_age``, ``delivered_fraction``, ``estimation_error_cm`` and
        ``mpc_solve_ms_median``.
    """
    import os

    from codesign_mb.adaptation.base import StaticQos
    from codesign_mb.cli.common import track
    from codesign_mb.evaluation.evaluate import component, rows_to_table, run_jobs, summarize
    from codesign_mb.plants.conveyor import ConveyorConfig

    env = ConveyorConfig(belt_speed_mps=cfg.belt_speed_mps)
    points = [(e, q) for e in cfg.estimators for q in cfg.reliabilities]
    jobs = [
        (
            component("controller", "mpc"),
            component("estimator", est),
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
    for j, row in track(
        stream, total=total, description="MPC on the conveyor", disable=not progress
    ):
        rows[j].append(row)
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


def robot_demo_command(
    ctx: Any,
    *,
    config: Any,
    reliability: list[float] | None,
    latency: int,
    episodes: int,
    seed: int,
    as_json: bool,
) -> None:
    """The body of ``codesign demo`` for the robot scenario (called from ``cli/demo.py``)."""
    from codesign_mb.cli.common import emit, explicit, load_config

    overrides = explicit(
        ctx,
        {
            "reliability": tuple(reliability) if reliability else None,
            "latency": latency,
            "episodes": episodes,
            "seed": seed,
        },
        rename={"reliability": "reliabilities", "latency": "latency_steps"},
    )
    cfg = load_config(RobotDemoConfig, config, overrides, section="robot_demo")
    result = run_robot_demo(cfg, progress=not as_json)
    if as_json:
        emit(result, as_json=True)
        return
    rows = [
        {
            "est.": r["estimator"],
            "q": r["reliability"],
            "success": f"{r['success_rate']:.2f}",
            "95% CI": f"[{r['success_ci_low']:.2f}, {r['success_ci_high']:.2f}]",
            "age": f"{r['mean_age']:.1f}",
            "deliv.": f"{r['delivered_fraction']:.2f}",
            "err cm": f"{r['estimation_error_cm']:.1f}",
            "MPC ms": f"{r['mpc_solve_ms_median']:.2f}",
        }
        for r in result["rows"]
    ]
    title = (
        f"MPC pick on the conveyor at {cfg.belt_speed_mps:g} m/s over a Bernoulli link, "
        f"tau = {cfg.latency_steps}: {cfg.episodes} episodes per row (predictor = "
        "delay-compensating Kalman prediction, plain = stale observation)"
    )
    emit(rows, as_json=False, title=title)
