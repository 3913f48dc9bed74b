"""``codesign tune``: the covariance rule's threshold for a success target, on the dev seeds.

Bisects (log scale) the ``threshold_m`` of the model-based co-design row's rule (MPC +
predictor + rule; the rule's other options are the row's) on a scenario's conveyor, each
probe ``-n`` episodes of the ``dev`` seed set (``--seed-set test`` is refused: reported
numbers come from it). A threshold meets the target when its success rate on those episodes
(the point estimate) is at least ``--target``; the chosen one is the largest that does (the
least network). Writes into ``OUT``:

``tune_probes.{parquet,csv,json}``
    One row per probe (threshold, success with its 95 % Wilson interval, mean requested
    reliability, delivered fraction, whether it met the target, the chosen one); the
    metadata holds the search, the choice and provenance (commit, versions).
``tune_episodes.*``
    Every episode of every probe.

``--write`` also stores the chosen threshold, with the search and its provenance, in the
shipped file the tables read (``models/tuned/rule_threshold.json``, keyed by scenario;
:mod:`codesign_mb.studies.tuned`); only a threshold that met the target is stored. Run it
again whenever the rule, the row or the scenario changes: a table falls back to the default
threshold (with a warning) for a stored value whose rule options or plant no longer match.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Annotated

import typer

from codesign_mb.cli.common import (
    SCENARIO_HELP,
    ConfigOption,
    JsonOption,
    cli_errors,
    emit,
    explicit,
    load_config,
    note,
    progress_bar,
    writable_folder,
)
from codesign_mb.plants.scenarios import DEFAULT_SCENARIO

__all__ = ["register", "tune_command"]


def tune_command(
    ctx: typer.Context,
    scenario: Annotated[
        str | None,
        typer.Option(
            "--scenario",
            help=f"{SCENARIO_HELP} The plant tuned for (and the key --write stores under). "
            f"\\[default: {DEFAULT_SCENARIO}]",
            show_default=False,
        ),
    ] = None,
    target: Annotated[
        float,
        typer.Option("--target", help="Success rate (point estimate on dev) to reach, in [0, 1]."),
    ] = 0.98,
    trials: Annotated[int, typer.Option("--trials", "-n", help="Episodes per probe.")] = 100,
    workers: Annotated[int, typer.Option("--workers", "-j", help="Worker processes.")] = 1,
    iterations: Annotated[int, typer.Option("--iterations", help="Bisection probes.")] = 7,
    low: Annotated[float, typer.Option("--low", help="Lower end of the bracket (m).")] = 0.002,
    high: Annotated[float, typer.Option("--high", help="Upper end of the bracket (m).")] = 1.0,
    seed_set_name: Annotated[
        str, typer.Option("--seed-set", help="Named seed set probed (test is refused).")
    ] = "dev",
    config: ConfigOption = None,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            "-o",
            help="Results folder (created if missing). \\[default: results/tune/SCENARIO]",
            file_okay=False,
            show_default=False,
        ),
    ] = None,
    write: Annotated[
        bool,
        typer.Option(
            "--write/--no-write",
            help="Store the chosen threshold in the shipped file the tables read "
            "(models/tuned/rule_threshold.json); only if it met the target.",
        ),
    ] = False,
    tuned_file: Annotated[
        Path | None,
        typer.Option(
            "--tuned-file",
            help="The file --write stores into. \\[default: the package's "
            "models/tuned/rule_threshold.json]",
            dir_okay=False,
            show_default=False,
        ),
    ] = None,
    as_json: JsonOption = False,
) -> None:
    """Bisect the rule threshold for a success target on the dev seeds; write the probes."""
    from codesign_mb.studies.tune import TuneConfig, run_tune, tuned_entry, write_tune_results
    from codesign_mb.studies.tuned import write_tuned

    cfg = load_config(
        TuneConfig,
        config,
        explicit(
            ctx,
            {
                "scenario": scenario,
                "target": target,
                "trials": trials,
                "workers": workers,
                "iterations": iterations,
                "low": low,
                "high": high,
                "seed_set_name": seed_set_name,
            },
            rename={
                "target": "target_success",
                "low": "low_m",
                "high": "high_m",
                "seed_set_name": "seed_set",
            },
        ),
        section="tune",
    )
    if write and cfg.plant is not None:
        raise ValueError("--write stores thresholds by scenario; this config tunes a custom plant")
    out = out if out is not None else Path("results/tune") / cfg.target_name()
    writable_folder("--out", out)
    command = "codesign " + shlex.join(sys.argv[1:])
    with progress_bar(f"tune {cfg.target_name()}", disable=as_json) as progress:
        result = run_tune(cfg, progress=progress)
    write_tune_results(result, out, command=command)
    note(f"results written to {out}")
    if result.limited_by == "high":
        note("every probe met the target: --high set the threshold (a larger one may do as well)")
    summary = {
        "target": cfg.target_name(),
        "threshold_m": result.threshold_m,
        "target_success": cfg.target_success,
        "target_met": result.target_met,
        "limited_by": result.limited_by,
        "dev_success_rate": result.chosen["success_rate"],
        "dev_success_ci": [result.chosen["success_ci_low"], result.chosen["success_ci_high"]],
        "dev_mean_requested_reliability": result.chosen["mean_requested_reliability"],
        "seed_set": cfg.seed_set,
        "episodes_per_probe": cfg.trials,
        "bracket_m": [cfg.low_m, cfg.high_m],
        "probes": result.probes[
            ["threshold_m", "success_rate", "mean_requested_reliability", "meets_target"]
        ],
        "wall_time_s": result.wall_time_s,
        "written": None,
    }
    if write:
        if not result.target_met:
            raise ValueError(
                f"no threshold in [{cfg.low_m:g}, {cfg.high_m:g}] m reached "
                f"{cfg.target_success:g} on {cfg.seed_set} (at --low: "
                f"{result.chosen['success_rate']:g}); nothing written (lower --low?)"
            )
        summary["written"] = str(
            write_tuned(cfg.scenario, tuned_entry(result, command=command), tuned_file)
        )
        note(f"threshold for {cfg.scenario!r} stored in {summary['written']}")
    if as_json:
        emit(summary, as_json=True)
        return
    probes = summary.pop("probes")
    emit(probes, as_json=False, title="probes (in order)")
    emit(summary, as_json=False, title=f"codesign tune: {cfg.target_name()}")


def register(app: typer.Typer) -> None:
    """Add ``codesign tune`` to ``app``."""
    app.command("tune")(cli_errors(tune_command))
