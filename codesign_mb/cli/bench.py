"""``codesign bench``: solver and simulator benchmarks, each living with its part.

The registry maps a benchmark name to ``"module:function"``; the function has the signature
``(*, repeats: int, seed: int) -> dict`` (JSON-able figures: times in seconds, rates in Hz,
...). Modules are imported only when their benchmark runs, so a part that is not there yet
gives a readable error instead of breaking the whole CLI. ``solvers/bench_*.py`` are thin
scripts calling the same functions.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable
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
    note,
    track,
)

__all__ = ["BENCHMARKS", "BenchConfig", "register", "resolve_benchmark", "run_benchmark"]

BENCHMARKS: dict[str, str] = {
    "env": "codesign_mb.bench.env:bench_env",
    "mpc": "codesign_mb.bench.mpc:bench_mpc",
    "allocators": "codesign_mb.bench.allocators:bench_allocators",
}
"""Benchmark name -> ``"module:function"``; the function is ``(*, repeats, seed) -> dict``."""

BenchFunction = Callable[..., dict[str, Any]]


@dataclass(frozen=True)
class BenchConfig:
    """Settings of ``codesign bench`` (config file table ``[bench]`` or top level)."""

    repeats: int = 20
    """Repetitions per measurement (>= 1)."""
    seed: int = 0
    """Root seed passed to the benchmark function."""

    def __post_init__(self) -> None:
        if isinstance(self.repeats, bool) or not isinstance(self.repeats, int):
            raise ValueError(f"repeats must be an integer, got {self.repeats!r}")
        if self.repeats < 1:
            raise ValueError(f"repeats must be >= 1, got {self.repeats}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")


def resolve_benchmark(name: str) -> BenchFunction:
    """Import the benchmark ``name`` lazily.

    Raises
    ------
    ValueError
        Unknown name, or its module/function does not exist (yet).
    """
    if name not in BENCHMARKS:
        raise ValueError(
            f"unknown benchmark {name!r}; expected one of {', '.join(sorted(BENCHMARKS))} or all"
        )
    target = BENCHMARKS[name]
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        # Only "this part is not written yet" is a user-facing error; a missing dependency
        # *inside* an existing module is re-raised with its traceback.
        if exc.name is None or not module_name.startswith(exc.name):
            raise
        raise ValueError(
            f"benchmark {name!r} is not available: module {module_name!r} does not exist yet"
        ) from None
    func = getattr(module, attr, None)
    if not callable(func):
        raise ValueError(f"benchmark {name!r} is not available: {target} is not defined")
    return func


def run_benchmark(name: str, *, repeats: int, seed: int) -> dict[str, Any]:
    """Run one benchmark; the result gets ``benchmark``, ``repeats``, ``seed``, ``wall_s``."""
    BenchConfig(repeats=repeats, seed=seed)  # validates
    func = resolve_benchmark(name)
    start = time.perf_counter()
    figures = func(repeats=repeats, seed=seed)
    wall = time.perf_counter() - start
    if not isinstance(figures, dict):
        raise TypeError(f"benchmark {name!r} must return a dict, got {type(figures).__name__}")
    return {"benchmark": name, "repeats": repeats, "seed": seed, **figures, "wall_s": wall}


def register(app: typer.Typer) -> None:
    """Add ``codesign bench`` to ``app``."""

    @app.command()
    @cli_errors
    def bench(
        ctx: typer.Context,
        name: Annotated[
            str,
            typer.Argument(
                help=f"Benchmark to run: {', '.join(BENCHMARKS)}, or 'all' (skips those whose "
                "part is not installed yet).",
                show_default=False,
            ),
        ],
        repeats: Annotated[
            int, typer.Option("--repeats", "-n", help="Repetitions per measurement.")
        ] = BenchConfig.repeats,
        seed: SeedOption = BenchConfig.seed,
        config: ConfigOption = None,
        as_json: JsonOption = False,
    ) -> None:
        """Time the hot paths: env steps/s, MPC solve time (s), allocator solve time (s).

        Prints one record per benchmark (times in seconds); nothing is written to disk.
        """
        cfg = load_config(
            BenchConfig, config, explicit(ctx, {"repeats": repeats, "seed": seed}), section="bench"
        )
        repeats, seed = cfg.repeats, cfg.seed
        if name == "all":
            results: list[dict[str, Any]] = []
            for bench_name in track(list(BENCHMARKS), description="bench", disable=as_json):
                try:
                    results.append(run_benchmark(bench_name, repeats=repeats, seed=seed))
                except ValueError as exc:
                    note(f"skipped: {exc}")
                    results.append({"benchmark": bench_name, "skipped": str(exc)})
            emit(results, as_json=as_json, title="benchmarks")
        else:
            emit(run_benchmark(name, repeats=repeats, seed=seed), as_json=as_json, title=name)
