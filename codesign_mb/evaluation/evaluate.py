"""Seeded, parallel evaluation of a (controller, estimator, QoS policy) triple on a plant.

The way the paper evaluates its policies (Table ``tab_p``, Fig. ``fig_cn``): many independent
seeded episodes, success rate with a confidence interval, the mean requested reliability
(the paper's "average PDR"), the delivered fraction and the age of what the robot acted on.

Reproducibility: episode ``i`` gets the seed ``SeedSequence(seed).spawn(trials)[i]``, every
component is reset from it at the episode's start (the controller also drops its solver's
warm start), and episodes run in fresh copies of the components. The table is therefore the
same whatever the number of worker processes, except the wall-time columns
(:data:`TIMING_COLUMNS`). The rows and their aggregate are
:mod:`codesign_mb.evaluation.metrics`' (re-exported here).

Episodes run in the one process pool (:mod:`codesign_mb.evaluation.pool`); a script calling
:func:`evaluate` with ``workers > 1`` needs the usual ``if __name__ == "__main__":`` guard.
With a :class:`~codesign_mb.core.records.RecordStore` (``store=``), every episode is kept as
it finishes, keyed by everything that determines it, and a rerun takes the kept ones instead
of running them (:func:`run_jobs`): an interrupted evaluation resumes to the same table.

Components are given either as instances (pickled into each worker and reset per episode)
or as picklable factories, called once per worker as ``factory(env)`` (``env`` is the plant,
unwrapped) or ``factory()`` when they take no argument; the component registry
(:mod:`codesign_mb.core.registry`) turns a kind name (``"mpc"``, ``"predictor"``,
``"none"``, ...) into such a factory.
"""

from __future__ import annotations

import inspect
import math
import pickle
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import pandas as pd

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.mpc import MpcConfig
from codesign_mb.core import registry
from codesign_mb.core.config import STEPS_CAP, WORKERS_CAP, check_range, from_mapping
from codesign_mb.core.records import RecordStore, digest
from codesign_mb.core.registry import ComponentSpec, Factory
from codesign_mb.core.seeds import episode_seeds
from codesign_mb.evaluation import pool
from codesign_mb.evaluation.metrics import TIMING_COLUMNS, episode_row, rows_to_table, summarize
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.qos import QosRequest
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace
from codesign_mb.plants.scenarios import DEFAULT_SCENARIO, get_scenario
from codesign_mb.rollout import rollout

__all__ = [
    "TIMING_COLUMNS",
    "EvaluateConfig",
    "episode_record",
    "episode_row",
    "evaluate",
    "iter_episodes",
    "make_env",
    "rows_to_table",
    "run_config",
    "run_jobs",
    "summarize",
]


def make_env(env_config: Any) -> Any:
    """The plant env of ``env_config``: a ``ConveyorConfig``, or a zero-argument env factory."""
    if isinstance(env_config, ConveyorConfig):
        return ConveyorPickPlace(config=env_config)
    if callable(env_config):
        return env_config()
    raise ValueError(
        f"no env known for a {type(env_config).__name__}; pass a ConveyorConfig or an env factory"
    )


def _is_instance_of(obj: Any, method: str) -> bool:
    return not isinstance(obj, type) and not isinstance(obj, Factory) and hasattr(obj, method)


def _build(spec: Any, method: str, env: Any, what: str) -> Any:
    if _is_instance_of(spec, method):
        return spec
    if not callable(spec):
        raise TypeError(f"{what} must be an instance with .{method}() or a factory, got {spec!r}")
    if isinstance(spec, Factory):
        obj = spec(env)
    else:
        try:
            params = inspect.signature(spec).parameters.values()
            required = [
                p
                for p in params
                if p.default is p.empty and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
            ]
        except (TypeError, ValueError):
            required = []
        obj = spec(env) if required else spec()
    if not hasattr(obj, method):
        raise TypeError(f"{what} factory returned {obj!r}, which has no .{method}()")
    return obj


# -- episodes --------------------------------------------------------------------------------
@dataclass
class _Job:
    """Everything a worker needs; pickled once per worker."""

    controller: Any
    estimator: Any
    qos_policy: Any
    env_config: Any
    link: Any
    max_steps: int | None


class _Runner:
    """The components of one process, built once, reset per episode."""

    def __init__(self, job: _Job) -> None:
        env = make_env(job.env_config)
        link = job.link if job.link is not None else BernoulliLink()
        if not hasattr(link, "step"):
            link = _build(link, "step", env, "link")
        qos = _build(job.qos_policy, "request", env, "qos_policy")
        self.env = LinkObservationWrapper(env, link, qos)
        self.estimator = _build(job.estimator, "estimate", env, "estimator")
        self.controller = _build(job.controller, "act", env, "controller")
        self.max_steps = job.max_steps

    def run(self, episode: int, seed: int) -> dict[str, Any]:
        return episode_record(
            self.env,
            self.estimator,
            self.controller,
            seed,
            episode=episode,
            max_steps=self.max_steps,
        )


def episode_record(
    env: LinkObservationWrapper,
    estimator: Any,
    controller: Any,
    seed: int,
    *,
    episode: int = 0,
    max_steps: int | None = None,
) -> dict[str, Any]:
    """One episode's row of an evaluation: :func:`episode_row`, each component's
    ``episode_metrics()`` (phase errors, CPU time) and the wall time."""
    start = time.perf_counter()
    steps = rollout(env, estimator, controller, seed=seed, max_steps=max_steps)
    row: dict[str, Any] = {"episode": episode, "seed": seed}
    row.update(episode_row(steps))
    for obj in (controller, estimator, env.qos_policy):
        metrics = getattr(obj, "episode_metrics", None)
        if callable(metrics):
            row.update(metrics())
    row["wall_time_s"] = time.perf_counter() - start
    return row


_RUNNERS: dict[int, _Runner] = {}
_PAYLOADS: list[bytes] = []
_CACHE = 2  # runners kept per process (each holds an env and a built controller)


def _runner_for(job: int) -> _Runner:
    runner = _RUNNERS.get(job)
    if runner is None:
        while len(_RUNNERS) >= _CACHE:
            _RUNNERS.pop(next(iter(_RUNNERS)))
        runner = _Runner(pickle.loads(_PAYLOADS[job]))
        _RUNNERS[job] = runner
    return runner


def _load_payloads(payloads: list[bytes]) -> None:
    _RUNNERS.clear()
    _PAYLOADS[:] = payloads


def _run_episode(job: int, episode: int, seed: int) -> tuple[int, dict[str, Any]]:
    return job, _runner_for(job).run(episode, seed)


def run_jobs(
    jobs: Sequence[tuple[Any, Any, Any, Any, int, int]],
    *,
    link: Any = None,
    workers: int | None = None,
    max_steps: int | None = None,
    store: RecordStore | None = None,
) -> Iterator[tuple[int, dict[str, Any]]]:
    """Run several evaluations in one process pool, yielding ``(job index, row)`` as done.

    Each job is ``(controller, estimator, qos_policy, env_config, trials, seed)`` as in
    :func:`evaluate`; all episodes of all jobs share the pool (e.g. the points of a figure).
    With a ``store`` (:class:`~codesign_mb.core.records.RecordStore`), episodes it holds are
    yielded first without running them, and every other one is stored as it finishes, keyed
    by its job's components, plant, link, step cap and root seed, and its index and seed.
    """
    payloads: list[bytes] = []
    tasks: list[tuple[int, int, int]] = []
    groups: list[str] = []
    for j, (controller, estimator, qos_policy, env_config, trials, seed) in enumerate(jobs):
        if qos_policy is None:
            qos_policy = StaticQos()
        job = _Job(controller, estimator, qos_policy, env_config, link, max_steps)
        payloads.append(pickle.dumps(job))  # fails early, here, on an unpicklable component
        tasks.extend((j, i, s) for i, s in enumerate(episode_seeds(seed, trials)))
        if store is not None:
            groups.append(digest({"episodes of": job, "seed": seed}))
    if store is not None:
        kept: dict[tuple[int, int, int], dict[str, Any]] = {}
        for group in dict.fromkeys(groups):
            mine: dict[str, list[tuple[int, int, int]]] = {}
            for j, i, s in tasks:
                if groups[j] == group:
                    mine.setdefault(f"{i}:{s}", []).append((j, i, s))
            for item, row in store.take(group, mine).items():
                kept.update((task, row) for task in mine[item])
        for (j, _, _), row in kept.items():
            yield j, row
        tasks = [t for t in tasks if t not in kept]
    for j, i, s, row in _run_tasks(tasks, payloads, workers):
        yield j, row if store is None else store.add(groups[j], f"{i}:{s}", row)


def _run_tasks(
    tasks: list[tuple[int, int, int]], payloads: list[bytes], workers: int | None
) -> Iterator[tuple[int, int, int, dict[str, Any]]]:
    """``(job, episode, seed, row)`` of every task ``(job, episode, seed)``, as each finishes."""
    if not tasks:
        return
    if pool.check_workers(workers, len(tasks)) == 1:  # in this process, fresh components
        runners: dict[int, _Runner] = {}
        for j, i, s in tasks:
            if j not in runners:
                runners.clear()
                runners[j] = _Runner(pickle.loads(payloads[j]))
            yield j, i, s, runners[j].run(i, s)
        return
    stream = pool.imap(
        _run_episode, tasks, workers=workers, initializer=_load_payloads, initargs=(payloads,)
    )
    for k, (j, row) in stream:
        yield j, tasks[k][1], tasks[k][2], row


def iter_episodes(
    controller: Any,
    estimator: Any,
    qos_policy: Any,
    env_config: Any,
    trials: int,
    seed: int,
    *,
    link: Any = None,
    workers: int | None = None,
    max_steps: int | None = None,
    store: RecordStore | None = None,
) -> Iterator[dict[str, Any]]:
    """Run the episodes of :func:`evaluate`, yielding each row as it completes (any order)."""
    job = (controller, estimator, qos_policy, env_config, trials, seed)
    for _, row in run_jobs([job], link=link, workers=workers, max_steps=max_steps, store=store):
        yield row


def evaluate(
    controller: Any,
    estimator: Any,
    qos_policy: Any,
    env_config: Any,
    trials: int,
    seed: int,
    *,
    link: Any = None,
    workers: int | None = None,
    max_steps: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    store: RecordStore | None = None,
) -> pd.DataFrame:
    """Run ``trials`` seeded episodes in parallel and return one row per episode.

    Parameters
    ----------
    controller, estimator, qos_policy:
        A :class:`~codesign_mb.control.base.Controller`, an
        :class:`~codesign_mb.estimation.base.Estimator` and a
        :class:`~codesign_mb.network.qos.QosPolicy` (``None``: perfect, ``StaticQos()``),
        each an instance or a picklable factory (see the module docstring).
    env_config:
        The plant's config (e.g. ``ConveyorConfig``) or a zero-argument env factory.
    trials:
        Number of episodes.
    seed:
        Root seed; episode ``i`` uses ``episode_seeds(seed, trials)[i]``.
    link:
        A :class:`~codesign_mb.network.link.Link` instance or factory
        (default: :class:`~codesign_mb.network.link.BernoulliLink`).
    workers:
        Worker processes (default: one per CPU, at most ``trials``); 1 runs in this process.
    max_steps:
        Cap on an episode's steps (default: the plant's own horizon).
    progress:
        Called as ``progress(done, trials)`` after each episode.
    store:
        Keeps every finished episode and gives back those of an earlier run
        (:class:`~codesign_mb.core.records.RecordStore`, :func:`run_jobs`).

    Returns
    -------
    pandas.DataFrame
        Sorted by ``episode``. Columns: ``episode``, ``seed``, ``success``, ``success_step``,
        ``steps``, ``return``, ``mean_requested_reliability`` (the paper's average PDR),
        ``mean_latency_steps``, ``mean_qos_cost``, ``delivered_fraction``, ``mean_age``,
        ``max_age``, ``mean_estimation_error``, ``max_estimation_error``, the plant's
        ``lifted`` and ``min_gripper_object_distance`` when it reports them, the
        conveyor's ``perceived_fraction`` (steps with a fresh detection at the edge),
        ``failure_reason`` (``None`` for a success, else one of
        :data:`~codesign_mb.plants.outcomes.FAILURE_REASONS`) and ``time_to_grasp_s``, the
        estimation error and NEES per phase of the object (``phase_steps_<phase>``,
        ``est_error_mm_<phase>``, ``nees_<phase>``, ``nees_state_<phase>``:
        :mod:`~codesign_mb.evaluation.phase_metrics`), the ``episode_metrics()`` of the
        controller, estimator and QoS policy (for the MPC:
        ``mpc_solves``, ``mpc_failures``, ``mpc_solve_ms_median``, ``mpc_solve_ms_p99``,
        ``mpc_solve_ms_max`` (wall clock), ``mpc_solve_cpu_ms_median``,
        ``mpc_solve_cpu_ms_p99`` (CPU); for the QoS planner, ``qos_asked_<reason>``),
        ``wall_time_s``.
    """
    rows = []
    for row in iter_episodes(
        controller,
        estimator,
        qos_policy,
        env_config,
        trials,
        seed,
        link=link,
        workers=workers,
        max_steps=max_steps,
        store=store,
    ):
        rows.append(row)
        if progress is not None:
            progress(len(rows), trials)
    return rows_to_table(rows)


# -- configured runs (the CLI and sweeps) --------------------------------------------------------
_CONTROLLERS = ("mpc", "scripted")
_ESTIMATORS = ("predictor", "belt_imm", "none")
QOS_POLICIES = ("static",)
"""QoS policies of ``codesign evaluate``: the static ``(q, tau)`` of the config."""


@dataclass(frozen=True)
class EvaluateConfig:
    """One evaluation, as the CLI and config files give it (table ``[evaluate]``).

    Parameters
    ----------
    controller:
        A controller kind of the registry that needs no checkpoint (``"mpc"``, ``"scripted"``).
    estimator:
        An estimator kind that needs no checkpoint (``"predictor"``, ``"belt_imm"``, ``"none"``).
    qos:
        ``"static"``.
    reliability, latency_steps:
        The QoS ``(q, tau)`` of the static policy.
    belt_speed_mps:
        Belt speed (overrides ``env.belt_speed_mps``, and clears a scenario's per-episode
        ``belt_speed_range_mps`` unless ``env`` sets one, so the speed given is the episodes'
        base speed); ``None`` keeps the scenario's.
    trials, seed, workers, max_steps:
        As in :func:`evaluate`.
    scenario:
        The conveyor scenario (:data:`codesign_mb.plants.scenarios.SCENARIOS`) whose options
        the plant starts from; default ``"paper"``.
    env:
        Overrides of the scenario's plant config (``ConveyorConfig`` fields), checked strictly.
    mpc:
        Overrides of :class:`~codesign_mb.control.mpc.MpcConfig` (controller ``"mpc"``).
    predictor:
        Keyword arguments of :class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor`.
    """

    controller: str = "mpc"
    estimator: str = "predictor"
    qos: str = "static"
    reliability: float = 1.0
    latency_steps: int = 0
    belt_speed_mps: float | None = None
    trials: int = 100
    seed: int = 0
    workers: int | None = None
    max_steps: int | None = None
    scenario: str = DEFAULT_SCENARIO
    env: dict[str, Any] = field(default_factory=dict)
    mpc: dict[str, Any] = field(default_factory=dict)
    predictor: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, choices in (
            ("controller", _CONTROLLERS),
            ("estimator", _ESTIMATORS),
            ("qos", QOS_POLICIES),
        ):
            value = getattr(self, name)
            if value not in choices:
                raise ValueError(f"{name} must be one of {', '.join(choices)}, got {value!r}")
        QosRequest(self.reliability, self.latency_steps)  # validates both, naming the field
        if self.belt_speed_mps is not None and not (
            math.isfinite(self.belt_speed_mps) and self.belt_speed_mps >= 0
        ):
            raise ValueError(f"belt_speed_mps must be >= 0, got {self.belt_speed_mps}")
        episode_seeds(self.seed, self.trials)  # validates trials and seed
        if self.workers is not None and (int(self.workers) != self.workers or self.workers < 1):
            raise ValueError(f"workers must be an integer >= 1, got {self.workers!r}")
        if self.max_steps is not None and (
            int(self.max_steps) != self.max_steps or self.max_steps < 1
        ):
            raise ValueError(f"max_steps must be an integer >= 1, got {self.max_steps!r}")
        get_scenario(self.scenario)  # an unknown name names the choices
        for name in ("env", "mpc", "predictor"):
            if not isinstance(getattr(self, name), Mapping):
                raise ValueError(f"{name} must be a table of options, got {getattr(self, name)!r}")
        check_range("workers", self.workers, cap=WORKERS_CAP)
        check_range("max_steps", self.max_steps, cap=STEPS_CAP)
        self.env_config(), self.components()  # the option tables, checked when loaded

    def env_config(self) -> Any:
        """The plant config: the scenario's options, then :attr:`env`, :attr:`belt_speed_mps`."""
        data = {**get_scenario(self.scenario).options, **self.env}
        if self.belt_speed_mps is not None:
            data["belt_speed_mps"] = float(self.belt_speed_mps)
            if "belt_speed_range_mps" not in self.env:  # else the range, not the speed, counts
                data["belt_speed_range_mps"] = ()
        return from_mapping(ConveyorConfig, data, where="env")

    def components(self) -> tuple[Factory, Factory, Any]:
        """``(controller, estimator, qos_policy)`` for :func:`evaluate`."""
        kwargs: dict[str, Any] = {}
        if self.controller == "mpc":
            kwargs["config"] = from_mapping(MpcConfig, self.mpc, where="mpc")
        elif self.mpc:
            raise ValueError(f"mpc options given but the controller is {self.controller!r}")
        if self.predictor and self.estimator != "predictor":
            raise ValueError(f"predictor options given but the estimator is {self.estimator!r}")
        controller = registry.factory("controller", ComponentSpec(self.controller, options=kwargs))
        options = dict(self.predictor) if self.estimator == "predictor" else {}
        estimator = registry.factory("estimator", ComponentSpec(self.estimator, options=options))
        return controller, estimator, StaticQos(self.reliability, self.latency_steps)


def run_config(
    config: EvaluateConfig,
    *,
    progress: Callable[[int, int], None] | None = None,
    store: RecordStore | None = None,
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Run :func:`evaluate` as ``config`` says (keeping episodes in ``store``); return the
    table and its :func:`summarize`."""
    controller, estimator, qos = config.components()
    table = evaluate(
        controller,
        estimator,
        qos,
        config.env_config(),
        config.trials,
        config.seed,
        workers=config.workers,
        max_steps=config.max_steps,
        progress=progress,
        store=store,
    )
    return table, summarize(table)
