"""Benchmark of the conveyor env: control steps per second, single process, no rendering.

One control step is what :meth:`ConveyorPickPlace.step` does: 20 MuJoCo substeps of 2 ms,
each preceded by the Pinocchio operational-space torques, plus the observation, reward and
``info``. The actions are those of :class:`ScriptedPickController` (approach, grasp, lift:
the contacts of a real episode); only the time spent in ``env.step`` is counted.
"""

from __future__ import annotations

import os
import platform
import time
from typing import Any

import mujoco
import numpy as np

from codesign_mb.bench.physics import recording_controls, replay_physics
from codesign_mb.control.scripted import ScriptedPickController
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace

__all__ = ["bench_env"]


def _episode(
    env: ConveyorPickPlace, policy: ScriptedPickController, episode_seed: int
) -> tuple[float, float, int]:
    """One scripted episode: the wall and CPU time inside ``env.step``, and its steps."""
    obs, _ = env.reset(seed=episode_seed)
    policy.reset(seed=episode_seed)
    elapsed, cpu, steps, done = 0.0, 0.0, 0, False
    while not done:
        action = policy.act(obs)
        c0, t0 = time.thread_time(), time.perf_counter()
        obs, _, terminated, truncated, _ = env.step(action)
        elapsed += time.perf_counter() - t0
        cpu += time.thread_time() - c0
        steps += 1
        done = terminated or truncated
    return elapsed, cpu, steps


def _one_repeat(
    env: ConveyorPickPlace, policy: ScriptedPickController, seeds: list[int]
) -> tuple[float, float, float, float]:
    """Env and bare-physics rates (wall, CPU) of one repeat over the episodes of ``seeds``."""
    recorded = []
    for s in seeds:
        controls: list[np.ndarray] = []
        with recording_controls(env, controls):
            _episode(env, policy, s)
        recorded.append(np.array(controls))
    elapsed = cpu = 0.0
    steps = 0
    for s in seeds:
        e_wall, e_cpu, e_steps = _episode(env, policy, s)
        elapsed, cpu, steps = elapsed + e_wall, cpu + e_cpu, steps + e_steps
    p_wall = p_cpu = 0.0
    for s, controls in zip(seeds, recorded, strict=True):
        w, c = replay_physics(env, s, controls)
        p_wall, p_cpu = p_wall + w, p_cpu + c
    n_replayed = sum(len(c) for c in recorded) / env.config.n_substeps
    return steps / elapsed, steps / cpu, n_replayed / p_wall, n_replayed / p_cpu


def bench_env(*, repeats: int = 5, seed: int = 0, episodes: int = 1) -> dict[str, Any]:
    """Time ``env.step`` over ``repeats`` runs of ``episodes`` scripted episodes each.

    Each timed episode is paired with a replay of its own actuator commands by bare
    ``mj_step`` calls, timed right after it (the same trajectory and contacts: MuJoCo is
    deterministic): the ceiling without the controller and the env, measured under the same
    load. Returns a JSON-ready dict: ``steps_per_s`` (wall clock, median over repeats),
    ``steps_per_s_min``, ``steps_per_s_max``, the per-repeat figures, ``cpu_steps_per_s``
    (the thread's CPU time, less sensitive to other processes on a shared machine),
    ``physics_only_steps_per_s`` and ``physics_only_cpu_steps_per_s`` (medians of the
    replays), ``physics_fraction`` (median over repeats of env rate / replay rate: the
    share of a step spent in the physics, a machine-independent figure) and the load
    average.
    """
    if int(repeats) < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    if int(episodes) < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    config = ConveyorConfig()
    env = ConveyorPickPlace(config)
    policy = ScriptedPickController(config)
    env.reset(seed=seed)
    env.step(np.zeros(4))  # compile the inner loop (numba) before timing
    n = int(episodes)
    per_repeat = [
        _one_repeat(env, policy, [seed + r * n + e for e in range(n)]) for r in range(int(repeats))
    ]
    rates, cpu_rates, physics_rates, physics_cpu_rates = (
        list(x) for x in zip(*per_repeat, strict=True)
    )
    fractions = [e / p for e, p in zip(rates, physics_rates, strict=True)]
    env.close()
    return {
        "name": "env",
        "steps_per_s": float(np.median(rates)),
        "steps_per_s_min": float(np.min(rates)),
        "steps_per_s_max": float(np.max(rates)),
        "steps_per_s_repeats": [float(x) for x in rates],
        "repeats": int(repeats),
        "episodes_per_repeat": int(episodes),
        "steps_per_repeat": int(episodes) * config.horizon,
        "substeps_per_step": config.n_substeps,
        "cpu_steps_per_s": float(np.median(cpu_rates)),
        "physics_only_steps_per_s": float(np.median(physics_rates)),
        "physics_only_cpu_steps_per_s": float(np.median(physics_cpu_rates)),
        "physics_only_steps_per_s_repeats": [float(x) for x in physics_rates],
        "physics_fraction": float(np.median(fractions)),
        "physics_fraction_repeats": [round(float(x), 3) for x in fractions],
        "osc_model_period": config.osc_model_period,
        "seed": int(seed),
        "load_average_1min": float(os.getloadavg()[0]) if hasattr(os, "getloadavg") else None,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "mujoco": mujoco.__version__,
    }
