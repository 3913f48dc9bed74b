"""``codesign demo``: the best scenario the toolkit has, in a few seconds.

The default scenario, ``robot``, is the MPC with the delay-compensating predictor picking off
the conveyor over a lossy link (:mod:`codesign_mb.evaluation.demo_robot`); giving ``--plant`` or
``--horizon`` selects ``lqg``. Scenario ``lqg``: certainty-equivalent LQG
(:func:`codesign_mb.control.lqr.lqg`) on a linear plant whose measurement reaches the
controller over a :class:`~codesign_mb.network.BernoulliLink`, for a few reliabilities ``q``,
several seeded episodes each, through :func:`~codesign_mb.evaluation.rollout.rollout`. The
table shows the mean stage cost per step (with a 95 % confidence half-width over episodes),
the mean age ``zeta`` and the delivered fraction; the title gives the Riccati cost for
``q = 1`` and Sinopoli's lower bound on the critical reliability. Every reliability runs on
the same episode seeds (common random numbers), so the columns compare like with like.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any

import typer

from codesign_mb.cli.common import (
    ConfigOption,
    JsonOption,
    SeedOption,
    cli_errors,
    emit,
    explicit,
    load_config,
    track,
)

__all__ = ["SCENARIOS", "LqgDemoConfig", "register", "run_lqg_demo"]

_PLANTS = ("scalar", "double_integrator", "pendulum")


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
        from codesign_mb.network.qos import QosRequest

        if self.plant not in _PLANTS:
            raise ValueError(f"plant must be one of {', '.join(_PLANTS)}, got {self.plant!r}")
        qs = tuple(self.reliabilities)
        if not qs:
            raise ValueError("reliabilities must hold at least one value")
        for q in qs:
            try:
                QosRequest(q, 0)
            except (TypeError, ValueError):
                raise ValueError(f"reliabilities must be in [0, 1], got {q!r}") from None
        object.__setattr__(self, "reliabilities", tuple(float(q) for q in qs))
        for name in ("latency_steps", "episodes", "horizon", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{name} must be an integer, got {value!r}")
        if self.latency_steps < 0:
            raise ValueError(f"latency_steps must be >= 0, got {self.latency_steps}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")


# Initial-state spread per plant (state units: m, rad, m/s, rad/s); costs are identities.
_X0_STD = {"scalar": 1.0, "double_integrator": 0.1, "pendulum": 0.1}


def run_lqg_demo(cfg: LqgDemoConfig, *, progress: bool = False) -> dict[str, Any]:
    """Run the LQG-over-a-lossy-link scenario; pure in ``cfg`` (seeded).

    Returns
    -------
    dict
        ``scenario``, ``plant``, the settings, ``riccati_cost`` (expected cost per step at
        ``q = 1`` without delay), ``critical_reliability_lower_bound`` (``1 - 1/rho(A)^2``)
        and ``rows``: one record per reliability with ``reliability``, ``mean_cost``,
        ``cost_ci95`` (half-width), ``mean_age`` (steps) and ``delivered_fraction``.
    """
    import numpy as np

    from codesign_mb.adaptation.base import StaticQos
    from codesign_mb.control.lqr import lqg, lqg_average_cost
    from codesign_mb.estimation.kalman import critical_arrival_lower_bound
    from codesign_mb.evaluation.rollout import rollout
    from codesign_mb.network import BernoulliLink, LinkObservationWrapper
    from codesign_mb.plants.linear import LinearPlantEnv, make_linear_plant

    plant = make_linear_plant(cfg.plant)
    n = plant.n_states
    base = LinearPlantEnv(plant, horizon=cfg.horizon, x0_cov=_X0_STD[cfg.plant] ** 2 * np.eye(n))
    seeds = [int(s) for s in np.random.SeedSequence(cfg.seed).generate_state(cfg.episodes)]
    jobs = [(q, s) for q in cfg.reliabilities for s in seeds]
    costs: dict[float, list[float]] = {q: [] for q in cfg.reliabilities}
    ages: dict[float, list[float]] = {q: [] for q in cfg.reliabilities}
    delivered: dict[float, list[float]] = {q: [] for q in cfg.reliabilities}
    for q, seed in track(jobs, description=f"LQG on {cfg.plant}", disable=not progress):
        env = LinkObservationWrapper(
            base, BernoulliLink(), StaticQos(reliability=q, latency_steps=cfg.latency_steps)
        )
        estimator, controller = lqg(env)
        df = rollout(env, estimator, controller, seed=seed)
        costs[q].append(float(df["stage_cost"].mean()))
        ages[q].append(float(df["age"].mean()))
        delivered[q].append(float(df["delivered"].mean()))
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


SCENARIOS: tuple[str, ...] = ("robot", "lqg")
"""The scenarios ``--scenario`` accepts; the first is the default."""


def register(app: typer.Typer) -> None:
    """Add ``codesign demo`` to ``app``."""

    @app.command()
    @cli_errors
    def demo(
        ctx: typer.Context,
        scenario: Annotated[
            str, typer.Option("--scenario", help=f"Scenario to run: {', '.join(SCENARIOS)}.")
        ] = SCENARIOS[0],
        plant: Annotated[
            str,
            typer.Option("--plant", help=f"Linear plant: {', '.join(_PLANTS)}."),
        ] = LqgDemoConfig.plant,
        reliability: Annotated[
            list[float] | None,
            typer.Option(
                "--reliability",
                "-q",
                help="Link reliability q in [0, 1]; repeat for several "
                "(default 1, 0.9, 0.7, 0.5, 0.3).",
                show_default=False,
            ),
        ] = None,
        latency: Annotated[
            int, typer.Option("--latency", help="Link latency tau in steps of 40 ms.")
        ] = LqgDemoConfig.latency_steps,
        episodes: Annotated[
            int, typer.Option("--episodes", "-n", help="Seeded episodes per reliability.")
        ] = LqgDemoConfig.episodes,
        horizon: Annotated[
            int, typer.Option("--horizon", help="Steps per episode.")
        ] = LqgDemoConfig.horizon,
        seed: SeedOption = LqgDemoConfig.seed,
        config: ConfigOption = None,
        as_json: JsonOption = False,
    ) -> None:
        """MPC + predictor picking off the conveyor (default), or LQG (--scenario lqg) vs q."""
        if scenario not in SCENARIOS:
            raise ValueError(f"scenario must be one of {', '.join(SCENARIOS)}, got {scenario!r}")
        lqg_only = explicit(ctx, {"plant": plant, "horizon": horizon})
        if scenario == "robot" and lqg_only and not explicit(ctx, {"scenario": scenario}):
            scenario = "lqg"  # the LQG-only options --plant/--horizon select that scenario
        if scenario == "robot":  # MPC + predictor on the conveyor (part MPC's module)
            from codesign_mb.evaluation.demo_robot import robot_demo_command

            robot_demo_command(
                ctx,
                config=config,
                reliability=reliability,
                latency=latency,
                episodes=episodes,
                seed=seed,
                as_json=as_json,
            )
            return
        overrides = explicit(
            ctx,
            {
                "plant": plant,
                "reliabilities": tuple(reliability) if reliability else None,
                "latency_steps": latency,
                "episodes": episodes,
                "horizon": horizon,
                "seed": seed,
            },
        )
        cfg = load_config(LqgDemoConfig, config, overrides, section="demo")
        result = run_lqg_demo(cfg, progress=not as_json)
        if as_json:
            emit(result, as_json=True)
            return
        title = (
            f"LQG on {result['plant']} over a Bernoulli link, tau = {cfg.latency_steps}: "
            f"{cfg.episodes} episodes x {cfg.horizon} steps; Riccati cost at q = 1: "
            f"{result['riccati_cost']:.4g}; critical q >= "
            f"{result['critical_reliability_lower_bound']:.3f}"
        )
        emit(result["rows"], as_json=False, title=title)
