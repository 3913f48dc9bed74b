"""WiFi 6 (802.11ax) OFDMA cell for N robots: PHY, MAC, channel, traffic, allocators, simulator.

paper.tex sec. 5 and 6.1; see each module for the equations (``eq_rate``, ``eq_layout``,
``eq_per``, ``eq_drop``, ``eq_deadline``, ``eq_greedy``, ``eq_admit``, ``eq_qp``, ``eq_round``,
``eq_lp``).
"""

from codesign_mb.wifi.allocators import Allocator, GreedyEdfAllocator, TickDemand
from codesign_mb.wifi.cell import SharedChannel, WifiLink, generate_trace
from codesign_mb.wifi.channel import ChannelConfig
from codesign_mb.wifi.config import WifiConfig, make_allocator
from codesign_mb.wifi.convex import ConvexAllocator, ConvexAllocatorConfig
from codesign_mb.wifi.engine import FallbackCount
from codesign_mb.wifi.mac import MacTiming
from codesign_mb.wifi.offline import AirtimePrices, OfflineResult, airtime_prices, offline_optimum
from codesign_mb.wifi.phy import PhyConfig, data_rate_mbps, ru_plan
from codesign_mb.wifi.sim import Trace, replay
from codesign_mb.wifi.traffic import TrafficConfig, drop_probability

__all__ = [
    "AirtimePrices",
    "Allocator",
    "ChannelConfig",
    "ConvexAllocator",
    "ConvexAllocatorConfig",
    "FallbackCount",
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
    "ru_plan",
]
