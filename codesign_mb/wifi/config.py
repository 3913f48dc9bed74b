"""The WiFi 6 network as one typed config, and the allocator factory."""

from __future__ import annotations

from dataclasses import dataclass, field

from codesign_mb.core import registry
from codesign_mb.wifi.allocators import Allocator, GreedyEdfAllocator
from codesign_mb.wifi.channel import ChannelConfig
from codesign_mb.wifi.convex import ConvexAllocator, ConvexAllocatorConfig
from codesign_mb.wifi.mac import MacTiming
from codesign_mb.wifi.phy import PhyConfig
from codesign_mb.wifi.traffic import TrafficConfig

__all__ = ["SCHEDULERS", "WifiConfig", "make_allocator"]

SCHEDULERS = registry.kinds("allocator")
"""Allocator kinds of the component registry."""


@dataclass(frozen=True)
class WifiConfig:
    """A WiFi 6 OFDMA cell serving robots: PHY, MAC overheads, channel, traffic, scheduler.

    Parameters
    ----------
    phy, mac, channel, traffic:
        See :class:`PhyConfig`, :class:`MacTiming`, :class:`ChannelConfig`,
        :class:`TrafficConfig`.
    scheduler:
        ``"greedy"`` (:class:`GreedyEdfAllocator`), ``"convex"`` (:class:`ConvexAllocator`,
        OSQP hot path) or ``"convex-cvxpy"`` (the same model solved through cvxpy).
    """

    phy: PhyConfig = field(default_factory=PhyConfig)
    mac: MacTiming = field(default_factory=MacTiming)
    channel: ChannelConfig = field(default_factory=ChannelConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    scheduler: str = "greedy"

    def __post_init__(self) -> None:
        if self.scheduler not in SCHEDULERS:
            raise ValueError(f"scheduler must be one of {SCHEDULERS}, got {self.scheduler!r}")
        self.traffic.period_ticks(self.mac.tick_us)  # validates period_ms against tick_us


def greedy_allocator(config: WifiConfig, n_stations: int) -> Allocator:
    """The paper's greedy earliest-deadline scheduler for the cell of ``config``."""
    return GreedyEdfAllocator(config.phy.bandwidth_mhz)


def convex_allocator(config: WifiConfig, n_stations: int, *, hot_path: bool = True) -> Allocator:
    """The convex RU allocator for ``n_stations`` (OSQP hot path, or its cvxpy model)."""
    return ConvexAllocator(
        ConvexAllocatorConfig(
            bandwidth_mhz=config.phy.bandwidth_mhz,
            n_stations=max(n_stations, 1),
            hot_path=hot_path,
        )
    )


def convex_cvxpy_allocator(config: WifiConfig, n_stations: int) -> Allocator:
    """The convex RU allocator solved through its cvxpy model (the reference path)."""
    return convex_allocator(config, n_stations, hot_path=False)


def make_allocator(config: WifiConfig, n_stations: int, scheduler: str | None = None) -> Allocator:
    """A fresh allocator of ``scheduler`` (default ``config.scheduler``) for ``n_stations``."""
    name = scheduler or config.scheduler
    if name not in SCHEDULERS:
        raise ValueError(f"scheduler must be one of {SCHEDULERS}, got {name!r}")
    allocator: Allocator = registry.create("allocator", name, config, n_stations)
    return allocator
