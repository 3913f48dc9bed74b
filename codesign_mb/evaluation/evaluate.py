"""Seeded, parallel evaluation of a (controller, estimator, QoS policy) triple on a plant.

The way the paper evaluates its policies (Table ``tab_p``, Fig. ``fig_cn``): many independent
seeded episodes, success rate with a confidence interval, the mean requested reliability
(the paper's "average PDR"), the delivered fraction and the age of what the robot acted on.

Reproducibility: episode ``i`` gets the seed ``SeedSequence(seed).spawn(trials)[i]``, every
component is reset from it at the episode's start (the controller also drops its solver's
warm start), and episodes run in fresh copies of the components. The table is therefore the
same whatever the number of worker processes, except the wall-time columns
(:data:`TIMING_COLUMNS`).

Workers are started with the ``spawn`` method (safe with MuJoCo, CasADi and torch loaded):
a script calling :func:`evaluate` with ``workers > 1`` needs the usual
``if __name__ == "__main__":`` guard.

Components are given either as instances (pickled into each worker and reset per episode)
or as picklable factories, called once per worker as ``factory(env)`` (``env`` is the plant,
unwrapped) or ``factory()`` when they take no argument. :class:`Factory` names a factory by
import path, and :func:`component` builds the named ones the CLI offers (``"mpc"``,
``"predictor"``, ``"plain"``, ...).
"""

from __future__ import annotations

import importlib
import inspect
import math
import os
import pickle
import statistics
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from multiprocessing import get_context
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.evaluation.rollout import rollout
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper

__all__ = [
    "CONTROLLERS",
    "ESTIMATORS",
    "QOS_POLICIES",
    "TIMING_COLUMNS",
    "EvaluateConfig",
    "Factory",
    "component",
    "episode_seeds",
    "evaluate",
    "iter_episodes",
    "make_env",
    "rows_to_table",
    "run_config",
    "run_jobs",
    "single_threaded_worker",
    "summarize",
    "wilson_interval",
]

TIMING_COLUMNS = (
    "wall_time_s",
    "mpc_solve_ms_median",
    "mpc_solve_ms_p99",
    "mpc_solve_ms_max",
    "mpc_solve_cpu_ms_median",
    "mpc_solve_cpu_ms_p99",
)
"""Per-episode columns measuring wall time: they vary from run to run, the rest does not."""

_ENVS: dict[str, str] = {
    "ConveyorConfig": "codesign_mb.plants.conveyor:ConveyorPickPlace",
}
"""Config class name -> env class (built as ``Env(config=config)``)."""


# -- factories ---------------------------------------------------------------------------------
def _resolve(target: str) -> Any:
    module_name, _, attr = target.partition(":")
    if not module_name or not attr:
        raise ValueError(f"factory target must be 'module:attribute', got {target!r}")
    obj: Any = importlib.import_module(module_name)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


@dataclass(frozen=True)
class Factory:
    """A picklable factory named by import path: ``target(env, **kwargs)`` or ``target(**kwargs)``.

    Parameters
    ----------
    target:
        ``"package.module:attribute"`` (dotted attributes allowed, e.g. a classmethod).
    kwargs:
        Keyword arguments of the call.
    takes_env:
        Whether ``target`` takes the plant env as its first argument.

    Examples
    --------
    >>> f = Factory("codesign_mb.adaptation.base:StaticQos", {"reliability": 0.5}, takes_env=False)
    >>> f()
    StaticQos(reliability=0.5, latency_steps=0)
    """

    target: str
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    takes_env: bool = True

    def __call__(self, env: Any = None) -> Any:
        fn = _resolve(self.target)
        if self.takes_env:
            return fn(env, **dict(self.kwargs))
        return fn(**dict(self.kwargs))


CONTROLLERS: dict[str, tuple[str, bool]] = {
    "mpc": ("codesign_mb.control.mpc:MpcController.from_env", True),
    "scripted": ("codesign_mb.control.scripted:ScriptedPickController.from_env", True),
}
"""Controller name -> (factory target, takes_env)."""

ESTIMATORS: dict[str, tuple[str, bool]] = {
    "predictor": ("codesign_mb.estimation.predictor:DelayCompensatingPredictor.from_env", True),
    "plain": ("codesign_mb.estimation.base:PassThroughEstimator", False),
}
"""Estimator name -> (factory target, takes_env). ``plain`` uses the stale observation as is."""


def component(kind: str, name: str, **kwargs: Any) -> Factory:
    """The named controller (``kind="controller"``) or estimator (``kind="estimator"``).

    Raises ``ValueError`` naming the choices for an unknown name.
    """
    registry = {"controller": CONTROLLERS, "estimator": ESTIMATORS}.get(kind)
    if registry is None:
        raise ValueError(f"kind must be 'controller' or 'estimator', got {kind!r}")
    if name not in registry:
        raise ValueError(f"unknown {kind} {name!r}; expected one of {', '.join(registry)}")
    target, takes_env = registry[name]
    return Factory(target, kwargs, takes_env=takes_env)


def make_env(env_config: Any) -> Any:
    """The plant env of ``env_config``: a known config dataclass, or a zero-argument factory."""
    name = type(env_config).__name__
    if name in _ENVS:
        return _resolve(_ENVS[name])(config=env_config)
    if callable(env_config):
        return env_config()
    raise ValueError(f"no env known for a {name}; pass one of {', '.join(_ENVS)} or an env factory")


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


# -- seeds and statistics ----------------------------------------------------------------------
def episode_seeds(seed: int, trials: int) -> list[int]:
    """Independent episode seeds: ``SeedSequence(seed).spawn(trials)``, one integer each."""
    if isinstance(trials, bool) or int(trials) != trials or trials < 1:
        raise ValueError(f"trials must be an integer >= 1, got {trials!r}")
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    children = np.random.SeedSequence(int(seed)).spawn(int(trials))
    return [int(c.generate_state(1, dtype=np.uint32)[0]) for c in children]


def wilson_interval(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion ``k / n``.

    ``(p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)`` with ``z`` the two-sided
    normal quantile of ``confidence``. Unlike the normal approximation it stays inside [0, 1]
    and is informative at ``k = n`` (e.g. 100/100 gives [0.963, 1]).

    Examples
    --------
    >>> [round(x, 4) for x in wilson_interval(8, 10)]
    [0.4902, 0.9433]
    """
    if int(n) != n or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    if int(k) != k or not 0 <= k <= n:
        raise ValueError(f"k must be an integer in [0, n={n}], got {k!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    z = statistics.NormalDist().inv_cdf(0.5 + confidence / 2.0)
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    low = 0.0 if k == 0 else max(0.0, centre - half)
    high = 1.0 if k == n else min(1.0, centre + half)
    return low, high


def summarize(table: pd.DataFrame, confidence: float = 0.95) -> dict[str, Any]:
    """Aggregate an :func:`evaluate` table: success rate with its Wilson interval, QoS, age, MPC.

    Solve-time figures are over episodes: the median of the episodes' medians, the median of
    their 99th percentiles and the overall maximum.
    """
    if len(table) == 0:
        raise ValueError("cannot summarise an empty table")
    n = len(table)
    k = int(table["success"].sum())
    low, high = wilson_interval(k, n, confidence)
    out: dict[str, Any] = {
        "trials": n,
        "successes": k,
        "success_rate": k / n,
        "success_ci_low": low,
        "success_ci_high": high,
        "confidence": confidence,
    }
    for column in (
        "mean_requested_reliability",
        "delivered_fraction",
        "mean_age",
        "mean_qos_cost",
        "mean_estimation_error",
        "steps",
    ):
        if column in table:
            out[column] = float(table[column].mean())
    if "max_age" in table:
        out["max_age"] = int(table["max_age"].max())
    if "mpc_solve_ms_median" in table:
        out["mpc_solve_ms_median"] = float(table["mpc_solve_ms_median"].median())
        out["mpc_solve_ms_p99"] = float(table["mpc_solve_ms_p99"].median())
        out["mpc_solve_ms_max"] = float(table["mpc_solve_ms_max"].max())
        if "mpc_solve_cpu_ms_median" in table:
            out["mpc_solve_cpu_ms_median"] = float(table["mpc_solve_cpu_ms_median"].median())
            out["mpc_solve_cpu_ms_p99"] = float(table["mpc_solve_cpu_ms_p99"].median())
        out["mpc_failures"] = int(table["mpc_failures"].sum())
    return out


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
        start = time.perf_counter()
        steps = rollout(
            self.env, self.estimator, self.controller, seed=seed, max_steps=self.max_steps
        )
        row: dict[str, Any] = {"episode": episode, "seed": seed}
        row.update(episode_row(steps))
        for obj in (self.controller, self.estimator, self.env.qos_policy):
            metrics = getattr(obj, "episode_metrics", None)
            if callable(metrics):
                row.update(metrics())
        row["wall_time_s"] = time.perf_counter() - start
        return row


def episode_row(steps: pd.DataFrame) -> dict[str, Any]:
    """One episode's metrics from its :func:`~codesign_mb.evaluation.rollout.rollout` record."""
    success = steps["success"].astype(bool) if "success" in steps else pd.Series(False)
    row: dict[str, Any] = {
        "success": bool(success.any()),
        "success_step": int(np.argmax(success.to_numpy())) if success.any() else -1,
        "steps": len(steps),
        "return": float(steps["reward"].sum()) if "reward" in steps else math.nan,
        "mean_requested_reliability": float(steps["qos_reliability"].mean()),
        "mean_latency_steps": float(steps["qos_latency_steps"].mean()),
        "mean_qos_cost": float(steps["qos_cost"].mean()),
        "delivered_fraction": float(steps["delivered"].astype(float).mean()),
        "mean_age": float(steps["age"].mean()),
        "max_age": int(steps["age"].max()),
        "mean_estimation_error": float(steps["estimation_error"].mean()),
        "max_estimation_error": float(steps["estimation_error"].max()),
    }
    if "lifted" in steps:
        row["lifted"] = bool(steps["lifted"].astype(bool).any())
    if "gripper_object_distance" in steps:
        row["min_gripper_object_distance"] = float(steps["gripper_object_distance"].min())
    return row


_RUNNERS: dict[int, _Runner] = {}
_PAYLOADS: list[bytes] = []
_CACHE = 2  # runners kept per process (each holds an env and a built controller)
_MAX_POOL_RESTARTS = 2


def _runner_for(job: int) -> _Runner:
    runner = _RUNNERS.get(job)
    if runner is None:
        while len(_RUNNERS) >= _CACHE:
            _RUNNERS.pop(next(iter(_RUNNERS)))
        runner = _Runner(pickle.loads(_PAYLOADS[job]))
        _RUNNERS[job] = runner
    return runner


def single_threaded_worker() -> None:
    """Process-pool initializer: one OpenMP/BLAS thread in this worker process.

    Workers already use every core; torch's default of one intra-op thread per core makes
    the small networks of the learned components about 20x slower when the workers share
    the cores (SAC's actor: 6.6 ms a call instead of 0.3 ms on 2 cores). An explicit
    ``OMP_NUM_THREADS`` in the environment is kept.
    """
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(variable, "1")
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


def _init_worker(payloads: list[bytes]) -> None:
    single_threaded_worker()
    _RUNNERS.clear()
    _PAYLOADS[:] = payloads


def _run_in_worker(job: int, episode: int, seed: int) -> tuple[int, dict[str, Any]]:
    return job, _runner_for(job).run(episode, seed)


def _check_workers(workers: int | None, tasks: int) -> int:
    if workers is None:
        workers = os.cpu_count() or 1
    if isinstance(workers, bool) or int(workers) != workers or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    return max(1, min(int(workers), tasks))


def run_jobs(
    jobs: Sequence[tuple[Any, Any, Any, Any, int, int]],
    *,
    link: Any = None,
    workers: int | None = None,
    max_steps: int | None = None,
) -> Iterator[tuple[int, dict[str, Any]]]:
    """Run several evaluations in one process pool, yielding ``(job index, row)`` as done.

    Each job is ``(controller, estimator, qos_policy, env_config, trials, seed)`` as in
    :func:`evaluate`; all episodes of all jobs share the pool (e.g. the points of a figure).
    """
    payloads: list[bytes] = []
    tasks: list[tuple[int, int, int]] = []
    for j, (controller, estimator, qos_policy, env_config, trials, seed) in enumerate(jobs):
        if qos_policy is None:
            qos_policy = StaticQos()
        job = _Job(controller, estimator, qos_policy, env_config, link, max_steps)
        payloads.append(pickle.dumps(job))  # fails early, here, on an unpicklable component
        tasks.extend((j, i, s) for i, s in enumerate(episode_seeds(seed, trials)))
    workers = _check_workers(workers, len(tasks))
    if workers == 1:
        runner: _Runner | None = None
        current = -1
        for j, i, s in tasks:
            if j != current:  # fresh copies of the components, as a worker would have
                runner, current = _Runner(pickle.loads(payloads[j])), j
            assert runner is not None
            yield j, runner.run(i, s)
        return
    pending = list(tasks)
    restarts = 0
    while pending:
        with ProcessPoolExecutor(
            max_workers=workers,
            mp_context=get_context("spawn"),
            initializer=_init_worker,
            initargs=(payloads,),
        ) as pool:
            futures = {pool.submit(_run_in_worker, *task): task for task in pending}
            try:
                for future in as_completed(futures):
                    result = future.result()
                    pending.remove(futures[future])
                    yield result
            except BrokenProcessPool:
                # A worker died (killed from outside, out of memory): episodes are pure
                # functions of their seed, so the missing ones are rerun in a fresh pool.
                restarts += 1
                if restarts > _MAX_POOL_RESTARTS:
                    raise
                warnings.warn(
                    f"a worker process died; rerunning {len(pending)} episodes in a new pool",
                    RuntimeWarning,
                    stacklevel=2,
                )
            finally:
                for future in futures:
                    future.cancel()


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
) -> Iterator[dict[str, Any]]:
    """Run the episodes of :func:`evaluate`, yielding each row as it completes (any order)."""
    job = (controller, estimator, qos_policy, env_config, trials, seed)
    for _, row in run_jobs([job], link=link, workers=workers, max_steps=max_steps):
        yield row


def rows_to_table(rows: Sequence[Mapping[str, Any]]) -> pd.DataFrame:
    """The per-episode table from rows in any order: sorted by ``episode``."""
    return pd.DataFrame(list(rows)).sort_values("episode", kind="stable").reset_index(drop=True)


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
) -> pd.DataFrame:
    """Run ``trials`` seeded episodes in parallel and return one row per episode.

    Parameters
    ----------
    controller, estimator, qos_policy:
        A :class:`~codesign_mb.control.base.Controller`, an
        :class:`~codesign_mb.estimation.base.Estimator` and a
        :class:`~codesign_mb.adaptation.base.QosPolicy` (``None``: perfect, ``StaticQos()``),
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

    Returns
    -------
    pandas.DataFrame
        Sorted by ``episode``. Columns: ``episode``, ``seed``, ``success``, ``success_step``,
        ``steps``, ``return``, ``mean_requested_reliability`` (the paper's average PDR),
        ``mean_latency_steps``, ``mean_qos_cost``, ``delivered_fraction``, ``mean_age``,
        ``max_age``, ``mean_estimation_error``, ``max_estimation_error``, the plant's
        ``lifted`` and ``min_gripper_object_distance`` when it reports them, the
        ``episode_metrics()`` of the controller, estimator and QoS policy (for the MPC:
        ``mpc_solves``, ``mpc_failures``, ``mpc_solve_ms_median``, ``mpc_solve_ms_p99``,
        ``mpc_solve_ms_max`` (wall clock), ``mpc_solve_cpu_ms_median``,
        ``mpc_solve_cpu_ms_p99`` (CPU)), ``wall_time_s``.
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
    ):
        rows.append(row)
        if progress is not None:
            progress(len(rows), trials)
    return rows_to_table(rows)


# -- configured runs (the CLI and sweeps) --------------------------------------------------------
QOS_POLICIES: dict[str, str] = {
    "static": "codesign_mb.adaptation.base:StaticQos",
}
"""QoS policy name -> class taking ``(reliability, latency_steps)``."""


@dataclass(frozen=True)
class EvaluateConfig:
    """One evaluation, as the CLI and config files give it (table ``[evaluate]``).

    Parameters
    ----------
    controller:
        Name in :data:`CONTROLLERS` (``"mpc"``, ``"scripted"``).
    estimator:
        Name in :data:`ESTIMATORS` (``"predictor"``, ``"plain"``).
    qos:
        Name in :data:`QOS_POLICIES` (``"static"``).
    reliability, latency_steps:
        The QoS ``(q, tau)`` of the static policy.
    belt_speed_mps:
        Belt speed (overrides ``env.belt_speed_mps``); ``None`` keeps the env's default.
    trials, seed, workers, max_steps:
        As in :func:`evaluate`.
    env:
        Overrides of the plant config (``ConveyorConfig`` fields), checked strictly.
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
    env: dict[str, Any] = field(default_factory=dict)
    mpc: dict[str, Any] = field(default_factory=dict)
    predictor: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, registry in (
            ("controller", CONTROLLERS),
            ("estimator", ESTIMATORS),
            ("qos", QOS_POLICIES),
        ):
            value = getattr(self, name)
            if value not in registry:
                raise ValueError(f"{name} must be one of {', '.join(registry)}, got {value!r}")
        from codesign_mb.network.qos import QosRequest

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
        for name in ("env", "mpc", "predictor"):
            if not isinstance(getattr(self, name), Mapping):
                raise ValueError(f"{name} must be a table of options, got {getattr(self, name)!r}")

    def env_config(self) -> Any:
        """The plant config: ``ConveyorConfig`` from :attr:`env` and :attr:`belt_speed_mps`."""
        from codesign_mb.config import from_mapping
        from codesign_mb.plants.conveyor import ConveyorConfig

        data = dict(self.env)
        if self.belt_speed_mps is not None:
            data["belt_speed_mps"] = float(self.belt_speed_mps)
        return from_mapping(ConveyorConfig, data, where="env")

    def components(self) -> tuple[Factory, Factory, Any]:
        """``(controller, estimator, qos_policy)`` for :func:`evaluate`."""
        from codesign_mb.config import from_mapping

        kwargs: dict[str, Any] = {}
        if self.controller == "mpc":
            from codesign_mb.control.mpc import MpcConfig

            kwargs["config"] = from_mapping(MpcConfig, self.mpc, where="mpc")
        elif self.mpc:
            raise ValueError(f"mpc options given but the controller is {self.controller!r}")
        if self.predictor and self.estimator != "predictor":
            raise ValueError(f"predictor options given but the estimator is {self.estimator!r}")
        controller = component("controller", self.controller, **kwargs)
        estimator = component(
            "estimator",
            self.estimator,
            **(dict(self.predictor) if self.estimator == "predictor" else {}),
        )
        qos = _resolve(QOS_POLICIES[self.qos])(self.reliability, self.latency_steps)
        return controller, estimator, qos


def run_config(
    config: EvaluateConfig, *, progress: Callable[[int, int], None] | None = None
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Run :func:`evaluate` as ``config`` says; return the table and its :func:`summarize`."""
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
    )
    return table, summarize(table)
