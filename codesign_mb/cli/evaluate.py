"""``codesign evaluate``: seeded episodes of controller + estimator + QoS on the conveyor.

``codesign evaluate`` runs one configuration (100 episodes by default) and writes the
per-episode table and a JSON summary; ``codesign evaluate fig-cn`` makes the paper's Fig. 4
(success vs delay and vs reliability, with and without the predictor), model-based.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from codesign_mb.cli.common import (
    ConfigOption,
    FreshOption,
    JsonOption,
    OutOption,
    ScenarioOption,
    SeedOption,
    cli_errors,
    emit,
    explicit,
    load_config,
    note,
    progress_bar,
    track,
    writable_folder,
)

__all__ = ["evaluate_command", "fig_cn_command", "register"]

WorkersOption = Annotated[
    int | None,
    typer.Option("--workers", "-j", help="Worker processes. \\[default: one per CPU]"),
]


def evaluate_command(
    ctx: typer.Context,
    config: ConfigOption = None,
    controller: Annotated[str, typer.Option(help="Ideal controller: mpc or scripted.")] = "mpc",
    estimator: Annotated[
        str,
        typer.Option(
            help="Estimator: predictor (delay-compensating Kalman), belt_imm (switching-belt "
            "IMM with a carried mode) or none (stale observation)."
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
        typer.Option("--belt-speed", help="Belt speed in m/s. \\[default: the scenario's]"),
    ] = None,
    scenario: ScenarioOption = None,
    trials: Annotated[int, typer.Option("--trials", "-n", help="Episodes (>= 1).")] = 100,
    seed: SeedOption = 0,
    workers: WorkersOption = None,
    max_steps: Annotated[
        int | None,
        typer.Option(help="Cap on the steps of an episode. \\[default: the plant's horizon]"),
    ] = None,
    out: OutOption = Path("results/evaluate"),
    name: Annotated[str, typer.Option(help="Table name in the results folder.")] = "evaluate",
    fresh: FreshOption = False,
    as_json: JsonOption = False,
) -> None:
    """Evaluate controller + estimator + QoS policy on the conveyor (seeded, parallel).

    Runs seeded episodes in parallel and writes OUT/NAME.parquet/.csv/.json and a summary.
    The summary (success rate with its 95% Wilson interval, mean requested reliability,
    delivered fraction, mean age, failure reasons, MPC solve times, the object's estimation
    error per phase est_error_mm_<belt|grasp|carried> and, for the predictor, its NEES per
    phase with the 95% band of a consistent filter) is printed and written to
    OUT/NAME_summary.json. Finished episodes are kept in OUT/.records as they finish: rerun
    an interrupted command to resume it (--fresh: recompute). A config file may hold the
    options at top level or under \\[evaluate], with the tables \\[evaluate.env]
    (ConveyorConfig fields on top of the --scenario preset), \\[evaluate.mpc] (MpcConfig) and
    \\[evaluate.predictor] (the predictor's keyword arguments).
    """
    if ctx.invoked_subcommand is not None:
        return
    from codesign_mb.evaluation.evaluate import EvaluateConfig
    from codesign_mb.studies.evaluate_run import evaluation_label, run_evaluation

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
                "scenario": scenario,
                "trials": trials,
                "seed": seed,
                "workers": workers,
                "max_steps": max_steps,
            },
            rename={"belt_speed": "belt_speed_mps"},
        ),
        section="evaluate",
    )
    writable_folder("--out", out)
    label = evaluation_label(cfg)
    with progress_bar(label, disable=as_json) as progress:
        result = run_evaluation(cfg, out, name=name, progress=progress, fresh=fresh)
    if result.reused:
        note(f"resumed: {result.reused} episodes reused from {out / '.records'}")
    if not as_json:
        note(f"results written to {result.files['parquet']} and {result.files['summary']}")
    emit(result.summary, as_json=as_json, title=label)


def fig_cn_command(
    ctx: typer.Context,
    config: ConfigOption = None,
    trials: Annotated[int, typer.Option("--trials", "-n", help="Episodes per point (>= 1).")] = 100,
    seed: SeedOption = 0,
    workers: WorkersOption = None,
    delays: Annotated[
        list[int] | None,
        typer.Option("--delay", help="Fixed delays in steps (repeat). \\[default: 0..8]"),
    ] = None,
    belt_speeds: Annotated[
        list[float] | None,
        typer.Option("--belt-speed", help="Belt speeds in m/s (repeat). \\[default: 0.2, 0.6]"),
    ] = None,
    reliabilities: Annotated[
        list[float] | None,
        typer.Option(
            "--reliability",
            "-q",
            help="I.i.d. reliabilities (repeat). \\[default: 1 .8 .5 .3 .2 .1 .05]",
        ),
    ] = None,
    out: OutOption = Path("results/fig_cn"),
    fresh: FreshOption = False,
    as_json: JsonOption = False,
) -> None:
    """Fig. 4 (fig_cn): success vs delay and vs reliability; MPC +/- predictor, and the
    learned rows (stage-A controller alone, + MLP, + LSTM) when their checkpoints read the
    plant (else skipped, with the reason printed).

    Writes OUT/fig_cn.parquet/.csv/.json (one row per point, with Wilson intervals) and
    OUT/fig_cn.png. Config file: top level or \\[fig_cn] (FigCnConfig fields).
    """
    from codesign_mb.studies.fig_cn import FigCnConfig, learned_skip_reason, run_fig_cn_study

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
    writable_folder("--out", out)
    skipped = learned_skip_reason(cfg)
    if skipped is not None and not as_json:
        note(f"learned rows skipped: {skipped}")
    table, files = run_fig_cn_study(
        cfg,
        out,
        progress=lambda it, total: track(it, total=total, description="fig_cn", disable=as_json),
        fresh=fresh,
    )
    if as_json:
        emit(table, as_json=True)
        return
    note(f"results written to {files['csv']} and {files['png']}")
    emit(_fig_cn_rows(table), as_json=False, title=f"fig_cn: {cfg.trials} episodes per point")


def _fig_cn_rows(table: Any) -> list[dict[str, Any]]:
    """Fig. 4's points as printed: success with its interval, the MPC's failed solves."""
    rows = []
    for r in table.to_dict("records"):
        row = {
            "sweep": r["sweep"],
            "belt m/s": r["belt_speed_mps"],
            "pipeline": r.get("pipeline", ""),
            "estimator": r["estimator"],
            "tau": r["latency_steps"],
            "q": r["reliability"],
            "success": f"{r['success_rate']:.2f}",
            "95% CI": f"[{r['success_ci_low']:.2f}, {r['success_ci_high']:.2f}]",
        }
        if "mpc_failures" in r:
            row["MPC failures"] = r["mpc_failures"]
        rows.append(row)
    return rows


def register(app: typer.Typer) -> None:
    """Add ``codesign evaluate`` (and ``codesign evaluate fig-cn``) to ``app``."""
    group = typer.Typer(  # no help=: `evaluate --help` shows the callback's docstring
        name="evaluate",
        invoke_without_command=True,
        no_args_is_help=False,
    )
    group.callback()(cli_errors(evaluate_command))
    group.command("fig-cn")(cli_errors(fig_cn_command))
    app.add_typer(group)
