"""Recorded traces of a WiFi 6 cell and their replay through the slot simulator.

The channel state (bits per data subcarrier and symbol of every station, per tick) and the
admitted frames form a :class:`Trace` (stored as an instance file, ``solvers/README.md``);
:func:`replay` runs any allocator on a trace through the slot simulator
(:class:`~codesign_mb.wifi.engine.ChannelEngine`), and
:func:`codesign_mb.wifi.offline.offline_optimum` bounds what any allocator can do on it.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from codesign_mb.core.config import (
    ROBOTS_CAP,
    STEPS_CAP,
    Cap,
    ConfigError,
    as_matrix,
    check_range,
    from_mapping,
    show,
    to_mapping,
)
from codesign_mb.wifi.allocators import Allocator
from codesign_mb.wifi.config import WifiConfig, make_allocator
from codesign_mb.wifi.engine import ChannelEngine, FallbackCount, Frame

if TYPE_CHECKING:
    from codesign_mb.wifi.offline_windows import TraceSource

__all__ = [
    "REPLAY_CHUNK_TICKS",
    "TRACE_CELLS_CAP",
    "TRACE_FORMAT",
    "ReplayResult",
    "Trace",
    "TraceFile",
    "check_frames",
    "replay",
]

TRACE_FORMAT = "codesign-wifi-trace/1"
REPLAY_CHUNK_TICKS = 10_000
"""Ticks of channel :func:`replay` reads at a time from a trace's source (10 s)."""


@dataclass(frozen=True)
class Trace:
    """A recorded traffic and channel trace: what every allocator faces, and the LP's data.

    Attributes
    ----------
    config:
        The cell (PHY, MAC, traffic; the scheduler field is ignored on replay).
    horizon_ticks:
        Number of ticks ``T``.
    ul_bpss, dl_bpss:
        ``(n_stations, T)`` bits per data subcarrier and symbol, UL and DL, at each tick
        (``N_BPSCS * R * N_SS`` of the MCS link adaptation chose).
    frames:
        One row per admitted frame: ``station, step, capture_tick, deadline_tick, ul_bits,
        dl_bits, ul_ok, dl_ok``.
    """

    config: WifiConfig
    horizon_ticks: int
    ul_bpss: NDArray[np.float64]
    dl_bpss: NDArray[np.float64]
    frames: pd.DataFrame

    COLUMNS = (
        "station",
        "step",
        "capture_tick",
        "deadline_tick",
        "ul_bits",
        "dl_bits",
        "ul_ok",
        "dl_ok",
    )

    def __post_init__(self) -> None:
        ul = np.asarray(self.ul_bpss, dtype=float)
        dl = np.asarray(self.dl_bpss, dtype=float)
        if ul.ndim != 2 or ul.shape != dl.shape or ul.shape[1] != self.horizon_ticks:
            raise ValueError(
                f"ul_bpss and dl_bpss must both have shape (n_stations, horizon_ticks="
                f"{self.horizon_ticks}), got {ul.shape} and {dl.shape}"
            )
        if np.any(ul < 0) or np.any(dl < 0):
            raise ValueError("ul_bpss and dl_bpss must be >= 0")
        missing = [c for c in self.COLUMNS if c not in self.frames.columns]
        if missing:
            raise ValueError(f"frames lacks columns {missing}")
        f = self.frames
        if len(f) and (
            f["station"].min() < 0
            or f["station"].max() >= ul.shape[0]
            or (f["deadline_tick"] <= f["capture_tick"]).any()
            or f["capture_tick"].min() < 0
        ):
            raise ValueError(
                "frames must have 0 <= station < n_stations, capture_tick >= 0 and "
                "deadline_tick > capture_tick"
            )
        object.__setattr__(self, "ul_bpss", ul)
        object.__setattr__(self, "dl_bpss", dl)

    @property
    def n_stations(self) -> int:
        return int(self.ul_bpss.shape[0])

    def to_json(self) -> dict[str, Any]:
        """The instance-file form (``solvers/README.md``)."""
        return {
            "format": TRACE_FORMAT,
            "config": to_mapping(self.config),
            "n_stations": self.n_stations,
            "horizon_ticks": self.horizon_ticks,
            "ul_bpss": self.ul_bpss.round(6).tolist(),
            "dl_bpss": self.dl_bpss.round(6).tolist(),
            "frames": {c: self.frames[c].astype(int).tolist() for c in self.COLUMNS},
        }

    @classmethod
    def from_json(cls, data: Any) -> Trace:
        """Parse the instance-file form (:class:`TraceFile`); errors name the field."""
        spec = from_mapping(TraceFile, data, where="") if isinstance(data, dict) else None
        if spec is None:
            raise ConfigError(f"an instance must be a JSON object, got {show(data)}")
        return cls(
            config=from_mapping(WifiConfig, spec.config, where="config"),
            horizon_ticks=spec.horizon_ticks,
            ul_bpss=spec.ul_bpss,
            dl_bpss=spec.dl_bpss,
            frames=pd.DataFrame(
                {c: np.asarray(spec.frames[c], dtype=np.int64) for c in cls.COLUMNS}
            ),
        )

    def channel(
        self, first_tick: int, end_tick: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``ul_bpss`` and ``dl_bpss`` of ticks ``[first_tick, end_tick)`` (views)."""
        return self.ul_bpss[:, first_tick:end_tick], self.dl_bpss[:, first_tick:end_tick]

    def save(self, path: str | Path) -> None:
        """Write the instance file: Parquet if ``path`` ends in ``.parquet``, else JSON."""
        if Path(path).suffix == ".parquet":
            from codesign_mb.wifi.trace_parquet import save_parquet  # imports this module

            save_parquet(self, path)
            return
        Path(path).write_text(json.dumps(self.to_json()) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Trace:
        """Read an instance file, Parquet (``.parquet``) or JSON; errors name the field and
        the file."""
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"instance file {str(path)!r} does not exist")
        if path.suffix == ".parquet":
            from codesign_mb.wifi.trace_parquet import load_parquet

            return load_parquet(path)
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"instance file {str(path)!r} is not valid JSON: {exc}") from None
        try:
            return cls.from_json(data)
        except ValueError as exc:
            raise ConfigError(f"{exc} (instance file {str(path)!r})") from exc


TRACE_CELLS_CAP = Cap(4_000_000, "channel states of a trace: stations x ticks")


@dataclass(frozen=True)
class TraceFile:
    """The schema of an instance file (``solvers/README.md``), checked by ``from_mapping``.

    Every number finite and in range, the frame columns of equal length, each frame's
    station one of the trace's, its deadline after its capture and within the horizon.
    """

    format: str
    horizon_ticks: int
    ul_bpss: Any
    dl_bpss: Any
    frames: dict[str, tuple[int, ...]]
    config: dict[str, Any] = field(default_factory=dict)
    n_stations: int | None = None
    comment: str = ""

    def __post_init__(self) -> None:
        if self.format != TRACE_FORMAT:
            raise ValueError(f"format must be {TRACE_FORMAT!r}, got {show(self.format)}")
        check_range("horizon_ticks", self.horizon_ticks, ge=1, cap=STEPS_CAP)
        ul = as_matrix("ul_bpss", self.ul_bpss)
        dl = as_matrix("dl_bpss", self.dl_bpss, ul.shape)
        check_range("n_stations (rows of ul_bpss)", ul.shape[0], cap=ROBOTS_CAP)
        check_range("ul_bpss and dl_bpss", ul.size, cap=TRACE_CELLS_CAP)
        for name, m in (("ul_bpss", ul), ("dl_bpss", dl)):
            check_range(name, m.min(), ge=0)
        if ul.shape[1] != self.horizon_ticks:
            raise ValueError(
                f"ul_bpss must have horizon_ticks = {self.horizon_ticks} columns, got {ul.shape}"
            )
        if self.n_stations is not None and self.n_stations != ul.shape[0]:
            raise ValueError(f"n_stations is {self.n_stations} but ul_bpss has {ul.shape[0]} rows")
        self._check_frames(ul.shape[0])
        object.__setattr__(self, "ul_bpss", ul)
        object.__setattr__(self, "dl_bpss", dl)

    def _check_frames(self, n_stations: int) -> None:
        check_frames(self.frames, n_stations, self.horizon_ticks)


def check_frames(frames: Mapping[str, Any], n_stations: int, horizon_ticks: int) -> None:
    """Raise ``ValueError`` naming the column unless ``frames`` (column -> values) is a frame
    table of a trace of ``n_stations`` and ``horizon_ticks`` (the checks of :class:`TraceFile`,
    shared with the Parquet form, :mod:`codesign_mb.wifi.trace_parquet`)."""
    unknown = sorted(set(frames) - set(Trace.COLUMNS))
    missing = [c for c in Trace.COLUMNS if c not in frames]
    if unknown or missing:
        raise ValueError(
            f"frames must have the columns {', '.join(Trace.COLUMNS)}; "
            f"unknown {unknown}, missing {missing}"
        )
    lengths = {len(v) for v in frames.values()}
    if len(lengths) > 1:
        raise ValueError(f"frames columns must have one length, got lengths {sorted(lengths)}")
    f = {c: np.asarray(v, dtype=np.int64) for c, v in frames.items()}
    if not lengths or lengths == {0}:
        return
    check_range("frames.station", f["station"].max(), le=n_stations - 1)
    for c in ("station", "step", "capture_tick", "ul_bits", "dl_bits"):
        check_range(f"frames.{c}", f[c].min(), ge=0)
    for c in ("ul_ok", "dl_ok"):
        bad = f[c][(f[c] != 0) & (f[c] != 1)]
        if bad.size:
            raise ValueError(f"frames.{c} must be 0 or 1, got {int(bad[0])}")
    late = f["deadline_tick"] - f["capture_tick"]
    check_range("frames.deadline_tick - capture_tick", late.min(), ge=1)
    check_range("frames.deadline_tick", f["deadline_tick"].max(), le=horizon_ticks)


@dataclass(frozen=True)
class ReplayResult:
    """Outcome of :func:`replay`: per-station summary, per-frame fates, layouts (optional).

    ``fallbacks`` counts the ticks whose allocator could not use its solver's solution.
    """

    summary: pd.DataFrame
    frames: pd.DataFrame
    layouts: list[tuple[int, str, NDArray[np.int64]]] | None
    fallbacks: FallbackCount

    @property
    def delivered(self) -> int:
        """Frames whose state reached the robot in time."""
        return int(self.summary["delivered"].sum())


def replay(
    trace: Trace | TraceSource,
    allocator: str | tuple[Allocator, Allocator],
    *,
    record_layouts: bool = False,
) -> ReplayResult:
    """Run a scheduler on a recorded trace (deterministic: no randomness left in a trace).

    Parameters
    ----------
    trace:
        The trace: in memory, or any source of its channel by tick range (a Parquet trace,
        :class:`~codesign_mb.wifi.trace_parquet.ParquetTrace`, is read
        :data:`REPLAY_CHUNK_TICKS` ticks at a time; the same result bit for bit).
    allocator:
        A scheduler name (``"greedy"``, ``"convex"``, ``"convex-cvxpy"``, ``"tick-optimal"``)
        or a ``(ul_allocator, dl_allocator)`` pair.
    record_layouts:
        Keep every tick's layout (for validity tests).
    """
    n = trace.n_stations
    if isinstance(allocator, str):
        ul, dl = (
            make_allocator(trace.config, n, allocator),
            make_allocator(trace.config, n, allocator),
        )
    else:
        ul, dl = allocator
    engine = ChannelEngine(trace.config, n, ul, dl)
    if record_layouts:
        engine.layouts = []
    order = trace.frames.sort_values(["capture_tick", "station"], kind="stable")
    columns = [order[c].to_numpy(dtype=np.int64).tolist() for c in Trace.COLUMNS]
    captured = columns[Trace.COLUMNS.index("capture_tick")]
    frames: list[Frame] = []
    j = 0
    for lo in range(0, trace.horizon_ticks, REPLAY_CHUNK_TICKS):
        hi = min(lo + REPLAY_CHUNK_TICKS, trace.horizon_ticks)
        ul_bpss, dl_bpss = trace.channel(lo, hi)
        for k in range(lo, hi):
            while j < len(order) and captured[j] <= k:
                station, step, cap, dead, ul_bits, dl_bits, ul_ok, dl_ok = (c[j] for c in columns)
                f = Frame(station, step, cap, dead, ul_bits, dl_bits, bool(ul_ok), bool(dl_ok))
                engine.add(f)
                frames.append(f)
                j += 1
            engine.run_tick(ul_bpss[:, k - lo], dl_bpss[:, k - lo])
    engine.flush()
    fates = pd.DataFrame(
        {
            "station": [f.station for f in frames],
            "step": [f.step for f in frames],
            "capture_tick": [f.capture_tick for f in frames],
            "fate": [f.fate for f in frames],
            "delivered_tick": [f.delivered_tick for f in frames],
        }
    )
    return ReplayResult(engine.summary(), fates, engine.layouts, engine.fallbacks)
