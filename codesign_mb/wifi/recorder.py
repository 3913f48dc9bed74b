"""Recording a cell's trace: what a :class:`~codesign_mb.wifi.cell.SharedChannel` keeps of an
episode (the channel per tick, the admitted frames), whole or in parts
(:func:`codesign_mb.wifi.cell.record_trace`), and the engine that only keeps the clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from codesign_mb.wifi.config import WifiConfig
from codesign_mb.wifi.engine import ChannelEngine, Frame
from codesign_mb.wifi.sim import Trace

__all__ = ["TraceChunk", "TraceRecorder", "TrafficOnlyEngine"]


@dataclass(frozen=True)
class TraceChunk:
    """A part of a recording (:func:`~codesign_mb.wifi.cell.record_trace`): ticks
    ``[first_tick, first_tick + k)`` (``ul_bpss`` and ``dl_bpss``, ``(n_stations, k)``) and the
    frames admitted since the previous part (the columns of :attr:`Trace.COLUMNS`)."""

    first_tick: int
    ul_bpss: NDArray[np.float64]
    dl_bpss: NDArray[np.float64]
    frames: pd.DataFrame


class TraceRecorder:
    """The ticks and frames of a :class:`~codesign_mb.wifi.cell.SharedChannel` 's episode."""

    def __init__(self) -> None:
        self.ul: list[NDArray] = []
        self.dl: list[NDArray] = []
        self.frames: list[tuple[int, ...]] = []
        self.taken = 0  # ticks handed out by take()

    def _arrays(self, n: int) -> tuple[NDArray, NDArray, pd.DataFrame]:
        rows = np.array(self.frames, dtype=np.int64).reshape(-1, len(Trace.COLUMNS))
        table = pd.DataFrame(rows, columns=list(Trace.COLUMNS))
        if not self.ul:
            return np.zeros((n, 0)), np.zeros((n, 0)), table
        return np.stack(self.ul, axis=1), np.stack(self.dl, axis=1), table

    def take(self, n: int) -> TraceChunk:
        """What was recorded since the last call, removed from the recorder."""
        chunk = TraceChunk(self.taken, *self._arrays(n))
        self.taken += len(self.ul)
        self.ul, self.dl, self.frames = [], [], []
        return chunk

    def trace(self, config: WifiConfig, n: int) -> Trace:
        ul, dl, table = self._arrays(n)
        return Trace(
            config=config, horizon_ticks=len(self.ul), ul_bpss=ul, dl_bpss=dl, frames=table
        )


class TrafficOnlyEngine(ChannelEngine):
    """A :class:`ChannelEngine` whose clock runs but that queues and serves nothing."""

    def add(self, frame: Frame) -> None:
        return None

    def run_tick(self, ul_bpss: NDArray, dl_bpss: NDArray) -> None:
        self.tick += 1
