"""Issue 34: the clairvoyant schedule of every episode of the QoS planner's row.

For each episode of the row (``test`` seeds, as the tables), the planner's own requests and
outcome, and the 1-minimal clairvoyant schedule found from them by replay
(:mod:`codesign_mb.evaluation.clairvoyant`): how many of its packets the episode needed.

    .venv/bin/python docs/results/clairvoyant/run.py realistic 200 2 \
        > docs/results/clairvoyant/realistic.json
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from codesign_mb.core.registry import PlantSpec
from codesign_mb.core.seeds import episode_seeds, seed_set
from codesign_mb.core.stats import wilson_interval
from codesign_mb.evaluation.clairvoyant import clairvoyant_episodes
from codesign_mb.plants.scenarios import scenario_options
from codesign_mb.stages.training import git_commit
from codesign_mb.studies.table_rows import PLANNER_ROW, model_based_rows


def main(scenario: str, episodes: int, workers: int) -> dict:
    row = next(r for r in model_based_rows(scenario) if r.name == PLANNER_ROW)
    plant = PlantSpec("conveyor", scenario_options(scenario))
    seeds = episode_seeds(seed_set("test"), episodes)
    started = time.perf_counter()
    results = sorted(
        clairvoyant_episodes(plant, row.controller, row.estimator, row.qos, seeds, workers=workers),
        key=lambda r: seeds.index(r.seed),
    )
    n = len(results)
    planner_ok = sum(r.policy_success for r in results)
    bound_ok = sum(r.success for r in results)
    found = [r for r in results if r.steps is not None]
    both = [r for r in results if r.policy_success]
    summary = {
        "episodes": n,
        "planner_success": planner_ok / n,
        "planner_success_wilson": wilson_interval(planner_ok, n),
        "planner_requested": float(np.mean([r.policy_requested for r in results])),
        "planner_packets": float(np.mean([len(r.policy_steps) for r in results])),
        "clairvoyant_success": bound_ok / n,
        "clairvoyant_success_wilson": wilson_interval(bound_ok, n),
        "clairvoyant_requested": float(np.mean([r.requested for r in found])),
        "clairvoyant_packets": float(np.mean([len(r.steps) for r in found])),
        "starts": {s: sum(r.start == s for r in results) for s in ("policy", "static", "none")},
        "ratio_on_planner_successes": float(
            np.mean([r.policy_requested for r in both]) / np.mean([r.requested for r in both])
        ),
        "replays_per_episode": float(np.mean([r.replays for r in results])),
    }
    return {
        "what": "the QoS planner's requests per episode and the 1-minimal clairvoyant "
        "schedule found from them by replay (an achievable schedule: the fewest packets the "
        "episode needs are at most this)",
        "scenario": scenario,
        "row": PLANNER_ROW,
        "seed_set": "test",
        "command": "python docs/results/clairvoyant/run.py " + " ".join(sys.argv[1:]),
        "git_commit": git_commit(),
        "wall_time_s": time.perf_counter() - started,
        "summary": summary,
        "episodes": [
            {
                "seed": r.seed,
                "planner_steps": list(r.policy_steps),
                "planner_success": r.policy_success,
                "planner_requested": r.policy_requested,
                "start": r.start,
                "clairvoyant_steps": None if r.steps is None else list(r.steps),
                "clairvoyant_success": r.success,
                "clairvoyant_requested": r.requested,
                "replays": r.replays,
            }
            for r in results
        ],
    }


if __name__ == "__main__":
    scenario, episodes, workers = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    print(json.dumps(main(scenario, episodes, workers), indent=1, allow_nan=True))
