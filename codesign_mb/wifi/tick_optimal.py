"""The tick-optimal allocator: admission ([admit]), then the exact per-tick optimum.

It shares the convex allocator's admission (RU-size-aware) and per-tick objective
(:mod:`codesign_mb.wifi.tick_dp`), but instead of relaxing the layout problem and rounding,
it solves it exactly with the dynamic programme of :class:`~codesign_mb.wifi.tick_dp.TickDp`
(the tests check its value equals HiGHS's optimum of the MILP in
:mod:`codesign_mb.wifi.tick_milp`); spectrum left over goes towards the whole backlog,
admitted frames first, then the rejected ones, each in deadline order. No solver, so no
fallback.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from codesign_mb.wifi.allocators import TickDemand
from codesign_mb.wifi.convex import _TickAllocator
from codesign_mb.wifi.phy import ru_plan

if TYPE_CHECKING:
    from codesign_mb.wifi.config import WifiConfig

__all__ = ["TickOptimalAllocator", "TickOptimalConfig", "tick_optimal_allocator"]


@dataclass(frozen=True)
class TickOptimalConfig:
    """Settings of :class:`TickOptimalAllocator` (the meaning of each is the one of
    :class:`~codesign_mb.wifi.convex.ConvexAllocatorConfig`)."""

    bandwidth_mhz: int = 40
    n_stations: int = 24
    surplus_weight: float = 0.05
    surplus_decay: float = 0.2
    admission: bool = True
    admission_capacity: float = 0.95

    def __post_init__(self) -> None:
        ru_plan(self.bandwidth_mhz)  # validates bandwidth_mhz
        if isinstance(self.n_stations, bool) or not isinstance(self.n_stations, int):
            raise ValueError(f"n_stations must be an integer, got {self.n_stations!r}")
        if self.n_stations < 1:
            raise ValueError(f"n_stations must be >= 1, got {self.n_stations}")
        for name in ("surplus_weight", "surplus_decay", "admission_capacity"):
            value = getattr(self, name)
            top = 1.0 if name == "admission_capacity" else 1.0 - 1e-12
            if not (isinstance(value, int | float) and math.isfinite(value) and 0 < value <= top):
                raise ValueError(f"{name} must be in (0, {top:g}], got {value!r}")
        if not isinstance(self.admission, bool):
            raise ValueError(f"admission must be true or false, got {self.admission!r}")


class TickOptimalAllocator(_TickAllocator):
    """Admission control ([admit], RU-size-aware), then the layout that maximises the
    per-tick objective exactly (:class:`~codesign_mb.wifi.tick_dp.TickDp`)."""

    def __init__(self, config: TickOptimalConfig | None = None) -> None:
        self.config = config or TickOptimalConfig()
        self._setup()

    def allocate(self, demand: TickDemand) -> NDArray[np.int64]:
        return self._layout(self._tick(demand), None)


def tick_optimal_allocator(config: WifiConfig, n_stations: int) -> TickOptimalAllocator:
    """The tick-optimal allocator for the cell of ``config`` (registry kind ``tick-optimal``)."""
    return TickOptimalAllocator(
        TickOptimalConfig(bandwidth_mhz=config.phy.bandwidth_mhz, n_stations=max(n_stations, 1))
    )
