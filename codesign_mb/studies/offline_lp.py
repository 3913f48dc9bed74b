"""Instances of the offline allocation LP: recorded (``codesign wifi trace``) and solved.

:func:`write_trace` records a static-QoS trace on a capacity-study cell as an instance file
(JSON, or Parquet for a path ending in ``.parquet``: :mod:`codesign_mb.wifi.trace_parquet`);
what ``codesign solve`` prints: the optimum of :func:`~codesign_mb.wifi.offline.offline_optimum`
(the most frames any scheduler delivers in time on the trace) and, optionally, what the greedy
and convex allocators deliver when replayed on the same trace.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from codesign_mb.core.config import LATENCY_STEPS_CAP, ROBOTS_CAP, SEED_CAP, check_range
from codesign_mb.evaluation.pool import check_workers, imap
from codesign_mb.network.qos import QosRequest
from codesign_mb.studies.fig_wifi import CHANNEL_PRESETS
from codesign_mb.wifi.cell import generate_trace
from codesign_mb.wifi.offline import offline_optimum
from codesign_mb.wifi.offline_windows import TraceSource, solve_windows
from codesign_mb.wifi.sim import TRACE_CELLS_CAP, Trace, replay
from codesign_mb.wifi.trace_parquet import ParquetTrace, save_parquet

__all__ = ["solve_instance", "write_trace"]


def write_trace(
    out: str | Path,
    *,
    channel: str = "paper",
    robots: int = 6,
    steps: int = 10,
    reliability: float = 1.0,
    latency_steps: int = 1,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> Trace:
    """Record a static-QoS traffic trace on a :data:`CHANNEL_PRESETS` cell and save it.

    The instance is what ``codesign solve`` and the allocation LP read: JSON, or Parquet when
    ``out`` ends in ``.parquet`` (row groups of ticks; ``progress(done, total)`` per group
    written). The recorder (:func:`~codesign_mb.wifi.cell.generate_trace`) returns the trace
    whole, so its size, robots x ticks, is capped
    (:data:`~codesign_mb.wifi.sim.TRACE_CELLS_CAP`) before anything runs.
    """
    if channel not in CHANNEL_PRESETS:
        raise ValueError(f"channel must be one of {sorted(CHANNEL_PRESETS)}, got {channel!r}")
    check_range("robots", robots, ge=1, cap=ROBOTS_CAP)
    check_range("steps", steps, ge=1)
    check_range("latency_steps", latency_steps, ge=1, cap=LATENCY_STEPS_CAP)
    check_range("seed", seed, ge=0, cap=SEED_CAP)
    QosRequest(reliability, latency_steps)  # reliability in [0, 1]
    config = CHANNEL_PRESETS[channel]
    ticks = (steps + latency_steps) * config.traffic.period_ticks(config.mac.tick_us)
    check_range("robots x ticks of the trace", robots * ticks, cap=TRACE_CELLS_CAP)
    trace = generate_trace(
        config,
        robots,
        steps=steps,
        reliability=reliability,
        latency_steps=latency_steps,
        seed=seed,
    )
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix == ".parquet":
        save_parquet(trace, out, progress=progress)
    else:
        trace.save(out)
    return trace


def solve_instance(
    path: str | Path,
    *,
    solver: str = "auto",
    compare: bool = False,
    windows: bool = True,
    workers: int | None = 1,
    backend: str = "local",
    address: str | None = None,
    journal: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Solve the instance at ``path``; with ``compare``, the allocators' frames and gaps.

    ``windows``: by independent windows (:mod:`codesign_mb.wifi.offline_windows`, the same
    optimum), solved by ``workers`` processes of the project's pool (``backend="local"``) or
    as Ray tasks (``"ray"``, on the cluster at ``address`` or a local instance), finished
    windows recorded in ``journal`` (a killed solve resumes); else as one LP.

    A Parquet instance (``.parquet``) solved by windows without ``compare`` is read by window
    (:class:`~codesign_mb.wifi.trace_parquet.ParquetTrace`): the frames table whole, each
    window's channel as it is solved; otherwise the instance is read whole.
    """
    check_workers(workers, 1)
    if backend not in ("local", "ray"):
        raise ValueError(f"backend must be local or ray, got {backend!r}")
    streamed = windows and not compare and Path(path).suffix == ".parquet"
    trace: TraceSource = ParquetTrace.open(path) if streamed else Trace.load(path)
    record: dict[str, Any] = {"instance": str(path)}
    if windows:
        mapper = (
            functools.partial(imap, workers=workers)
            if backend == "local"
            else functools.partial(_on_ray, workers=workers, address=address)
        )
        result = solve_windows(
            trace, solver=solver, mapper=mapper, journal=journal, progress=progress
        )
        table = result.windows
        optimum = result.optimum
        record.update(
            optimum_frames=optimum,
            solver=",".join(sorted(set(table["solver"]))),
            solve_time_s=result.solve_time_s,
            build_time_s=float(table["build_time_s"].sum()),
            status=result.status,
            frames_admitted=len(trace.frames),
            frames_deliverable=int(table["frames"].sum()),
            variables=result.n_variables,
            constraints=int(table["constraints"].sum()),
            windows=len(table),
            windows_resumed=int(table["resumed"].sum()),
            largest_window_variables=int(table["variables"].max()),
            per_window=table[["first_tick", "end_tick", "frames", "optimum"]].to_dict("list"),
            per_robot=result.stations["frames"].round(9).tolist(),
        )
    else:
        assert isinstance(trace, Trace)  # read whole: streamed only by windows
        mono = offline_optimum(trace, solver=solver)
        optimum = mono.optimum
        record.update(
            optimum_frames=optimum,
            solver=mono.solver,
            solve_time_s=mono.solve_time_s,
            build_time_s=mono.build_time_s,
            status=mono.status,
            frames_admitted=mono.n_frames_admitted,
            frames_deliverable=mono.n_frames,
            variables=mono.n_variables,
            constraints=mono.n_constraints,
        )
    if compare:
        assert isinstance(trace, Trace)
        for name in ("greedy", "convex"):
            replayed = replay(trace, name)
            delivered = replayed.delivered
            record[f"{name}_frames"] = delivered
            record[f"{name}_solver_fallbacks"] = replayed.fallbacks.total
            record[f"{name}_gap"] = (optimum - delivered) / optimum if optimum > 0 else 0.0
    return record


def _apply(call: tuple[Callable[..., Any], tuple[Any, ...]], index: int) -> Any:
    fn, args = call
    return fn(*args)


def _on_ray(
    fn: Callable[..., Any],
    tasks: Sequence[tuple[Any, ...]],
    *,
    workers: int | None,
    address: str | None,
) -> Iterator[tuple[int, Any]]:
    """A window mapper over Ray tasks (the sweeps' Ray backend, :func:`iter_ray`)."""
    from codesign_mb.studies.sweep_ray import iter_ray

    pending = [(str(i), (fn, task), i) for i, task in enumerate(tasks)]
    for key, result in iter_ray(_apply, pending, workers, address):
        yield int(key), result
