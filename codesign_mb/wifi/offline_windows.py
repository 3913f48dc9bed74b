"""[lp] by windows: the horizon cut where no frame is in flight, each window solved alone.

Every variable of [lp] belongs to one frame and lives on the ticks of that frame's life,
``[capture, deadline)``, or is a tick's ``y_k``; every row is a frame's (monotonicity,
precedence, DL exchange) or a tick's (capacity). Cut the horizon at a tick boundary that no
admitted frame's life spans: no row then holds variables of both sides, the constraint matrix
is block-diagonal over the windows, and the LP's optimum is the sum of the windows' optima,
exactly (the windows' solutions together are the monolithic one's, and no better solution of
the whole can exist, since it would give a better one of some window). No approximation and no
iteration: the decomposition is a reordering of one LP.

Such cuts exist wherever the cell falls silent for a moment: traffic of robots that ask for few
packets (a co-design's 10 % leaves about one tick in a hundred free of frames on a 48-robot
cell). A cell whose robots all stream (static QoS, ``q = 1``) has frames in flight at every
tick, one window, and is solved whole (``solvers/README.md`` gives both cases' figures).

Windows shorter than ``min_ticks`` are merged with the next (still a union of independent
blocks), so that a solver call is never spent on a handful of variables; they are solved in
any order by any ``mapper`` (the project's process pool, :func:`codesign_mb.evaluation.pool.
imap`, or Ray) and, given a ``journal`` file, a killed solve resumes with the windows it had
finished.

A trace comes from memory (:class:`~codesign_mb.wifi.sim.Trace`) or from any
:class:`TraceSource`, such as a Parquet trace read by window
(:class:`codesign_mb.wifi.trace_parquet.ParquetTrace`): the cuts need its frames table only,
and each window's channel is read when that window is solved (in the worker, for a pool), so
the channel of the whole trace is never in memory at once.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from codesign_mb.wifi.config import WifiConfig
from codesign_mb.wifi.offline import offline_optimum
from codesign_mb.wifi.sim import Trace

__all__ = [
    "TraceSource",
    "Window",
    "WindowedResult",
    "solve_windows",
    "split_windows",
    "window_trace",
]

Mapper = Callable[[Callable[..., Any], Sequence[tuple[Any, ...]]], Iterable[tuple[int, Any]]]
"""``mapper(fn, tasks)`` yields ``(task index, fn(*task))`` for every task, in any order."""


class TraceSource(Protocol):
    """What the windows need of a trace: its frames whole, its channel by tick range."""

    @property
    def config(self) -> WifiConfig: ...

    @property
    def horizon_ticks(self) -> int: ...

    @property
    def n_stations(self) -> int: ...

    @property
    def frames(self) -> pd.DataFrame: ...

    def channel(
        self, first_tick: int, end_tick: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``ul_bpss`` and ``dl_bpss`` of ticks ``[first_tick, end_tick)``."""
        ...


@dataclass(frozen=True)
class Window:
    """Ticks ``[first_tick, end_tick)`` and the trace's frame-table rows whose lives are in it."""

    first_tick: int
    end_tick: int
    frame_rows: NDArray[np.int64]


def _lives(trace: TraceSource) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """The frames [lp] may hold (both hops deliver them): rows, captures, clipped deadlines."""
    f = trace.frames
    keep = ((f["ul_ok"] != 0) & (f["dl_ok"] != 0)).to_numpy()
    rows = np.flatnonzero(keep).astype(np.int64)
    cap = f["capture_tick"].to_numpy(dtype=np.int64)[keep]
    dead = np.minimum(f["deadline_tick"].to_numpy(dtype=np.int64)[keep], trace.horizon_ticks)
    return rows, cap, dead


def split_windows(trace: TraceSource, *, min_ticks: int = 200) -> list[Window]:
    """The horizon cut at every tick boundary no frame's life spans, windows merged up to at
    least ``min_ticks`` ticks (the last may be shorter). One window when frames are always in
    flight."""
    if int(min_ticks) != min_ticks or min_ticks < 1:
        raise ValueError(f"min_ticks must be an integer >= 1, got {min_ticks!r}")
    horizon = trace.horizon_ticks
    rows, cap, dead = _lives(trace)
    live = np.zeros(horizon + 1, dtype=np.int64)  # live[c]: frames with cap < c < dead
    np.add.at(live, cap + 1, 1)
    np.add.at(live, np.maximum(dead, cap + 1), -1)
    spanning = np.cumsum(live)[:horizon]
    cuts = (np.flatnonzero(spanning[1:] == 0) + 1).tolist()  # boundaries before tick c
    bounds, first = [], 0
    for c in cuts:
        if c - first >= min_ticks:
            bounds.append((first, c))
            first = c
    bounds.append((first, horizon))
    order = np.argsort(cap, kind="stable")
    starts = np.searchsorted(cap[order], [b[0] for b in bounds], side="left")
    ends = np.searchsorted(cap[order], [b[1] for b in bounds], side="left")
    return [
        Window(lo, hi, np.sort(rows[order[s:e]]))
        for (lo, hi), s, e in zip(bounds, starts.tolist(), ends.tolist(), strict=True)
    ]


@dataclass(frozen=True)
class PendingWindow:
    """A window whose channel is still in its source: read by :meth:`load` where it is solved.

    ``frames`` are the window's, re-based to its first tick; ``source`` is pickled to a
    worker without its frames table (:class:`~codesign_mb.wifi.trace_parquet.ParquetTrace`).
    """

    source: TraceSource
    first_tick: int
    end_tick: int
    frames: pd.DataFrame

    def load(self) -> Trace:
        ul, dl = self.source.channel(self.first_tick, self.end_tick)
        return Trace(
            config=self.source.config,
            horizon_ticks=self.end_tick - self.first_tick,
            ul_bpss=ul,
            dl_bpss=dl,
            frames=self.frames,
        )


def _pending(trace: TraceSource, window: Window) -> PendingWindow:
    lo, hi = window.first_tick, window.end_tick
    frames = trace.frames.iloc[window.frame_rows].reset_index(drop=True)
    frames = frames.assign(
        capture_tick=frames["capture_tick"] - lo,
        deadline_tick=np.minimum(frames["deadline_tick"], trace.horizon_ticks) - lo,
    )
    frames = frames[frames["deadline_tick"] > frames["capture_tick"]].reset_index(drop=True)
    return PendingWindow(trace, lo, hi, frames)


def window_trace(trace: TraceSource, window: Window) -> Trace:
    """The trace of one window: its ticks and frames, re-based to start at tick 0."""
    return _pending(trace, window).load()


@dataclass(frozen=True)
class WindowedResult:
    """[lp]'s optimum as the sum of its windows' and what each window and robot holds.

    ``windows``: one row per window (``first_tick``, ``end_tick``, ``frames``, ``variables``,
    ``constraints``, ``optimum``, ``solver``, ``status``, ``build_time_s``, ``solve_time_s``,
    the airtime prices of :func:`solve_window`, ``resumed``: read from the journal);
    ``stations``: the optimum's frames per robot.
    """

    optimum: float
    status: str
    windows: pd.DataFrame
    stations: pd.DataFrame

    @property
    def solve_time_s(self) -> float:
        return float(self.windows["solve_time_s"].sum())

    @property
    def n_variables(self) -> int:
        return int(self.windows["variables"].sum())


PRICED = 1e-7
"""A tick whose UL or DL capacity row has a dual price above this is counted as priced
(airtime there is scarce; the interior point leaves prices of about 1e-9 on free ticks)."""


def solve_window(trace: Trace | PendingWindow, solver: str) -> dict[str, Any]:
    """One window's optimum, timings, frames delivered per station and airtime prices (the
    sums and maximum over its ticks of the duals of :class:`~codesign_mb.wifi.offline.
    AirtimePrices`, the ticks priced above :data:`PRICED`; NaN without duals): a picklable
    task."""
    if isinstance(trace, PendingWindow):
        trace = trace.load()
    r = offline_optimum(trace, solver=solver)
    stations = trace.frames["station"].to_numpy()[r.frame_rows] if r.n_frames else np.zeros(0)
    per_station = np.bincount(
        stations.astype(np.int64), weights=r.delivered, minlength=trace.n_stations
    )
    ul, dl = (np.full(1, np.nan) if p is None else p for p in (r.ul_price, r.dl_price))
    return {
        "frames": r.n_frames,
        "variables": r.n_variables,
        "constraints": r.n_constraints,
        "optimum": r.optimum,
        "solver": r.solver,
        "status": r.status,
        "build_time_s": r.build_time_s,
        "solve_time_s": r.solve_time_s,
        "ul_price_sum": float(ul.sum()),
        "dl_price_sum": float(dl.sum()),
        "ul_price_max": float(ul.max()) if ul.size else 0.0,
        "priced_ticks": int(((ul > PRICED) | (dl > PRICED)).sum()),
        "stations": per_station.tolist(),
    }


def _in_process(
    fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]
) -> Iterator[tuple[int, Any]]:
    for i, task in enumerate(tasks):
        yield i, fn(*task)


def _fingerprint(trace: TraceSource, windows: list[Window], solver: str) -> str:
    """A hash of the channel (read window by window, tick-major), frames, cuts and solver:
    the same for a trace in memory and in a Parquet file."""
    h = hashlib.sha256()
    for w in windows:
        for part in trace.channel(w.first_tick, w.end_tick):
            h.update(np.ascontiguousarray(part.T).tobytes())
    h.update(np.ascontiguousarray(trace.frames[list(Trace.COLUMNS)].to_numpy()).tobytes())
    h.update(json.dumps([[w.first_tick, w.end_tick] for w in windows] + [solver]).encode())
    return h.hexdigest()[:16]


class _Tasks(Sequence[tuple[Trace | PendingWindow, str]]):
    """The windows to solve, each made when a mapper takes it (lazy: a trace read by window
    is read one window at a time in this process, or in the workers of a pool)."""

    def __init__(self, trace: TraceSource, windows: list[Window], solver: str) -> None:
        self.trace, self.windows, self.solver = trace, windows, solver

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        w = self.windows[i]
        if isinstance(self.trace, Trace):  # in memory already: views of its arrays
            return window_trace(self.trace, w), self.solver
        return _pending(self.trace, w), self.solver


def _read_journal(path: Path, key: str) -> dict[int, dict[str, Any]]:
    """The windows a journal for the same trace, cuts and solver holds (others: ignored)."""
    done: dict[int, dict[str, Any]] = {}
    if not path.is_file():
        return done
    for line in path.read_text().splitlines():
        try:
            entry = json.loads(line)
        except json.JSONDecodeError:  # a line cut by a kill: that window is solved again
            continue
        if isinstance(entry, dict) and entry.get("key") == key and entry.get("status") == "optimal":
            done[int(entry["window"])] = entry
    return done


def solve_windows(
    trace: TraceSource,
    *,
    solver: str = "auto",
    min_ticks: int = 200,
    mapper: Mapper | None = None,
    journal: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> WindowedResult:
    """Solve [lp] window by window (:func:`split_windows`); the optimum is the monolithic one.

    ``mapper`` runs the windows (default: in this process, in order); ``journal`` (a file)
    records each finished window, and a later call with the same trace, cuts and solver
    reuses them; ``progress(done, total)`` is called as windows finish. ``trace`` is a
    :class:`~codesign_mb.wifi.sim.Trace` or any :class:`TraceSource` (read by window).
    """
    windows = split_windows(trace, min_ticks=min_ticks)
    path = Path(journal) if journal is not None else None
    key = _fingerprint(trace, windows, solver) if path is not None else ""
    done = _read_journal(path, key) if path is not None else {}
    todo = [i for i in range(len(windows)) if i not in done]
    tasks = _Tasks(trace, [windows[i] for i in todo], solver)
    results: dict[int, dict[str, Any]] = {i: {**done[i], "resumed": True} for i in done}
    if progress is not None:
        progress(len(results), len(windows))
    for j, record in (mapper or _in_process)(solve_window, tasks):
        i = todo[j]
        results[i] = {**record, "resumed": False}
        if path is not None:
            with path.open("a") as fh:
                fh.write(json.dumps({"key": key, "window": i, **record}) + "\n")
        if progress is not None:
            progress(len(results), len(windows))
    rows = [
        {"first_tick": w.first_tick, "end_tick": w.end_tick, **results[i]}
        for i, w in enumerate(windows)
    ]
    stations = np.sum([r.pop("stations") for r in rows], axis=0)
    table = pd.DataFrame(rows)
    ok = bool((table["status"] == "optimal").all())
    return WindowedResult(
        optimum=float(table["optimum"].sum()) if ok else float("nan"),
        status="optimal" if ok else "; ".join(sorted(set(table["status"]) - {"optimal"})),
        windows=table,
        stations=pd.DataFrame(
            {"station": np.arange(trace.n_stations), "frames": np.asarray(stations, dtype=float)}
        ),
    )
