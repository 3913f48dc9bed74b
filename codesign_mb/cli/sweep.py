"""``codesign sweep``: a grid of trials on local processes or a Ray cluster, resumable."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from codesign_mb.cli.common import (
    SCENARIO_NAMES,
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
    writable_folder,
)

__all__ = ["register", "sweep_command"]

_DEFAULTS: dict[str, Any] = {
    "scenario": "linear",
    "name": "sweep",
    "seed": 0,
    "n_seeds": 3,
}
"""Mirrors :class:`codesign_mb.studies.sweep.SweepConfig` (kept here so --help is fast)."""


_HELP = (
    "Run a sweep: pipelines x belt speeds x robot counts x seeds, one row per trial.\n\n"
    "Finished trials are kept in OUT/.records/sweep_NAME.jsonl, so rerunning an interrupted "
    "sweep computes only the missing ones; the table goes to OUT/NAME.parquet (+ .csv, .json). "
    "A config file "
    "holds the grid at top level or under \\[sweep] (keys: scenario, name, seed, n_seeds, "
    "belt_speeds_mps, robot_counts, pipelines) and the scenario's settings under "
    "\\[sweep.params] (linear: reliability, latency_steps, capacity_robots, horizon_steps, ...; "
    "conveyor: episodes, horizon, belt_profile, link, capacity_robots, channel, scheduler, "
    "plant_options), or with --param KEY=VALUE."
)


def _parse_param(item: str) -> tuple[str, Any]:
    """A ``--param`` assignment: ``key=value`` with a JSON value (else a string)."""
    import json

    key, sep, text = item.partition("=")
    if not sep or not key.strip():
        raise ValueError(f"--param expects key=value, got {item!r}")
    try:
        value = json.loads(text.strip())
    except json.JSONDecodeError:
        value = text.strip()
    return f"params.{key.strip()}", value


def sweep_command(
    ctx: typer.Context,
    config: ConfigOption = None,
    out: OutOption = Path("results/sweep"),
    scenario: Annotated[
        str,
        typer.Option(
            help="Scenario: 'linear' (LQG over a lossy link, fast), 'conveyor' (MuJoCo "
            "pick-and-place on its paper scenario), a conveyor scenario preset ("
            + ", ".join(SCENARIO_NAMES)
            + "; configs/scenarios/), or an importable module path."
        ),
    ] = _DEFAULTS["scenario"],
    pipelines: Annotated[
        list[str] | None,
        typer.Option(
            "--pipeline",
            "-p",
            help="Pipeline to compare (repeat the option). \\[default: all of the scenario's]",
        ),
    ] = None,
    belt_speeds: Annotated[
        list[float] | None,
        typer.Option(
            "--belt-speed",
            "-v",
            help="Belt speed in m/s (repeat the option). \\[default: 0.2, 0.6]",
        ),
    ] = None,
    robot_counts: Annotated[
        list[int] | None,
        typer.Option(
            "--robots",
            help="Number of robots sharing the network (repeat the option). \\[default: 1]",
        ),
    ] = None,
    n_seeds: Annotated[
        int,
        typer.Option(
            "--seeds", "--trials", "-n", help="Replicates (trials, one seed each) per grid point."
        ),
    ] = _DEFAULTS["n_seeds"],
    seed: SeedOption = _DEFAULTS["seed"],
    name: Annotated[str, typer.Option(help="Table name in the results folder.")] = _DEFAULTS[
        "name"
    ],
    backend: Annotated[
        str,
        typer.Option(
            help="Where trials run: 'local' (process pool), 'ray' (cluster at --address, "
            "or a local Ray instance), 'serial' (this process)."
        ),
    ] = "local",
    address: Annotated[
        str | None,
        typer.Option(help="Ray cluster address ('auto', 'ray://host:10001'); needs --backend ray."),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(help="Parallel trials (pool size / local Ray CPUs). \\[default: all CPUs]"),
    ] = None,
    params: Annotated[
        list[str] | None,
        typer.Option(
            "--param",
            help="Scenario setting key=value (JSON value; repeat the option), on top of "
            "\\[sweep.params]: --param horizon=40 --param link=wifi",
        ),
    ] = None,
    fresh: Annotated[
        bool,
        typer.Option("--fresh", help="Recompute every trial instead of resuming."),
    ] = False,
    as_json: JsonOption = False,
) -> None:
    """Run a sweep: pipelines x belt speeds x robot counts x seeds, one row per trial."""
    from codesign_mb.studies.sweep import SweepConfig, run_sweep

    overrides = explicit(
        ctx,
        {
            "scenario": scenario,
            "pipelines": pipelines,
            "belt_speeds": belt_speeds,
            "robot_counts": robot_counts,
            "n_seeds": n_seeds,
            "seed": seed,
            "name": name,
        },
        rename={"belt_speeds": "belt_speeds_mps"},
    )
    overrides.update(_parse_param(p) for p in params or [])
    cfg = load_config(SweepConfig, config, overrides, section="sweep")
    writable_folder("--out", out)
    result = run_sweep(  # Ctrl-C: cli_errors says which trials are kept
        cfg,
        out,
        backend=backend,  # type: ignore[arg-type]  # validated by run_sweep
        address=address,
        workers=workers,
        fresh=fresh,
        progress=lambda it, total: track(
            it, total=total, description=f"sweep {cfg.name}", disable=as_json
        ),
    )
    if not as_json:
        note(
            f"{result.n_trials} trials ({result.computed} computed, {result.reused} reused); "
            f"results written to {result.paths['parquet']}"
        )
    emit(
        {
            "results_dir": str(out),
            "table": cfg.name,
            "files": {k: str(v) for k, v in result.paths.items()},
            "backend": result.backend,
            "n_trials": result.n_trials,
            "computed": result.computed,
            "reused": result.reused,
        },
        as_json=as_json,
        title="sweep",
    )


def register(app: typer.Typer) -> None:
    """Add ``codesign sweep`` to ``app``."""
    app.command("sweep", help=_HELP)(cli_errors(sweep_command))
