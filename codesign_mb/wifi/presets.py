"""Named cells: the radio settings a study, a trace or a benchmark asks for by name.

Data of the radio layer (no study's knowledge in them), so that every layer above can name a
cell; the assumptions behind each are in :mod:`codesign_mb.studies.fig_wifi_config`.
"""

from __future__ import annotations

import math
from dataclasses import replace

from codesign_mb.wifi.channel import ChannelConfig
from codesign_mb.wifi.config import WifiConfig
from codesign_mb.wifi.mac import MacTiming
from codesign_mb.wifi.phy import PhyConfig

__all__ = ["CHANNEL_PRESETS"]

_PAPER_CELL = WifiConfig(
    phy=PhyConfig(guard_interval_us=3.2, ul_guard_interval_us=3.2),
    channel=ChannelConfig(fixed_mcs=1, rician_k_db=math.inf),
    mac=MacTiming(legacy_rate_mbps=6.0),
)

CHANNEL_PRESETS: dict[str, WifiConfig] = {
    "paper": _PAPER_CELL,
    "better": WifiConfig(channel=ChannelConfig(q0=0.95, distance_range_m=(5.0, 20.0))),
    "paper-scheduled": replace(_PAPER_CELL, mac=replace(_PAPER_CELL.mac, scheduled_uplink=True)),
}
"""Named cells for ``codesign wifi capacity --channels`` and ``codesign wifi trace``."""
