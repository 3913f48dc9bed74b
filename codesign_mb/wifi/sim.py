"""Recorded traces of a WiFi 6 cell and their replay through the slot simulator.

The channel state (bits per data subcarrier and symbol of every station, per tick) and the
admitted frames form a :class:`Trace` (stored as an instance file, ``solvers/README.md``);
:func:`replay` runs any allocator on a trace through the slot simulator
(:class:`~codesign_mb.wifi.engine.ChannelEngine`), and
:func:`codesign_mb.wifi.offline.offline_optimum` bounds what any allocator can do on it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from codesign_mb.core.config import from_mapping, to_mapping
from codesign_mb.wifi.allocators import Allocator
from codesign_mb.wifi.config import WifiConfig, make_allocator
from codesign_mb.wifi.engine import ChannelEngine, FallbackCount, Frame

__all__ = ["TRACE_FORMAT", "ReplayResult", "Trace", "replay"]

TRACE_FORMAT = "codesign-wifi-trace/1"


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
    def from_json(cls, data: dict[str, Any]) -> Trace:
        """Parse the instance-file form; errors name the offending field."""
        if not isinstance(data, dict) or data.get("format") != TRACE_FORMAT:
            raise ValueError(
                f"instance format must be {TRACE_FORMAT!r}, got {data.get('format')!r}"
            )
        unknown = sorted(
            set(data) - {"format", "config", "n_stations", "horizon_ticks", "ul_bpss", "dl_bpss",
                         "frames", "comment"}
        )  # fmt: skip
        if unknown:
            raise ValueError(f"unknown keys {unknown} in the instance")
        config = from_mapping(WifiConfig, data.get("config", {}), where="config")
        frames = data.get("frames", {})
        if not isinstance(frames, dict):
            raise ValueError("frames must be a table of columns")
        table = pd.DataFrame(
            {c: np.asarray(frames.get(c, []), dtype=np.int64) for c in cls.COLUMNS}
        )
        trace = cls(
            config=config,
            horizon_ticks=int(data["horizon_ticks"]),
            ul_bpss=np.asarray(data["ul_bpss"], dtype=float),
            dl_bpss=np.asarray(data["dl_bpss"], dtype=float),
            frames=table,
        )
        if "n_stations" in data and int(data["n_stations"]) != trace.n_stations:
            raise ValueError(
                f"n_stations is {data['n_stations']} but ul_bpss has {trace.n_stations} rows"
            )
        return trace

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json()) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Trace:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"instance file {str(path)!r} does not exist")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"instance file {str(path)!r} is not valid JSON: {exc}") from exc
        return cls.from_json(data)


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
    trace: Trace,
    allocator: str | tuple[Allocator, Allocator],
    *,
    record_layouts: bool = False,
) -> ReplayResult:
    """Run a scheduler on a recorded trace (deterministic: no randomness left in a trace).

    Parameters
    ----------
    trace:
        The trace.
    allocator:
        A scheduler name (``"greedy"``, ``"convex"``, ``"convex-cvxpy"``) or a
        ``(ul_allocator, dl_allocator)`` pair.
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
    rows = order.to_dict("records")
    frames: list[Frame] = []
    j = 0
    for k in range(trace.horizon_ticks):
        while j < len(rows) and rows[j]["capture_tick"] <= k:
            r = rows[j]
            f = Frame(
                int(r["station"]),
                int(r["step"]),
                int(r["capture_tick"]),
                int(r["deadline_tick"]),
                int(r["ul_bits"]),
                int(r["dl_bits"]),
                bool(r["ul_ok"]),
                bool(r["dl_ok"]),
            )
            engine.add(f)
            frames.append(f)
            j += 1
        engine.run_tick(trace.ul_bpss[:, k], trace.dl_bpss[:, k])
    engine.flush()
    fates = pd.DataFrame(
        {
            "station": [f.station for f in frames],
            "step": [f.step for f in frames],
            "fate": [f.fate for f in frames],
            "delivered_tick": [f.delivered_tick for f in frames],
        }
    )
    return ReplayResult(engine.summary(), fates, engine.layouts, engine.fallbacks)
