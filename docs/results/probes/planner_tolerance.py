"""Issue 34 probe: the QoS planner's tolerances scaled by k, on the `dev` seeds (selection).

Every tolerance of the planner row (grasp, far, closing; lateral RMS, m) times k, with the
gated MPC's grasp gate fixed at the shipped 12 mm or scaled with them, on the planner row's
stack (gated MPC + belt IMM). A first sweep of the knob a Pareto front of the planner would
draw; the shipped row is k = 1.

    .venv/bin/python docs/results/probes/planner_tolerance.py 100 \
        > docs/results/probes/planner_tolerance.json
"""

from __future__ import annotations

import json
import sys
import time

from codesign_mb.core.registry import ComponentSpec
from codesign_mb.core.seeds import seed_set
from codesign_mb.core.stats import wilson_interval
from codesign_mb.studies.table import TableConfig, run_table
from codesign_mb.studies.table_rows import (
    GATED_MPC_CONFIG,
    PLANNER_CLOSING_STD_M,
    PLANNER_CLOSING_USEFUL_WIDTH_M,
    PLANNER_FAR_STD_M,
    PLANNER_GRASP_STD_M,
    TableRow,
)

SCALES = (1.0, 1.5, 2.0, 3.0)
IMM = ComponentSpec("belt_imm", options={"velocity_output": "likeliest"})


def row(k: float, *, scaled_gate: bool) -> TableRow:
    """The planner row with its tolerances times ``k`` (and the MPC's gate, if scaled)."""
    mpc = dict(GATED_MPC_CONFIG)
    if scaled_gate:
        mpc["grasp_std_gate_m"] = PLANNER_GRASP_STD_M * k
    qos = ComponentSpec(
        "planner",
        options={
            "grasp_std_m": PLANNER_GRASP_STD_M * k,
            "far_std_m": PLANNER_FAR_STD_M * k,
            "closing_std_m": PLANNER_CLOSING_STD_M * k,
            "closing_useful_width_m": PLANNER_CLOSING_USEFUL_WIDTH_M,
            "lookahead": True,
        },
    )
    gate = "scaled" if scaled_gate else "fixed"
    return TableRow(
        f"k={k:g}, gate {gate}", ComponentSpec("mpc", options={"config": mpc}), IMM, qos
    )


def main(episodes: int) -> dict:
    rows = tuple(row(k, scaled_gate=g) for k in SCALES for g in (False, True) if k > 1 or not g)
    out: dict = {"episodes": episodes, "seed_set": "dev", "scenarios": {}}
    started = time.perf_counter()
    for scenario in ("realistic", "variable"):
        config = TableConfig(
            scenario=scenario,
            rows=rows,
            trials=episodes,
            seed=seed_set("dev"),
            workers=2,
            references=False,
        )
        summary, _ = run_table(config)
        out["scenarios"][scenario] = [
            {
                "row": r["row"],
                "success": r["success_rate"],
                "success_wilson": wilson_interval(int(r["successes"]), int(r["trials"])),
                "requested": r["mean_requested_reliability"],
            }
            for r in summary.to_dict("records")
        ]
    out["wall_time_s"] = round(time.perf_counter() - started, 1)
    out["command"] = f"python docs/results/probes/planner_tolerance.py {episodes}"
    return out


if __name__ == "__main__":
    print(json.dumps(main(int(sys.argv[1])), indent=1))
