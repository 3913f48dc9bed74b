"""``codesign demo``: the best scenario the toolkit has, in a few seconds.

The default scenario, ``robot``, is the MPC with the delay-compensating predictor picking off
the conveyor over a lossy link (:mod:`codesign_mb.studies.demo`); giving ``--plant`` or
``--horizon`` selects ``lqg``. Scenario ``lqg``: certainty-equivalent LQG
(:func:`codesign_mb.control.lqr.lqg`) on a linear plant whose measurement reaches the
controller over a :class:`~codesign_mb.network.BernoulliLink`, for a few reliabilities ``q``,
several seeded episodes each, through :func:`~codesign_mb.rollout.loop.rollout`. The
table shows the mean stage cost per step (with a 95 % confidence half-width over episodes),
the mean age ``zeta`` and the delivered fraction; the title gives the Riccati cost for
``q = 1`` and Sinopoli's lower bound on the critical reliability. Every reliability runs on
the same episode seeds (common random numbers), so the columns compare like with like.
"""

from __future__ import annotations

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
    progress_bar,
)

__all__ = ["SCENARIOS", "demo", "register"]

SCENARIOS: tuple[str, ...] = ("robot", "lqg")
"""The scenarios ``--scenario`` accepts; the first is the default."""

_ROBOT = {"reliabilities": "1, 0.3, 0.1", "latency_steps": 1, "episodes": 4}
_LQG = {"reliabilities": "1, 0.9, 0.7, 0.5, 0.3", "latency_steps": 0, "episodes": 8, "horizon": 250}
"""The defaults of ``RobotDemoConfig`` and ``LqgDemoConfig`` as ``--help`` shows them (here so
that ``--help`` imports no physics; a test checks they agree)."""

ROBOT_TABLE_NOTE = (
    "success: episodes whose object was lifted (95% Wilson interval); age: mean age of the "
    "held observation in steps; deliv.: delivered share of the packets; err cm: mean error of "
    "the estimated object position; MPC ms: median MPC solve time."
)
LQG_TABLE_NOTE = (
    "mean_cost: LQG stage cost x'Qx + u'Ru per step, averaged over the episodes (cost_ci95: "
    "the 95% half-width); mean_age: age of the held measurement in steps; delivered_fraction: "
    "share of the measurements that arrived."
)
"""The line printed under each demo's table: what its columns are."""


def demo(
    ctx: typer.Context,
    scenario: Annotated[
        str, typer.Option("--scenario", help=f"Scenario to run: {', '.join(SCENARIOS)}.")
    ] = SCENARIOS[0],
    plant: Annotated[
        str | None,
        typer.Option(
            "--plant",
            help="Linear plant of the lqg scenario: scalar, double_integrator or pendulum. "
            "\\[default: pendulum]",
            show_default=False,
        ),
    ] = None,
    reliability: Annotated[
        list[float] | None,
        typer.Option(
            "--reliability",
            "-q",
            help="Link reliability q in [0, 1]; repeat for several. "
            f"\\[default: robot {_ROBOT['reliabilities']}; lqg {_LQG['reliabilities']}]",
            show_default=False,
        ),
    ] = None,
    latency: Annotated[
        int | None,
        typer.Option(
            "--latency",
            help="Link latency tau in steps of 40 ms. "
            f"\\[default: robot {_ROBOT['latency_steps']}, lqg {_LQG['latency_steps']}]",
            show_default=False,
        ),
    ] = None,
    episodes: Annotated[
        int | None,
        typer.Option(
            "--trials",
            "--episodes",
            "-n",
            help="Seeded episodes per reliability. "
            f"\\[default: robot {_ROBOT['episodes']}, lqg {_LQG['episodes']}]",
            show_default=False,
        ),
    ] = None,
    horizon: Annotated[
        int | None,
        typer.Option(
            "--horizon",
            help=f"Steps per episode, lqg. \\[default: {_LQG['horizon']}]",
            show_default=False,
        ),
    ] = None,
    seed: SeedOption = 0,
    config: ConfigOption = None,
    as_json: JsonOption = False,
) -> None:
    """MPC + predictor picking off the conveyor (default), or LQG (--scenario lqg) vs q."""
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {', '.join(SCENARIOS)}, got {scenario!r}")
    lqg_only = explicit(ctx, {"plant": plant, "horizon": horizon})
    if scenario == "robot" and lqg_only and not explicit(ctx, {"scenario": scenario}):
        scenario = "lqg"  # the LQG-only options --plant/--horizon select that scenario
    if scenario == "robot" and lqg_only:
        given = " and ".join(f"--{k}" for k in lqg_only)
        verb = "apply" if len(lqg_only) > 1 else "applies"
        raise ValueError(f"{given} {verb} to --scenario lqg only, got --scenario robot")
    if scenario == "robot":  # MPC + predictor on the conveyor (part MPC's module)
        _robot_demo(
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
    from codesign_mb.studies.demo import LqgDemoConfig, run_lqg_demo

    cfg = load_config(LqgDemoConfig, config, overrides, section="demo")
    with progress_bar(f"LQG on {cfg.plant}", disable=as_json) as progress:
        result = run_lqg_demo(cfg, progress=progress)
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
    typer.echo(LQG_TABLE_NOTE)


def _robot_demo(
    ctx: Any,
    *,
    config: Any,
    reliability: list[float] | None,
    latency: int | None,
    episodes: int | None,
    seed: int,
    as_json: bool,
) -> None:
    """The body of ``codesign demo`` for the robot scenario."""
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
    from codesign_mb.studies.demo import RobotDemoConfig, run_robot_demo

    cfg = load_config(RobotDemoConfig, config, overrides, section="robot_demo")
    with progress_bar("MPC on the conveyor", disable=as_json) as progress:
        result = run_robot_demo(cfg, progress=progress)
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
        "delay-compensating Kalman prediction, none = stale observation)"
    )
    emit(rows, as_json=False, title=title)
    typer.echo(ROBOT_TABLE_NOTE)


def register(app: typer.Typer) -> None:
    """Add ``codesign demo`` to ``app``."""
    app.command()(cli_errors(demo))
