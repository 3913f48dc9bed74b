"""WiFi 6 (802.11ax) OFDMA cell for N robots: PHY, channel, traffic, allocators, simulator.

paper.tex sec. 5 and 6.1; see each module for the equations (``eq_rate``, ``eq_layout``,
``eq_per``, ``eq_drop``, ``eq_deadline``, ``eq_greedy``, ``eq_admit``, ``eq_qp``, ``eq_round``,
``eq_lp``).
"""

from codesign_mb.adaptation.rules import AgeTriggeredQos, CovarianceTriggeredQos
from codesign_mb.wifi.allocators import (
    Allocator,
    ConvexAllocator,
    ConvexAllocatorConfig,
    GreedyEdfAllocator,
    TickDemand,
)
from codesign_mb.wifi.cell import SharedChannel, WifiLink, generate_trace, rollout_shared
from codesign_mb.wifi.channel import ChannelConfig
from codesign_mb.wifi.config import WifiConfig, make_allocator
from codesign_mb.wifi.offline import AirtimePrices, OfflineResult, airtime_prices, offline_optimum
from codesign_mb.wifi.phy import MacTiming, PhyConfig, data_rate_mbps, ru_plan
from codesign_mb.wifi.sim import Trace, replay
from codesign_mb.wifi.traffic import TrafficConfig, drop_probability

__all__ = [
    "AgeTriggeredQos",
    "AirtimePrices",
    "Allocator",
    "ChannelConfig",
    "ConvexAllocator",
    "ConvexAllocatorConfig",
    "CovarianceTriggeredQos",
    "GreedyEdfAllocator",
    "MacTiming",
    "OfflineResult",
    "PhyConfig",
    "SharedChannel",
    "TickDemand",
    "Trace",
    "TrafficConfig",
    "WifiConfig",
    "WifiLink",
    "airtime_prices",
    "data_rate_mbps",
    "drop_probability",
    "generate_trace",
    "make_allocator",
    "offline_optimum",
    "replay",
    "rollout_shared",
    "ru_plan",
]
