"""Fig. 6 (``fig_wifi``): task success versus number of robots sharing one WiFi 6 channel.

For each robot count ``N`` and each curve (a cell, a scheduler and a pipeline), ``trials``
episodes run N robots in lockstep on one :class:`~codesign_mb.wifi.cell.SharedChannel`; a
trial's success rate is the fraction of its robots whose task succeeded (``info["success"]``
at any step). The *capacity* of a curve is the largest ``N`` up to which every simulated count
has a mean success of at least ``success_target`` (95 %).

Per point, :func:`capacity_table` gives the success pooled over the point's robot-episodes
(``trials x N``) with its Wilson interval, the requested reliability and the delivered
fraction (frames whose state arrived in time, per step). The robots of one trial share the
channel, so their outcomes are not independent: the interval, which counts each
robot-episode as one independent draw, is optimistic about that.

Cost: a trial at ``N`` robots costs ``N`` robot-episodes (:meth:`CapacityConfig.robot_episodes`
is the sweep's at most). The robot counts run in ascending order, every curve's trials of one
count together (in parallel with ``workers``); with ``stop_below``, a curve whose mean success
at a count is below it runs none of its larger counts (:func:`capacity_table` says where each
stopped). That never changes a capacity: ``stop_below`` is at most ``success_target``.

The sweep's settings (:class:`CapacityConfig`), the plants, pipelines and cells, and the
assumptions behind them, are in :mod:`codesign_mb.studies.fig_wifi_config`; the figure and
the files of ``codesign wifi capacity`` in :mod:`codesign_mb.studies.fig_wifi_figures`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.core.records import RecordStore, digest
from codesign_mb.core.registry import build, make_plant
from codesign_mb.core.stats import wilson_interval
from codesign_mb.evaluation import pool
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.rollout import rollout_shared
from codesign_mb.studies.fig_wifi_config import (
    CHANNEL_PRESETS,
    QOS_RULES,
    STACKS,
    AgeTriggeredQos,
    CapacityConfig,
    PipelineConfig,
    describe_channel,
)
from codesign_mb.wifi.cell import SharedChannel

__all__ = [
    "CAPACITY_MEASURES",
    "CHANNEL_PRESETS",
    "QOS_RULES",
    "STACKS",
    "AgeTriggeredQos",
    "CapacityConfig",
    "PipelineConfig",
    "capacity_ratios",
    "capacity_table",
    "describe_channel",
    "run_capacity",
    "run_point",
]


def _build(role: str, spec: Any, env: Any) -> Any:
    if role == "qos" and spec.kind in QOS_RULES:
        return QOS_RULES[spec.kind](env, **dict(spec.options))

    return build(role, spec, env)


def run_point(
    config: CapacityConfig,
    *,
    channel_name: str,
    scheduler: str,
    pipeline_name: str,
    n_robots: int,
    trial: int,
) -> dict[str, Any]:
    """One trial of one point: N robots, one episode each or back to back (continuous
    operation, ``config.episodes_per_robot``); returns success and network figures.

    ``successes`` is the number of counted robot-episodes whose task succeeded
    (``robot_episodes`` of them), ``success_rate`` their fraction; ``mean_reliability`` and
    ``delivered_fraction`` (the steps whose state arrived in time) are over every robot's
    steps of the trial, warm-up included. With an MPC, ``mpc_failures`` is its failed solves
    summed over the robots.
    """

    pipeline = config.pipelines[pipeline_name]
    channel = SharedChannel(CHANNEL_PRESETS[channel_name], n_robots, scheduler=scheduler)
    envs, estimators, controllers = [], [], []
    for i in range(n_robots):
        plant = make_plant(config.plant)
        qos = _build("qos", pipeline.qos, plant)
        envs.append(LinkObservationWrapper(plant, channel.links[i], qos))
        estimators.append(_build("estimator", pipeline.estimator, plant))
        controllers.append(_build("controller", pipeline.controller, plant))
    seed = int(np.random.SeedSequence([config.seed, trial]).generate_state(1)[0])
    tables = rollout_shared(
        envs,
        estimators,
        controllers,
        channel=channel,
        seed=seed,
        max_steps=config.max_steps,
        episodes=config.episodes_per_robot,
        warmup_episodes=config.warmup_episodes,
    )
    for env in envs:
        env.close()
    successes = [ok for t in tables for ok in _episode_successes(t)]
    summary = channel.summary()
    ages = [float(t["age"].mean()) for t in tables if len(t)]
    row = {
        "channel": channel_name,
        "scheduler": scheduler,
        "pipeline": pipeline_name,
        "robots": n_robots,
        "trial": trial,
        "successes": int(sum(successes)),
        "robot_episodes": len(successes),
        "success_rate": float(np.mean(successes)),
        "mean_reliability": float(np.nanmean(summary["mean_reliability"])),
        "delivered_fraction": float(summary["delivered"].sum() / max(summary["steps"].sum(), 1)),
        "late_frames": int(summary["late"].sum()),
        "mean_age": float(np.mean(ages)) if ages else float("nan"),
        "mean_latency_ms": float(np.nanmean(summary["mean_latency_ms"]))
        if summary["delivered"].sum()
        else float("nan"),
        # ticks whose convex QP failed and were rounded from zero service (never silent)
        "allocator_fallbacks": int(channel.fallbacks.total),
    }
    failures = [
        m["mpc_failures"] for m in map(_episode_metrics, controllers) if "mpc_failures" in m
    ]
    if failures:  # an MPC: its failed solves, summed over the robots
        row["mpc_failures"] = int(sum(failures))
    return row


def _episode_successes(table: pd.DataFrame) -> list[bool]:
    """Whether each episode of a robot's table succeeded (``info["success"]`` at any step)."""
    if "episode" not in table:
        return [bool(table["success"].any()) if "success" in table else False]
    if "success" not in table:
        return [False] * int(table["episode"].nunique())
    return [bool(v) for v in table.groupby("episode", sort=True)["success"].any()]


def _episode_metrics(component: Any) -> dict[str, Any]:
    metrics = getattr(component, "episode_metrics", None)
    return dict(metrics()) if callable(metrics) else {}


def _run_point_kwargs(args: tuple[CapacityConfig, dict[str, Any]]) -> dict[str, Any]:
    config, kwargs = args
    return run_point(config, **kwargs)


def _curve(point: Mapping[str, Any]) -> tuple[str, str, str]:
    return point["channel_name"], point["scheduler"], point["pipeline_name"]


def run_capacity(
    config: CapacityConfig,
    *,
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None,
    store: RecordStore | None = None,
) -> pd.DataFrame:
    """Every trial of every point run, one row each (tidy), in grid order.

    The robot counts run in ascending order, in rounds: round ``r`` is every running curve's
    ``r``-th count of its channel, all its trials (in parallel with ``config.workers``). After
    a round, a curve whose mean success at that count is below ``config.stop_below`` stops:
    its larger counts are not run and have no rows. ``progress`` wraps the stream of finished
    trials (at most ``len(config.points())``).

    ``store`` keeps every finished trial and gives back those of an earlier run
    (:mod:`codesign_mb.core.records`), keyed by the plant, root seed and step cap, and by the
    point: its channel's cell, scheduler, pipeline stack, robot count and trial. A resumed
    run takes the same stops, so it gives the same table.
    """
    points = config.points()
    rows: list[dict[str, Any] | None] = [None] * len(points)
    group, items = "", [""] * len(points)
    if store is not None:
        group = digest(
            {
                "trials of": config.plant,
                "seed": config.seed,
                "max_steps": config.max_steps,
                **_continuous_key(config),
            }
        )
        items = [_point_key(config, point) for point in points]
        kept = store.take(group, items)
        rows = [kept.get(item) for item in items]
    rank = [config.robots_of(p["channel_name"]).index(p["n_robots"]) for p in points]
    stopped: set[tuple[str, str, str]] = set()
    ran: list[int] = []  # the points of the rounds run, stored or computed

    def finished() -> Iterator[dict[str, Any]]:
        for r in range(max(rank, default=-1) + 1):
            members = [k for k in range(len(points)) if rank[k] == r]
            members = [k for k in members if _curve(points[k]) not in stopped]
            ran.extend(members)
            for k in members:
                stored = rows[k]
                if stored is not None:
                    yield stored
            todo = [k for k in members if rows[k] is None]
            for k, row in _compute(config, points, todo):
                done = row if store is None else store.add(group, items[k], row)
                rows[k] = done
                yield done
            rates: dict[tuple[str, str, str], list[float]] = {}
            for k in members:
                rates.setdefault(_curve(points[k]), []).append(_row(rows, k)["success_rate"])
            below = config.stop_below - 1e-12  # as capacity_table reads it
            stopped.update(c for c, v in rates.items() if float(np.mean(v)) < below)

    for _ in progress(finished()) if progress is not None else finished():
        pass
    return pd.DataFrame([_row(rows, k) for k in sorted(ran)])


def _continuous_key(config: CapacityConfig) -> dict[str, int]:
    """Continuous operation's settings, in the record key only when on (older keys hold)."""
    if config.episodes_per_robot == 1 and config.warmup_episodes == 0:
        return {}
    return {"episodes": config.episodes_per_robot, "warmup": config.warmup_episodes}


def _row(rows: list[dict[str, Any] | None], k: int) -> dict[str, Any]:
    row = rows[k]
    if row is None:
        raise RuntimeError(f"point {k} of the capacity sweep has no row")  # unreachable
    return row


def _point_key(config: CapacityConfig, point: Mapping[str, Any]) -> str:
    """The key of one trial of one point: the point and what its names stand for."""
    cell = CHANNEL_PRESETS[point["channel_name"]]
    return digest(
        {"point": point, "cell": cell, "pipeline": config.pipelines[point["pipeline_name"]]}
    )


def _compute(
    config: CapacityConfig, points: list[dict[str, Any]], todo: list[int]
) -> Iterator[tuple[int, dict[str, Any]]]:
    """``(point index, row)`` of the points ``todo``, as each finishes."""
    if not todo:
        return
    if config.workers == 1:
        for k in todo:
            yield k, run_point(config, **points[k])
        return
    # Largest points first keeps both workers busy to the end.
    order = sorted(todo, key=lambda k: -points[k]["n_robots"])
    stream = pool.imap(
        _run_point_kwargs, [((config, points[k]),) for k in order], workers=config.workers
    )
    for i, row in stream:
        yield order[i], row


_CURVE = ["channel", "scheduler", "pipeline"]


def capacity_table(
    results: pd.DataFrame,
    *,
    success_target: float = 0.95,
    stop_below: float = 0.0,
    confidence: float = 0.95,
) -> pd.DataFrame:
    """Per curve and robot count: success with its Wilson interval, QoS, and the capacity.

    ``success_rate`` is the mean of the trials' (all trials of a point have N robots: the
    success pooled over its ``robot_episodes``), ``success_ci_low`` and ``success_ci_high``
    its Wilson interval at ``confidence`` over the robot-episodes (optimistic: the robots of
    a trial share the channel, so they are not independent draws); the successes are the
    trials' ``successes``, or ``round(success_rate * robots)`` without that column.
    ``mean_reliability`` (requested) and ``delivered_fraction`` are the trials' means (NaN
    when ``results`` has no such column); ``mpc_failures`` (the trials' sum) is there when
    ``results`` has it, and so is ``allocator_fallbacks``.

    Per curve: ``capacity_robots`` is the largest robot count up to which every simulated
    count reaches ``success_target`` (0 if the smallest does not); ``capacity_censored``
    says it is the curve's largest count run (the capacity is at least that);
    ``stopped_at_robots`` is the count whose success fell below ``stop_below`` (the sweep's
    early stop: no larger count was run), NaN when none did or ``stop_below`` is 0.
    ``capacity_interval_robots`` (and ``capacity_interval_censored``) is the same with "not
    significantly below ``success_target``" (the Wilson upper bound reaches it) in place of
    "the mean reaches it": a stack that alone succeeds close to the target (the realistic
    planner row: 96 %) then gets a capacity set by the network rather than by chance.
    """
    keys = [*_CURVE, "robots"]
    results = results.assign(
        **{c: math.nan for c in ("mean_reliability", "delivered_fraction") if c not in results}
    )
    if "successes" not in results:
        results = results.assign(successes=(results["success_rate"] * results["robots"]).round())
    if "robot_episodes" not in results:  # one episode per robot (rows of older runs)
        results = results.assign(robot_episodes=results["robots"])
    sums = {c: (c, _sum_or_nan) for c in ("mpc_failures", "allocator_fallbacks") if c in results}
    curves = (
        results.groupby(keys, as_index=False)
        .agg(
            success_rate=("success_rate", "mean"),
            successes=("successes", "sum"),
            robot_episodes=("robot_episodes", "sum"),
            mean_reliability=("mean_reliability", "mean"),
            delivered_fraction=("delivered_fraction", "mean"),
            trials=("success_rate", "size"),
            **sums,
        )
        .sort_values(keys)
    )
    intervals = [
        wilson_interval(int(k), int(n), confidence)
        for k, n in zip(curves["successes"], curves["robot_episodes"], strict=True)
    ]
    curves["success_ci_low"] = [low for low, _ in intervals]
    curves["success_ci_high"] = [high for _, high in intervals]
    caps = []
    for key, group in curves.groupby(_CURVE):
        stopped = math.nan
        for n, rate in zip(group["robots"], group["success_rate"], strict=True):
            if rate < stop_below - 1e-12:
                stopped = int(n)
                break
        largest = int(group["robots"].max())
        capacity = _held(group["robots"], group["success_rate"], success_target)
        interval = _held(group["robots"], group["success_ci_high"], success_target)
        caps.append((*key, capacity, capacity == largest, stopped, interval, interval == largest))
    columns = [
        *_CURVE,
        "capacity_robots",
        "capacity_censored",
        "stopped_at_robots",
        "capacity_interval_robots",
        "capacity_interval_censored",
    ]
    return curves.merge(pd.DataFrame(caps, columns=columns), on=_CURVE)


def _held(robots: pd.Series, values: pd.Series, target: float) -> int:
    """The largest robot count up to which every count's value reaches ``target`` (else 0)."""
    capacity = 0
    for n, value in zip(robots, values, strict=True):
        if value < target - 1e-12:
            break
        capacity = int(n)
    return capacity


CAPACITY_MEASURES: dict[str, tuple[str, str]] = {
    "mean": ("capacity_robots", "capacity_censored"),
    "interval": ("capacity_interval_robots", "capacity_interval_censored"),
}
"""How a capacity is read (:func:`capacity_table`'s columns: the capacity, whether it is
censored): the mean success reaches the target, or it is not significantly below it (Wilson
upper bound)."""


def capacity_ratios(
    curves: pd.DataFrame,
    *,
    codesign: str = "codesign",
    static: str = "static",
    measures: tuple[str, ...] = ("mean", "interval"),
) -> pd.DataFrame:
    """Per cell, scheduler and capacity measure (:data:`CAPACITY_MEASURES`; column
    ``measure``): the co-design pipeline's capacity over the static one's.

    ``curves`` is :func:`capacity_table`'s. ``bound`` says what the ratio is: ``"exact"``,
    ``"at least"`` (the co-design curve held the target up to its largest count, so its
    capacity may be larger), ``"at most"`` (the static one did), ``"unknown"`` (both did).
    A static capacity of 0 gives an infinite ratio (NaN if both are 0). Empty when
    ``curves`` lacks either pipeline.
    """
    per_curve = curves.drop_duplicates(_CURVE).set_index(_CURVE)
    rows = []
    cells = zip(curves["channel"], curves["scheduler"], strict=True)
    for (channel, scheduler), measure in itertools.product(dict.fromkeys(cells), measures):
        column, censored = CAPACITY_MEASURES[measure]
        if column not in per_curve:
            continue
        try:
            c = per_curve.loc[(channel, scheduler, codesign)]
            s = per_curve.loc[(channel, scheduler, static)]
        except KeyError:
            continue
        c_cap, s_cap = int(c[column]), int(s[column])
        c_open = bool(c.get(censored, False))
        s_open = bool(s.get(censored, False))
        ratio = c_cap / s_cap if s_cap else (math.inf if c_cap else math.nan)
        bound = {
            (False, False): "exact",
            (True, False): "at least",
            (False, True): "at most",
            (True, True): "unknown",
        }[(c_open, s_open)]
        rows.append(
            {
                "channel": channel,
                "scheduler": scheduler,
                "measure": measure,
                "static_capacity": s_cap,
                "codesign_capacity": c_cap,
                "ratio": ratio,
                "bound": bound,
            }
        )
    columns = [
        "channel",
        "scheduler",
        "measure",
        "static_capacity",
        "codesign_capacity",
        "ratio",
        "bound",
    ]
    return pd.DataFrame(rows, columns=columns)


def _sum_or_nan(values: pd.Series) -> float:
    return float(values.sum(min_count=1))
