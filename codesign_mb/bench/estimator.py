"""Benchmark of the estimators: CPU time per step of the learned sequence estimator vs the IMM.

A few ``realistic`` episodes are recorded once (the scripted pick behind a random link,
:func:`~codesign_mb.stages.episodes.collect_episodes`); each estimator then replays them as a
rollout calls it (``reset``, then ``estimate`` every step), and the CPU time of each call is
measured. Reported: the median per-step time of each repeat's replay (medians over repeats),
and the ratio of the learned estimator's to the belt IMM's measured in the same repeat.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.plants.scenarios import scenario_options
from codesign_mb.stages.episodes import DelayDistribution, RandomQos, collect_episodes

__all__ = ["SEQUENCE_CHECKPOINT", "bench_estimator"]

SEQUENCE_CHECKPOINT = "checkpoints/stage_b_sequence_realistic/sequence.pt"
"""The shipped learned estimator of the realistic scenario (stage B, issue 30)."""


def _per_step_s(estimator: Any, episodes: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """Median CPU seconds of one ``estimate`` call over the recorded episodes."""
    times = []
    for nets, prevs in episodes:
        estimator.reset(nets[0])
        for t in range(1, len(nets)):
            c0 = time.thread_time()
            estimator.estimate(nets[t], prevs[t])
            times.append(time.thread_time() - c0)
    return float(np.median(times))


def bench_estimator(*, repeats: int, seed: int, episodes: int = 4) -> dict[str, Any]:
    """Per-step CPU time of the sequence estimator and the belt IMM, and their ratio."""
    import torch

    torch.set_num_threads(1)  # one step of one robot: no intra-op parallelism to gain
    plant = PlantSpec("conveyor", scenario_options("realistic"))
    data = collect_episodes(
        plant,
        ComponentSpec("scripted"),
        RandomQos(DelayDistribution()),
        episodes=episodes,
        seed=seed,
    )
    recorded = [
        (n.astype(np.float64), p.astype(np.float64))
        for n, p in zip(data.networked, data.prev_actions, strict=True)
    ]
    env = make_plant(plant)
    learned = build("estimator", ComponentSpec("sequence", SEQUENCE_CHECKPOINT), env)
    imm = build("estimator", ComponentSpec("belt_imm"), env)
    rows = []
    for _ in range(repeats):
        a, b = _per_step_s(learned, recorded), _per_step_s(imm, recorded)
        rows.append((a, b, a / b))
    env.close()
    med = np.median(np.asarray(rows), axis=0)
    return {
        "steps_per_repeat": int(sum(len(n) - 1 for n, _ in recorded)),
        "sequence_step_cpu_us": round(float(med[0]) * 1e6, 1),
        "belt_imm_step_cpu_us": round(float(med[1]) * 1e6, 1),
        "sequence_over_imm": round(float(med[2]), 3),
        "checkpoint": SEQUENCE_CHECKPOINT,
    }
