"""Instances of the offline allocation LP: recorded (``codesign wifi trace``) and solved.

:func:`write_trace` records a static-QoS trace on a capacity-study cell as an instance file
(JSON, or Parquet for a path ending in ``.parquet``: :mod:`codesign_mb.wifi.trace_parquet`);
what ``codesign solve`` prints: the optimum of :func:`~codesign_mb.wifi.offline.offline_optimum`
(the most frames any scheduler delivers in time on the trace), per window and per robot, the
airtime prices per window and, optionally, what the online allocators deliver when replayed on
the same trace.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from codesign_mb.core.config import (
    LATENCY_STEPS_CAP,
    ROBOTS_CAP,
    SEED_CAP,
    STEPS_CAP,
    ConfigError,
    check_range,
)
from codesign_mb.evaluation.pool import check_workers, imap
from codesign_mb.network.qos import QosRequest
from codesign_mb.studies.fig_wifi import CHANNEL_PRESETS
from codesign_mb.wifi.cell import join_chunks, record_trace
from codesign_mb.wifi.offline import offline_optimum
from codesign_mb.wifi.offline_windows import Mapper, TraceSource, solve_windows
from codesign_mb.wifi.sim import TRACE_CELLS_CAP, Trace, replay
from codesign_mb.wifi.trace_parquet import STREAMED_TICKS_CAP, ParquetTrace, TraceWriter

__all__ = [
    "CHUNK_STEPS",
    "COMPARED",
    "COMPARED_KEYS",
    "PER_WINDOW",
    "RecordedTrace",
    "solve_instance",
    "write_trace",
]

CHUNK_STEPS = 250
"""Control steps :func:`write_trace` records between writes (10 s; 48 robots: 10 MB of channel)."""
COMPARED = ("greedy", "convex", "tick-optimal")
"""The online allocators ``codesign solve --compare`` replays on the trace."""
COMPARED_KEYS: dict[str, str] = {name: name.replace("-", "_") for name in COMPARED}
"""Allocator -> the prefix of its keys in a solve's record (``tick_optimal_frames``)."""
PER_WINDOW = (
    "first_tick",
    "end_tick",
    "frames",
    "optimum",
    "ul_price_sum",
    "dl_price_sum",
    "ul_price_max",
    "priced_ticks",
)
"""The columns of a solve's ``per_window`` (``--compare`` adds each allocator's frames)."""


@dataclass(frozen=True)
class RecordedTrace:
    """What :func:`write_trace` wrote: the instance file and its sizes."""

    path: Path
    n_stations: int
    horizon_ticks: int
    frames: int


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
) -> RecordedTrace:
    """Record a static-QoS traffic trace on a :data:`CHANNEL_PRESETS` cell and save it.

    The instance is what ``codesign solve`` and the allocation LP read. Parquet (``out``
    ending in ``.parquet``) is written as it is recorded (:func:`~codesign_mb.wifi.cell.
    record_trace` into a :class:`~codesign_mb.wifi.trace_parquet.TraceWriter`, about
    :data:`CHUNK_STEPS` steps in memory at a time), so its length is bounded only by the
    format's caps; a JSON instance is held whole (the same chunks joined,
    :func:`~codesign_mb.wifi.cell.join_chunks`), so its size, robots x ticks, is capped
    (:data:`~codesign_mb.wifi.sim.TRACE_CELLS_CAP`) before anything runs.
    ``progress(done, total)`` counts the ticks recorded.
    """
    if channel not in CHANNEL_PRESETS:
        raise ValueError(f"channel must be one of {sorted(CHANNEL_PRESETS)}, got {channel!r}")
    check_range("robots", robots, ge=1, cap=ROBOTS_CAP)
    check_range("steps", steps, ge=1, cap=STEPS_CAP)
    check_range("latency_steps", latency_steps, ge=1, cap=LATENCY_STEPS_CAP)
    check_range("seed", seed, ge=0, cap=SEED_CAP)
    QosRequest(reliability, latency_steps)  # reliability in [0, 1]
    config = CHANNEL_PRESETS[channel]
    out = Path(out)
    ticks = (steps + latency_steps) * config.traffic.period_ticks(config.mac.tick_us)
    parquet = out.suffix == ".parquet"
    if parquet:
        check_range("ticks of the trace", ticks, cap=STREAMED_TICKS_CAP)
    elif robots * ticks > TRACE_CELLS_CAP.value:
        raise ConfigError(
            f"robots x ticks of the trace must be <= {TRACE_CELLS_CAP.value} for a JSON "
            f"instance (the cap on {TRACE_CELLS_CAP.what}), got {robots * ticks}; "
            f"write it as Parquet ({out.with_suffix('.parquet').name}), recorded as it goes"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    chunks = record_trace(
        config,
        robots,
        steps=steps,
        reliability=reliability,
        latency_steps=latency_steps,
        seed=seed,
        chunk_steps=CHUNK_STEPS,
    )
    frames = 0
    if parquet:
        with TraceWriter(out, config, robots, ticks) as writer:
            for chunk in chunks:
                writer.add_ticks(chunk.ul_bpss, chunk.dl_bpss)
                writer.add_frames(chunk.frames)
                frames += len(chunk.frames)
                if progress is not None:
                    progress(chunk.first_tick + chunk.ul_bpss.shape[1], ticks)
        return RecordedTrace(out, robots, ticks, frames)
    trace = join_chunks(config, chunks)
    trace.save(out)
    if progress is not None:
        progress(ticks, ticks)
    return RecordedTrace(out, robots, ticks, len(trace.frames))


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

    A Parquet instance (``.parquet``) solved by windows is read by window
    (:class:`~codesign_mb.wifi.trace_parquet.ParquetTrace`): the frames table whole, each
    window's channel as it is solved; ``--monolithic`` reads the instance whole.

    ``compare`` replays :data:`COMPARED` on the same trace (:func:`~codesign_mb.wifi.sim.
    replay`, a Parquet trace read in chunks of ticks), one task each on the same workers:
    each one's frames delivered in time, its gap to the optimum and, solved by windows, its
    frames per window (by capture tick) next to the window's optimum.
    """
    check_workers(workers, 1)
    if backend not in ("local", "ray"):
        raise ValueError(f"backend must be local or ray, got {backend!r}")
    streamed = windows and Path(path).suffix == ".parquet"
    trace: TraceSource = ParquetTrace.open(path) if streamed else Trace.load(path)
    record: dict[str, Any] = {"instance": str(path)}
    mapper: Mapper = (
        functools.partial(imap, workers=workers)
        if backend == "local"
        else functools.partial(_on_ray, workers=workers, address=address)
    )
    firsts: list[int] = []
    if windows:
        result = solve_windows(
            trace, solver=solver, mapper=mapper, journal=journal, progress=progress
        )
        table = result.windows
        optimum = result.optimum
        firsts = table["first_tick"].tolist()
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
            per_window=table[list(PER_WINDOW)].to_dict("list"),
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
        source = str(path) if isinstance(trace, ParquetTrace) else trace  # reopened by a worker
        tasks = [(source, name, firsts) for name in COMPARED]
        replays = dict(mapper(_replay, tasks))
        for i, name in enumerate(COMPARED):
            key, replayed = COMPARED_KEYS[name], replays[i]
            delivered = replayed["delivered"]
            record[f"{key}_frames"] = delivered
            record[f"{key}_solver_fallbacks"] = replayed["fallbacks"]
            record[f"{key}_gap"] = (optimum - delivered) / optimum if optimum > 0 else 0.0
            if windows:
                record["per_window"][key] = replayed["per_window"]
    return record


def _replay(source: Trace | str, name: str, firsts: list[int]) -> dict[str, Any]:
    """Replay ``name`` on a trace (or the Parquet trace at a path): frames delivered in time,
    fallbacks, and the delivered frames per window starting at the ticks ``firsts``."""
    trace = ParquetTrace.open(source) if isinstance(source, str) else source
    result = replay(trace, name)
    fates = result.frames
    captured = fates["capture_tick"].to_numpy()[(fates["fate"] == "delivered").to_numpy()]
    window = np.searchsorted(np.asarray(firsts, dtype=np.int64), captured, side="right") - 1
    return {
        "delivered": result.delivered,
        "fallbacks": result.fallbacks.total,
        "per_window": np.bincount(window, minlength=len(firsts)).tolist() if firsts else [],
    }


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
