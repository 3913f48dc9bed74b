"""README's paragraph on the WiFi cross-check: our cell's capacity against ns-3's.

Rendered from ``docs/results/wifi_crosscheck.json``, which ``codesign wifi crosscheck --out``
writes (not a ``codesign paper`` study: ns-3 is an optional extra and takes about an hour).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from codesign_mb.studies.readme_tables import markdown_table, pct

__all__ = ["CROSSCHECK_FILE", "crosscheck_section"]

CROSSCHECK_FILE = "wifi_crosscheck.json"
"""The cross-check's file in ``docs/results``."""

_COLUMNS = {
    "ours_greedy": "ours, greedy",
    "ours_convex": "ours, convex",
    "ns3_su": "ns-3 SU",
    "ns3_su-rts": "ns-3 SU + RTS",
    "ns3_ofdma": "ns-3 OFDMA (RR)",
}


def crosscheck_section(data: Mapping[str, Any]) -> str:
    """The table (capacity per MCS and capture, each side's set-ups, the gap) and the
    assumptions of each side."""
    rows = data.get("rows", [])
    columns = [c for c in _COLUMNS if any(c in r for r in rows)]
    table = markdown_table(
        ["MCS", "capture", *(_COLUMNS[c] for c in columns), "gap, best to best"],
        [
            [
                str(r["mcs"]),
                str(r["capture"]),
                *(str(r.get(c, "")) for c in columns),
                "" if r.get("gap") is None else f"{100.0 * float(r['gap']):+.0f} %",
            ]
            for r in rows
        ],
    )
    tolerance = float(data.get("tolerance", 0.25))
    held = sum(bool(r.get("within_tolerance")) for r in rows)
    assumptions = "\n".join(
        f"- {name.replace('ns3_', 'ns-3 ')}: {text}"
        for name, text in dict(data.get("assumptions", {})).items()
    )
    return (
        "**WiFi cell against ns-3** (`codesign wifi crosscheck --out "
        "docs/results/wifi_crosscheck.json`): capacity, the most stations of which at least "
        "95 % of the frames are delivered within their 40 ms period, each station sending a "
        "13,500 B camera frame up and receiving a 32 B state frame per period, 40 MHz, one "
        "fixed MCS, no channel errors, captures staggered over the period or synchronised. "
        f"Our best allocator against ns-3's best set-up: within {pct(tolerance)} in {held} of "
        f"{len(rows)} cells.\n\n{table}\n\n{assumptions}"
    )
