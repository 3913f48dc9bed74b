"""Sweeps and training searches on Ray: the ``"ray"`` backend of
:func:`~codesign_mb.studies.sweep.run_sweep` and :func:`tune_hyperparameters`.

Ray is imported only inside these functions (an optional dependency:
``pip install 'codesign_mb[ray]'``). Both use the running Ray instance when there is one,
else connect to ``address`` or start a local instance, which they shut down when done.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import pandas as pd

from codesign_mb.core.results import to_jsonable

__all__ = ["RAY_TASK_RETRIES", "iter_ray", "tune_hyperparameters"]

RAY_TASK_RETRIES = 3
"""Reruns of a Ray task whose worker died (Ray's default, stated: the tests rely on it)."""


def iter_ray(
    task: Callable[[Any, int], dict[str, Any]],
    pending: Sequence[tuple[str, Any, int]],
    workers: int | None,
    address: str | None,
) -> Iterator[tuple[str, dict[str, Any]]]:
    """Run ``task(trial, seed)`` for every ``(key, trial, seed)`` as Ray tasks; yield
    ``(key, row)`` as they finish (the ``"ray"`` backend of ``run_sweep``).

    ``address`` is a cluster (``"auto"``, ``"ray://host:10001"``); ``None`` starts a local
    instance with ``workers`` CPUs. A task's error is raised here; the tasks left are
    cancelled. A task whose worker process dies (killed, out of memory, a lost node) is run
    again, up to ``RAY_TASK_RETRIES`` times (tasks are pure functions of their arguments:
    the same row).
    """
    try:
        import ray
    except ModuleNotFoundError:
        raise ValueError("the ray backend needs Ray: pip install 'codesign_mb[ray]'") from None
    owns = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        owns = True
    elif address:
        # Already connected (e.g. inside a Ray job or a test fixture): use that cluster.
        pass
    remote = ray.remote(num_cpus=1, max_retries=RAY_TASK_RETRIES)(task)
    refs = {remote.remote(trial, seed): key for key, trial, seed in pending}
    remaining = list(refs)
    try:
        while remaining:
            done, remaining = ray.wait(remaining, num_returns=1)
            for ref in done:
                yield refs[ref], ray.get(ref)
    finally:
        # Only the tasks not yet finished: cancelling a finished task can abort Ray's core
        # worker ("Tried to complete task that was not pending"), taking the driver with it.
        for ref in remaining:
            ray.cancel(ref, force=False)
        if owns:
            ray.shutdown()


def tune_hyperparameters(
    trainable: Callable[[dict[str, Any]], Mapping[str, Any]],
    param_space: Mapping[str, Any],
    *,
    metric: str,
    mode: Literal["min", "max"],
    num_samples: int = 1,
    seed: int = 0,
    address: str | None = None,
    max_concurrent_trials: int | None = None,
    storage_path: str | Path | None = None,
    name: str = "tune",
    cpus_per_trial: float = 1.0,
) -> pd.DataFrame:
    """A hyperparameter search with Ray Tune around a plain ``trainable(config) -> metrics``.

    Parameters
    ----------
    trainable:
        A picklable function of one config dict (e.g. a training stage of
        :mod:`codesign_mb.stages` with its hyperparameters and ``"seed"``) returning its final
        metrics. It is wrapped so it reports them to Tune once; it need not know about Ray.
    param_space:
        Tune search space (``tune.grid_search``, ``tune.choice``, ``tune.loguniform``, plain
        values). A ``"seed"`` entry is added (the trial's sample seed) unless present.
    metric, mode:
        The metric of ``trainable``'s result to optimise, ``"min"`` or ``"max"``.
    num_samples:
        Samples of the space (each grid point is repeated ``num_samples`` times).
    seed:
        Seeds the variant generator, so the sampled configs are reproducible.
    address:
        Ray cluster address; ``None`` uses the running Ray instance or starts a local one.
    max_concurrent_trials, cpus_per_trial:
        Parallelism limits.
    storage_path, name:
        Where Tune keeps its experiment folder (default: a temporary folder).

    Returns
    -------
    pandas.DataFrame
        One row per trial: ``config/<key>`` columns and the reported metrics, sorted by
        ``metric`` (best first).
    """
    import tempfile

    import ray
    from ray import tune
    from ray.tune.search.basic_variant import BasicVariantGenerator

    if mode not in ("min", "max"):
        raise ValueError(f"mode must be 'min' or 'max', got {mode!r}")
    if isinstance(num_samples, bool) or not isinstance(num_samples, int):
        raise ValueError(f"num_samples must be an integer, got {num_samples!r}")
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples!r}")
    owns = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(include_dashboard=False, log_to_driver=False)
        owns = True
    space = dict(param_space)
    space.setdefault("seed", tune.randint(0, 2**31 - 1))
    try:
        tuner = tune.Tuner(
            tune.with_resources(_TuneReporter(trainable), {"cpu": cpus_per_trial}),
            param_space=space,
            tune_config=tune.TuneConfig(
                metric=metric,
                mode=mode,
                num_samples=num_samples,
                max_concurrent_trials=max_concurrent_trials,
                search_alg=BasicVariantGenerator(random_state=seed),
            ),
            run_config=tune.RunConfig(
                name=name,
                storage_path=str(storage_path or tempfile.mkdtemp(prefix="codesign-tune-")),
                verbose=0,
            ),
        )
        grid = tuner.fit()
        frame = grid.get_dataframe()
    finally:
        if owns:
            ray.shutdown()
    keep = [c for c in frame.columns if c.startswith("config/")]
    keep += [c for c in frame.columns if c not in keep and not _is_tune_bookkeeping(c)]
    frame = frame[keep].sort_values(metric, ascending=(mode == "min"), kind="stable")
    return frame.reset_index(drop=True)


_TUNE_BOOKKEEPING = {
    "timestamp",
    "checkpoint_dir_name",
    "done",
    "training_iteration",
    "trial_id",
    "date",
    "time_this_iter_s",
    "time_total_s",
    "pid",
    "hostname",
    "node_ip",
    "time_since_restore",
    "iterations_since_restore",
    "logdir",
}


def _is_tune_bookkeeping(column: str) -> bool:
    return column in _TUNE_BOOKKEEPING


class _TuneReporter:
    """Picklable wrapper reporting ``trainable(config)``'s metrics to Tune (function API)."""

    def __init__(self, trainable: Callable[[dict[str, Any]], Mapping[str, Any]]) -> None:
        self.trainable = trainable
        self.__name__ = getattr(trainable, "__name__", "trainable")

    def __call__(self, config: dict[str, Any]) -> None:
        from ray import tune

        metrics = self.trainable(dict(config))
        if not isinstance(metrics, Mapping):
            raise TypeError(f"trainable must return a dict, got {type(metrics).__name__}")
        tune.report(dict(to_jsonable(dict(metrics))))
