"""Sweeps over a grid of trials, on local processes or a Ray cluster, resumable.

A sweep is the grid ``pipelines x belt speeds x robot counts x replicates`` of one
*scenario*. Every grid point is one **trial**: a pure, picklable call
``run_trial(config: TrialConfig, seed: int) -> dict`` returning one table row. The same
trials give the same table whichever backend ran them:

- ``"serial"``: in this process (debugging, tiny sweeps);
- ``"local"`` (default): a ``spawn`` process pool on this machine;
- ``"ray"``: ``ray.remote`` tasks on ``ray.init(address=...)`` (a cluster), or on a local Ray
  instance when no address is given. The cluster's nodes need ``codesign_mb`` installed.

Seeds
-----
Trial seeds come from ``numpy.random.SeedSequence(seed).spawn(n_seeds)``: replicate ``r``
gets the same seed at every grid point (common random numbers), so pipelines, belt speeds
and robot counts are compared on the same draws.

Resuming
--------
The driver stores each finished trial as soon as it returns, one line of
``<out_dir>/.records/sweep_<name>.jsonl`` (:class:`~codesign_mb.core.records.RecordStore`,
the store of every long run). The key of a trial hashes everything its row depends on
(scenario, its params, grid point, seed), so rerunning an interrupted sweep only computes
the missing trials, and changing a parameter never reuses stale rows. The table is always
assembled from the rows as stored, in grid order, and written with
:func:`~codesign_mb.core.results.write_results` as ``<out_dir>/<name>.*``.

Scenarios
---------
A scenario is a module (registered in :data:`SWEEP_MODULES`, or any importable module path)
defining:

``run_trial(config: TrialConfig, seed: int) -> dict[str, scalar]``
    One trial, pure (everything random comes from ``seed``), returning the metrics of one
    row (floats, ints, bools, strings). The grid columns are added by the sweep.
``Params``
    A frozen, default-constructible dataclass of the scenario's settings;
    :attr:`SweepConfig.params` is parsed into it strictly (unknown keys are an error).
``PIPELINES``
    The pipeline names the scenario accepts; ``SweepConfig.pipelines = ()`` means
    ``DEFAULT_PIPELINES`` if the module defines it, else all.

Built in: ``"linear"`` (:mod:`codesign_mb.studies.sweep_linear`, LQG over a Bernoulli
link, milliseconds per trial) and ``"conveyor"`` (:mod:`codesign_mb.studies.sweep_conveyor`: the
MuJoCo pick-and-place with the pipelines of ``codesign table``, seconds per trial).

Ray
---
The Ray backend and :func:`~codesign_mb.studies.sweep_ray.tune_hyperparameters` (a
training-hyperparameter search with Ray Tune) are in :mod:`codesign_mb.studies.sweep_ray`.

The figure of a sweep is :func:`codesign_mb.studies.sweep_figures.plot_sweep`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import os
import re
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, Literal

import numpy as np
import pandas as pd

from codesign_mb.core.config import (
    EPISODES_CAP,
    ROBOTS_CAP,
    SEED_CAP,
    WORKERS_CAP,
    check_range,
    from_mapping,
    to_mapping,
)
from codesign_mb.core.records import RECORDS_DIR, RecordStore
from codesign_mb.core.results import to_jsonable, write_results
from codesign_mb.core.seeds import episode_seeds
from codesign_mb.evaluation import pool
from codesign_mb.plants.scenarios import SCENARIOS as CONVEYOR_SCENARIOS
from codesign_mb.studies.sweep_ray import iter_ray

__all__ = [
    "GRID_COLUMNS",
    "SWEEP_MODULES",
    "SweepConfig",
    "SweepResult",
    "TrialConfig",
    "execute_trial",
    "plan_sweep",
    "run_sweep",
]

Backend = Literal["serial", "local", "ray"]
BACKENDS: tuple[str, ...] = ("serial", "local", "ray")

SWEEP_MODULES: dict[str, str] = {
    "linear": "codesign_mb.studies.sweep_linear",
    "conveyor": "codesign_mb.studies.sweep_conveyor",
    **{name: "codesign_mb.studies.sweep_conveyor" for name in CONVEYOR_SCENARIOS},
}
"""Scenario name -> module defining ``run_trial``, ``Params`` and ``PIPELINES``. ``conveyor``
runs the conveyor on its ``paper`` scenario; a conveyor scenario name
(:data:`codesign_mb.plants.scenarios.SCENARIOS`) runs it on that scenario."""

GRID_COLUMNS: tuple[str, ...] = (
    "scenario",
    "pipeline",
    "belt_speed_mps",
    "n_robots",
    "replicate",
    "seed",
)
"""The columns every sweep row starts with (added by the sweep, not by ``run_trial``)."""

Scalar = float | int | bool | str | None

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
"""A sweep's name names its table and its records' file."""


@dataclass(frozen=True)
class TrialConfig:
    """One grid point of a sweep: what ``run_trial(config, seed)`` receives.

    Attributes
    ----------
    scenario:
        Scenario name (or module path).
    pipeline:
        Pipeline name, one of the scenario's ``PIPELINES``.
    belt_speed_mps:
        Conveyor belt speed in m/s.
    n_robots:
        Number of robots sharing the network.
    replicate:
        Replicate index in ``[0, n_seeds)``; the seed is derived from it.
    params:
        The scenario's ``Params`` instance (frozen dataclass).
    """

    scenario: str
    pipeline: str
    belt_speed_mps: float
    n_robots: int
    replicate: int
    params: Any = None


@dataclass(frozen=True)
class SweepConfig:
    """A sweep grid (``codesign sweep``; config file table ``[sweep]`` or top level).

    Attributes
    ----------
    scenario:
        Registered scenario (``linear``, ``conveyor``) or an importable module path.
    name:
        Table name in the results folder.
    seed:
        Root seed; replicate seeds are spawned from it.
    n_seeds:
        Replicates per grid point (>= 1).
    belt_speeds_mps:
        Belt speeds in m/s (>= 0).
    robot_counts:
        Numbers of robots sharing the network (>= 1).
    pipelines:
        Pipelines to compare; empty means all of the scenario's.
    params:
        Scenario settings, parsed strictly into the scenario's ``Params``.
    """

    scenario: str = "linear"
    name: str = "sweep"
    seed: int = 0
    n_seeds: int = 3
    belt_speeds_mps: tuple[float, ...] = (0.2, 0.6)
    robot_counts: tuple[int, ...] = (1,)
    pipelines: tuple[str, ...] = ()
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _require_int("seed", self.seed, minimum=0)
        _require_int("n_seeds", self.n_seeds, minimum=1)
        if not isinstance(self.scenario, str) or not self.scenario:
            raise ValueError(f"scenario must be a non-empty string, got {self.scenario!r}")
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty string, got {self.name!r}")
        speeds = tuple(_as_tuple("belt_speeds_mps", self.belt_speeds_mps))
        counts = tuple(_as_tuple("robot_counts", self.robot_counts))
        pipelines = tuple(_as_tuple("pipelines", self.pipelines))
        if not speeds:
            raise ValueError("belt_speeds_mps must not be empty")
        for v in speeds:
            if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
                raise ValueError(f"belt_speeds_mps must hold numbers, got {v!r}")
            if v < 0:
                raise ValueError(f"belt_speeds_mps must be >= 0, got {v!r}")
        if not counts:
            raise ValueError("robot_counts must not be empty")
        for n in counts:
            _require_int("robot_counts", n, minimum=1)
        for p in pipelines:
            if not isinstance(p, str) or not p:
                raise ValueError(f"pipelines must hold non-empty strings, got {p!r}")
        for label, values in (
            ("belt_speeds_mps", speeds),
            ("robot_counts", counts),
            ("pipelines", pipelines),
        ):
            if len(set(values)) != len(values):
                raise ValueError(f"{label} has duplicates: {list(values)!r}")
        if not isinstance(self.params, Mapping):
            raise ValueError(f"params must be a table, got {self.params!r}")
        object.__setattr__(self, "belt_speeds_mps", tuple(float(v) for v in speeds))
        object.__setattr__(self, "robot_counts", tuple(int(n) for n in counts))
        object.__setattr__(self, "pipelines", pipelines)
        object.__setattr__(self, "params", dict(self.params))
        check_range("seed", self.seed, cap=SEED_CAP)
        check_range("n_seeds", self.n_seeds, cap=EPISODES_CAP)
        check_range("robot_counts", counts, cap=ROBOTS_CAP)
        n_trials = len(speeds) * len(counts) * self.n_seeds * max(1, len(pipelines))
        check_range("the number of trials of the sweep", n_trials, cap=EPISODES_CAP)
        plan_sweep(self)  # the scenario, its pipelines and params, checked when loaded


def _require_int(name: str, value: Any, *, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}")


def _as_tuple(name: str, value: Any) -> tuple[Any, ...]:
    if isinstance(value, str) or not isinstance(value, Iterable):
        raise ValueError(f"{name} must be a list, got {value!r}")
    return tuple(value)


# --------------------------------------------------------------------------- scenarios


def _scenario_module_name(scenario: str) -> str:
    return SWEEP_MODULES.get(scenario, scenario)


def load_scenario(scenario: str) -> ModuleType:
    """Import the scenario module; a readable ``ValueError`` when it does not exist (yet)."""
    module_name = _scenario_module_name(scenario)
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is None or not module_name.startswith(exc.name):
            raise  # a dependency missing inside an existing scenario module: a real bug
        if scenario in SWEEP_MODULES:
            raise ValueError(
                f"scenario {scenario!r} is not available: module {module_name!r} does not exist yet"
            ) from None
        raise ValueError(
            f"unknown scenario {scenario!r}; expected one of {', '.join(SWEEP_MODULES)} "
            "or an importable module path"
        ) from None
    missing = [a for a in ("run_trial", "Params", "PIPELINES") if not hasattr(module, a)]
    if missing:
        raise ValueError(f"scenario module {module_name!r} does not define {', '.join(missing)}")
    return module


def plan_sweep(config: SweepConfig) -> list[tuple[TrialConfig, int]]:
    """The trials of ``config`` in grid order, with their seeds (validates the scenario).

    Order: pipelines (as configured), then belt speeds, robot counts, replicates.
    """
    module = load_scenario(config.scenario)
    known = tuple(module.PIPELINES)
    pipelines = config.pipelines or tuple(getattr(module, "DEFAULT_PIPELINES", known))
    unknown = [p for p in pipelines if p not in known]
    if unknown:
        raise ValueError(
            f"unknown pipeline{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
            f"for scenario {config.scenario!r}; expected one of {', '.join(known)}"
        )
    params = from_mapping(module.Params, config.params, where="params")
    seeds = episode_seeds(config.seed, config.n_seeds)
    return [
        (TrialConfig(config.scenario, p, v, n, r, params), seeds[r])
        for p in pipelines
        for v in config.belt_speeds_mps
        for n in config.robot_counts
        for r in range(config.n_seeds)
    ]


def trial_key(trial: TrialConfig, seed: int) -> str:
    """A stable hash of everything a trial's row depends on (file name of the stored row)."""
    params = to_mapping(trial.params) if dataclasses.is_dataclass(trial.params) else trial.params
    ident = {
        "scenario": _scenario_module_name(trial.scenario),
        "pipeline": trial.pipeline,
        "belt_speed_mps": trial.belt_speed_mps,
        "n_robots": trial.n_robots,
        "replicate": trial.replicate,
        "seed": seed,
        "params": to_jsonable(params),
    }
    text = json.dumps(ident, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def execute_trial(trial: TrialConfig, seed: int) -> dict[str, Scalar]:
    """Run one trial (in any process): grid columns + the scenario's metrics.

    This is the function shipped to workers; it imports the scenario by name, so it is
    picklable by reference.
    """
    module = load_scenario(trial.scenario)
    metrics = module.run_trial(trial, seed)
    if not isinstance(metrics, Mapping):
        raise TypeError(
            f"{module.__name__}.run_trial must return a dict, got {type(metrics).__name__}"
        )
    row: dict[str, Scalar] = {
        "scenario": trial.scenario,
        "pipeline": trial.pipeline,
        "belt_speed_mps": trial.belt_speed_mps,
        "n_robots": trial.n_robots,
        "replicate": trial.replicate,
        "seed": seed,
    }
    for name, value in metrics.items():
        if name in row:
            raise ValueError(f"{module.__name__}.run_trial returned grid column {name!r}")
        if isinstance(value, np.generic):
            value = value.item()
        if not isinstance(value, float | int | bool | str | type(None)):
            raise TypeError(
                f"{module.__name__}.run_trial: column {name!r} must be a scalar, "
                f"got {type(value).__name__}"
            )
        row[str(name)] = value
    return row


# --------------------------------------------------------------------------- backends

Pending = list[tuple[str, TrialConfig, int]]


def _iter_local(pending: Pending, workers: int) -> Iterator[tuple[str, dict[str, Scalar]]]:
    tasks = [(trial, seed) for _, trial, seed in pending]
    stream = pool.imap(execute_trial, tasks, workers=workers)
    for i, row in stream:
        yield pending[i][0], row


@dataclass(frozen=True)
class SweepResult:
    """What :func:`run_sweep` did: the table, where it went, computed vs. reused trials."""

    table: pd.DataFrame
    paths: dict[str, Path]
    computed: int
    reused: int
    backend: str

    @property
    def n_trials(self) -> int:
        return self.computed + self.reused


def run_sweep(
    config: SweepConfig,
    out_dir: str | Path,
    *,
    backend: Backend = "local",
    address: str | None = None,
    workers: int | None = None,
    fresh: bool = False,
    progress: Callable[[Iterator[Any], int], Iterable[Any]] | None = None,
) -> SweepResult:
    """Run (or resume) the sweep ``config`` and write its table into ``out_dir``.

    Parameters
    ----------
    config:
        The grid.
    out_dir:
        Results folder; finished trials are kept in ``out_dir/.records/sweep_<name>.jsonl``.
    backend:
        ``"local"`` (process pool), ``"ray"`` or ``"serial"``.
    address:
        Ray cluster address (``"auto"``, ``"ray://host:10001"``, ...); ``None`` starts a local
        Ray instance with ``workers`` CPUs (or uses the one already initialised).
    workers:
        Parallel trials (local pool size / local Ray CPUs); default ``os.cpu_count()``.
    fresh:
        Reuse no stored trial: recompute everything.
    progress:
        Wraps the stream of finished trials, e.g.
        ``lambda it, total: track(it, total=total, description="sweep")``.

    Returns
    -------
    SweepResult
        The table (grid columns :data:`GRID_COLUMNS` then the scenario's metrics, in grid
        order), the written paths, and how many trials were computed vs. reused.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if address is not None and backend != "ray":
        raise ValueError("address is only used with backend 'ray'")
    if workers is not None:
        _require_int("workers", workers, minimum=1)
        check_range("workers", workers, cap=WORKERS_CAP)
    if not _NAME.match(config.name):
        raise ValueError(f"name must match {_NAME.pattern}, got {config.name!r}")
    plan = plan_sweep(config)
    out = Path(out_dir)
    store = RecordStore(out / RECORDS_DIR, what="trial", fresh=fresh)
    group = f"sweep_{config.name}"
    keyed = [(trial_key(trial, seed), trial, seed) for trial, seed in plan]
    rows = store.take(group, [key for key, _, _ in keyed])
    pending = [item for item in keyed if item[0] not in rows]
    n_workers = min(workers or os.cpu_count() or 1, max(len(pending), 1))
    if not pending:
        stream: Iterator[tuple[str, dict[str, Scalar]]] = iter(())
    elif backend == "serial":
        stream = _iter_local(pending, 1)
    elif backend == "local":
        stream = _iter_local(pending, n_workers)
    else:
        stream = iter_ray(execute_trial, pending, n_workers, address)

    def stored() -> Iterator[tuple[str, dict[str, Scalar]]]:
        for key, row in stream:  # stored as soon as the driver has it
            rows[key] = store.add(group, key, row)
            yield key, rows[key]

    with store.on_interrupt():
        for _ in progress(stored(), len(pending)) if progress is not None else stored():
            pass
    table = pd.DataFrame([rows[key] for key, _, _ in keyed])
    paths = write_results(
        out,
        table=table,
        config=config,
        name=config.name,
        extra={
            "kind": "sweep",
            "backend": backend,
            "n_trials": len(keyed),
            "computed": len(pending),
            "reused": len(keyed) - len(pending),
            "trial_store": str(store.path(group).relative_to(out)),
        },
    )
    return SweepResult(
        table=table,
        paths=paths,
        computed=len(pending),
        reused=len(keyed) - len(pending),
        backend=backend,
    )
