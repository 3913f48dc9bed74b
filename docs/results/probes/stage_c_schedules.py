"""Issue 30 probe: can any simple packet schedule on the learned stack's own belief reach the
target (>= 95 % success at <= 15 % requested reliability) behind the stage-A actor?

Runs hand-written QoS schedules in stage C's own env (configs/stage_c_learned_realistic.toml:
the stage-A actor behind the GRU estimator, `realistic`), on `dev` episodes (selection seeds),
reading only the policy's `belief` features (the estimated object relative to the gripper, the
finger opening). Schedules:

* `near`: q = 1 while the estimated object is within `d` m of the gripper (3-D), else 0;
* `hover`: q = 1 while the fingers close (0.045-0.077 m), `p` while they are open and the object
  is within 3 cm, `p_far` while open and farther, 0 once closed (object held).

    .venv/bin/python docs/results/probes/stage_c_schedules.py 40 \
        > docs/results/probes/stage_c_schedules.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from codesign_mb.cli.train import stage_config
from codesign_mb.stages.qos_env import evaluate_qos_agent
from codesign_mb.stages.stage_c import make_qos_env
from codesign_mb.stages.training import selection_seeds

CONFIG = Path(__file__).resolve().parents[3] / "configs" / "stage_c_learned_realistic.toml"


class Schedule:
    """A QoS schedule with SB3's ``predict`` (action in [-1, 1] -> q in [0, 1])."""

    def __init__(self, offset: int, kind: str, **knobs: float) -> None:
        self.offset, self.kind, self.knobs = offset, kind, knobs

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        f = obs[self.offset :]
        rel = f[13:16] * 0.05  # estimated object - gripper, m (BeliefFeature's scales)
        finger = f[16] * 0.08
        near = float(np.linalg.norm(rel))
        k = self.knobs
        if self.kind == "near":
            q = 1.0 if near < k["d"] and finger > 0.01 else 0.0
        elif 0.045 < finger < 0.077:
            q = 1.0
        elif finger >= 0.077:
            q = k["p"] if near < 0.03 else k["p_far"]
        else:
            q = 0.0
        return np.array([2.0 * q - 1.0], dtype=np.float32), None


def main(episodes: int) -> None:
    cfg = stage_config(
        "c", CONFIG, assignments=[], seed=None, steps=None, estimator=None, scenario="realistic"
    )
    env = make_qos_env(cfg)
    offset = env.interface.remote_dim + 1
    grid = [("near", {"d": d}) for d in (0.03, 0.06, 0.1)]
    grid += [("hover", {"p": p, "p_far": pf}) for p in (0.2, 0.4) for pf in (0.0, 0.1)]
    rows = []
    for kind, knobs in grid:
        r = evaluate_qos_agent(
            env, Schedule(offset, kind, **knobs), seeds=selection_seeds(episodes)
        )
        rows.append({"schedule": kind, **knobs, "episodes": episodes, **r})
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    print(json.dumps({"config": str(CONFIG.name), "seed_set": "dev", "rows": rows}, indent=1))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 40)
