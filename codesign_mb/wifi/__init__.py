"""WiFi 6 (802.11ax) OFDMA cell for N robots: PHY, MAC, channel, traffic, allocators, simulator.

paper.tex sec. 5 (``sec_scheduling``, ``eq_drop``) and 6.1 (``sec_wifi``). The equations this
package adds, which paper.tex does not number, are named in brackets and written out in the
module that implements them: [rate] and [layout] (:mod:`~codesign_mb.wifi.phy`), [per] and
[snr] (:mod:`~codesign_mb.wifi.channel`), [deadline] (:mod:`~codesign_mb.wifi.traffic`),
[air_ul], [air_dl] and [serve] (:mod:`~codesign_mb.wifi.mac`, :mod:`~codesign_mb.wifi.engine`),
[greedy] (the paper's greedy scheduler of ``sec_scheduling``, :mod:`~codesign_mb.wifi.allocators`),
[admit] (:mod:`~codesign_mb.wifi.admission`), [qp] and [round]
(:mod:`~codesign_mb.wifi.convex_qp`, :mod:`~codesign_mb.wifi.convex`), [lp]
(:mod:`~codesign_mb.wifi.offline`). Labels of the form ``eq_*`` are paper.tex's own.
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
