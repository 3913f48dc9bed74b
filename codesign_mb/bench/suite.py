"""The benchmark suite: every benchmark by name, run one or all, figures as JSON-ready dicts.

A benchmark is a function ``(*, repeats: int, seed: int) -> dict`` (times in seconds, rates in
Hz, ratios against bare physics measured in the same run). Modules are imported only when
their benchmark runs, so ``codesign --help`` stays fast. ``solvers/bench_*.py`` are thin
scripts over the same functions.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from codesign_mb.core.config import SEED_CAP, Cap, check_range
from codesign_mb.core.registry import resolve

__all__ = ["BENCHMARKS", "BenchConfig", "BenchmarkFailed", "run_all", "run_benchmark"]

BENCHMARKS: dict[str, str] = {
    "env": "codesign_mb.bench.env:bench_env",
    "loop": "codesign_mb.bench.loop:bench_loop",
    "mpc": "codesign_mb.bench.mpc:bench_mpc",
    "allocators": "codesign_mb.bench.allocators:bench_allocators",
    "estimator": "codesign_mb.bench.estimator:bench_estimator",
    "offline-lp": "codesign_mb.bench.offline_lp:bench_offline_lp",
}
"""Benchmark name -> ``"module:function"``; the function is ``(*, repeats, seed) -> dict``."""


REPEATS_CAP = Cap(10_000, "repetitions of a benchmark")


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
        check_range("repeats", self.repeats, ge=1, cap=REPEATS_CAP)
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        check_range("seed", self.seed, cap=SEED_CAP)


class BenchmarkFailed(RuntimeError):
    """Some benchmarks of :func:`run_all` raised; ``results`` holds every record."""

    def __init__(self, failed: list[str], results: list[dict[str, Any]]) -> None:
        errors = "; ".join(f"{r['benchmark']}: {r['error']}" for r in results if "error" in r)
        super().__init__(f"{len(failed)} benchmark(s) failed: {errors}")
        self.failed = failed
        self.results = results


def run_benchmark(name: str, *, repeats: int, seed: int) -> dict[str, Any]:
    """Run one benchmark; the result gets ``benchmark``, ``repeats``, ``seed``, ``wall_s``."""
    BenchConfig(repeats=repeats, seed=seed)  # validates
    if name not in BENCHMARKS:
        raise ValueError(
            f"unknown benchmark {name!r}; expected one of {', '.join(sorted(BENCHMARKS))} or all"
        )
    func: Callable[..., Any] = resolve(BENCHMARKS[name])
    start = time.perf_counter()
    figures = func(repeats=repeats, seed=seed)
    wall = time.perf_counter() - start
    if not isinstance(figures, dict):
        raise TypeError(f"benchmark {name!r} must return a dict, got {type(figures).__name__}")
    return {"benchmark": name, "repeats": repeats, "seed": seed, **figures, "wall_s": wall}


def run_all(
    *, repeats: int, seed: int, progress: Callable[[int, int], None] | None = None
) -> list[dict[str, Any]]:
    """Run every benchmark; raise :class:`BenchmarkFailed` (with all records) if any failed.

    A failing benchmark does not stop the others: its record holds ``error`` instead of
    figures, and the suite as a whole fails.
    """
    results: list[dict[str, Any]] = []
    failed: list[str] = []
    for i, name in enumerate(BENCHMARKS, start=1):
        try:
            results.append(run_benchmark(name, repeats=repeats, seed=seed))
        except Exception as exc:  # recorded, and the suite fails below
            failed.append(name)
            results.append({"benchmark": name, "error": f"{type(exc).__name__}: {exc}"})
        if progress is not None:
            progress(i, len(BENCHMARKS))
    if failed:
        raise BenchmarkFailed(failed, results)
    return results
