"""``codesign bench``: run one benchmark of :mod:`codesign_mb.bench.suite`, or all of them."""

from __future__ import annotations

from typing import Annotated

import typer

from codesign_mb.bench.suite import (
    BENCHMARKS,
    BenchConfig,
    BenchmarkFailed,
    run_all,
    run_benchmark,
)
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

__all__ = ["bench", "register"]


def bench(
    ctx: typer.Context,
    name: Annotated[
        str,
        typer.Argument(
            help=f"Benchmark to run: {', '.join(BENCHMARKS)}, or 'all' (fails if any fails).",
            show_default=False,
        ),
    ],
    repeats: Annotated[
        int, typer.Option("--repeats", help="Repetitions per measurement.")
    ] = BenchConfig.repeats,
    seed: SeedOption = BenchConfig.seed,
    config: ConfigOption = None,
    as_json: JsonOption = False,
) -> None:
    """Time the hot paths: env and closed-loop steps/s against bare physics, MPC and allocator
    solve times (s).

    Prints one record per benchmark (times in seconds); nothing is written to disk.
    """
    overrides = explicit(ctx, {"repeats": repeats, "seed": seed})
    cfg = load_config(BenchConfig, config, overrides, section="bench")
    if name != "all":
        result = run_benchmark(name, repeats=cfg.repeats, seed=cfg.seed)
        emit(result, as_json=as_json, title=name)
        return
    try:
        with progress_bar("bench", disable=as_json) as progress:
            results = run_all(repeats=cfg.repeats, seed=cfg.seed, progress=progress)
    except BenchmarkFailed as failure:
        emit(failure.results, as_json=as_json, title="benchmarks")
        typer.echo(f"error: {failure}", err=True)
        raise typer.Exit(code=1) from None
    emit(results, as_json=as_json, title="benchmarks")


def register(app: typer.Typer) -> None:
    """Add ``codesign bench`` to ``app``."""
    app.command()(cli_errors(bench))
