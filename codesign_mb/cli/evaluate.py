"""``codesign evaluate``: seeded episodes of controller + estimator + QoS on the conveyor.

``codesign evaluate`` runs one configuration (100 episodes by default) and writes the
per-episode table and a JSON summary; ``codesign evaluate fig-cn`` makes the paper's Fig. 4
(success vs delay and vs reliability, with and without the predictor), model-based.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from codesign_mb.cli.common import (
    ConfigOption,
    JsonOption,
    OutOption,
    SeedOption,
    cli_errors,
    emit,
    explicit,
    load_config,
    note,
    track,
)

__all__ = ["register"]

WorkersOption = Annotated[
    int | None,
    typer.Option("--workers", "-j", help="Worker processes. [default: one per CPU]"),
]


def register(app: typer.Typer) -> None:
    """Add ``codesign evaluate`` (and ``codesign evaluate fig-cn``) to ``app``."""
    group = typer.Typer(
        name="evaluate",
        help="Evaluate controller + estimator + QoS policy on the conveyor (seeded, parallel).",
        invoke_without_command=True,
        no_args_is_help=False,
    )

    @group.callback()
    @cli_errors
    def evaluate(
        ctx: typer.Context,
        config: ConfigOption = None,
        controller: Annotated[str, typer.Option(help="Ideal controller: mpc or scripted.")] = "mpc",
        estimator: Annotated[
            str,
            typer.Option(
                help="Estimator: predictor (delay-compensating Kalman) or none (stale observation)."
            ),
        ] = "predictor",
        qos: Annotated[str, typer.Option(help="QoS policy: static.")] = "static",
        reliability: Annotated[
            float, typer.Option("--reliability", "-q", help="Requested reliability q in [0, 1].")
        ] = 1.0,
        latency_steps: Annotated[
            int,
            typer.Option("--latency-steps", "--delay", help="Latency tau in 40 ms steps (>= 0)."),
        ] = 0,
        belt_speed: Annotated[
            float | None,
            typer.Option("--belt-speed", help="Belt speed in m/s. [default: the env's]"),
        ] = None,
        trials: Annotated[int, typer.Option("--trials", "-n", help="Episodes (>= 1).")] = 100,
        seed: SeedOption = 0,
        workers: WorkersOption = None,
        max_steps: Annotated[
            int | None, typer.Option(help="Cap on the steps of an episode. [default: horizon]")
        ] = None,
        out: OutOption = Path("results/evaluate"),
        name: Annotated[str, typer.Option(help="Table name in the results folder.")] = "evaluate",
        as_json: JsonOption = False,
    ) -> None:
        """Run seeded episodes in parallel; write OUT/NAME.parquet/.csv/.json and a summary.

        The summary (success rate with its 95% Wilson interval, mean requested reliability,
        delivered fraction, mean age, MPC solve times) is printed and written to
        OUT/NAME_summary.json. A config file may hold the options at top level or under
        [evaluate], with the tables [evaluate.env] (ConveyorConfig), [evaluate.mpc]
        (MpcConfig) and [evaluate.predictor].
        """
        if ctx.invoked_subcommand is not None:
            return
        import json

        from codesign_mb.core.results import atomic_write, to_jsonable, write_results
        from codesign_mb.evaluation.evaluate import EvaluateConfig, iter_episodes, rows_to_table
        from codesign_mb.evaluation.evaluate import summarize as summarize_table

        cfg = load_config(
            EvaluateConfig,
            config,
            explicit(
                ctx,
                {
                    "controller": controller,
                    "estimator": estimator,
                    "qos": qos,
                    "reliability": reliability,
                    "latency_steps": latency_steps,
                    "belt_speed": belt_speed,
                    "trials": trials,
                    "seed": seed,
                    "workers": workers,
                    "max_steps": max_steps,
                },
                rename={"belt_speed": "belt_speed_mps"},
            ),
            section="evaluate",
        )
        ctl, est, policy = cfg.components()
        rows = iter_episodes(
            ctl,
            est,
            policy,
            cfg.env_config(),
            cfg.trials,
            cfg.seed,
            workers=cfg.workers,
            max_steps=cfg.max_steps,
        )
        label = f"{cfg.controller}+{cfg.estimator} q={cfg.reliability:g} tau={cfg.latency_steps}"
        table = rows_to_table(
            list(track(rows, total=cfg.trials, description=label, disable=as_json))
        )
        summary = summarize_table(table)
        paths = write_results(out, table=table, config=cfg, name=name, extra={"summary": summary})
        summary_path = Path(out) / f"{name}_summary.json"
        with atomic_write(summary_path, "w") as fh:
            fh.write(json.dumps(to_jsonable(summary), indent=2) + "\n")
        if not as_json:
            note(f"results written to {paths['parquet']} and {summary_path}")
        emit(summary, as_json=as_json, title=label)

    @group.command("fig-cn")
    @cli_errors
    def fig_cn(
        ctx: typer.Context,
        config: ConfigOption = None,
        trials: Annotated[
            int, typer.Option("--trials", "-n", help="Episodes per point (>= 1).")
        ] = 100,
        seed: SeedOption = 0,
        workers: WorkersOption = None,
        delays: Annotated[
            list[int] | None,
            typer.Option("--delay", help="Fixed delays in steps (repeat). [default: 0..8]"),
        ] = None,
        belt_speeds: Annotated[
            list[float] | None,
            typer.Option("--belt-speed", help="Belt speeds in m/s (repeat). [default: 0.2, 0.6]"),
        ] = None,
        reliabilities: Annotated[
            list[float] | None,
            typer.Option(
                "--reliability",
                "-q",
                help="I.i.d. reliabilities (repeat). [default: 1 .8 .5 .3 .2 .1 .05]",
            ),
        ] = None,
        out: OutOption = Path("results/fig_cn"),
        as_json: JsonOption = False,
    ) -> None:
        """Fig. 4 (fig_cn), model-based: success vs delay and vs reliability, +/- predictor.

        Writes OUT/fig_cn.parquet/.csv/.json (one row per point, with Wilson intervals) and
        OUT/fig_cn.png. Config file: top level or [fig_cn] (FigCnConfig fields).
        """
        from codesign_mb.core.results import write_results
        from codesign_mb.studies.fig_cn import FigCnConfig, plot_fig_cn, run_fig_cn

        cfg = load_config(
            FigCnConfig,
            config,
            explicit(
                ctx,
                {
                    "trials": trials,
                    "seed": seed,
                    "workers": workers,
                    "delays": delays,
                    "belt_speeds": belt_speeds,
                    "reliabilities": reliabilities,
                },
                rename={"belt_speeds": "belt_speeds_mps"},
            ),
            section="fig_cn",
        )
        table = run_fig_cn(
            cfg,
            progress=lambda it, total: track(
                it, total=total, description="fig_cn", disable=as_json
            ),
        )
        paths = write_results(out, table=table, config=cfg, name="fig_cn")
        png = plot_fig_cn(table, Path(out) / "fig_cn.png")
        if not as_json:
            note(f"results written to {paths['csv']} and {png}")
        if as_json:
            emit(table, as_json=True)
            return
        rows = [
            {
                "sweep": r.sweep,
                "belt m/s": r.belt_speed_mps,
                "estimator": r.estimator,
                "tau": r.latency_steps,
                "q": r.reliability,
                "success": f"{r.success_rate:.2f}",
                "95% CI": f"[{r.success_ci_low:.2f}, {r.success_ci_high:.2f}]",
            }
            for r in table.itertuples()
        ]
        emit(rows, as_json=False, title=f"fig_cn: {cfg.trials} episodes per point")

    app.add_typer(group)
