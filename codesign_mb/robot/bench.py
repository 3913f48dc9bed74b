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

import numpy as np

__all__ = ["bench_env"]


def bench_env(*, repeats: int = 5, seed: int = 0, episodes: int = 1) -> dict[str, Any]:
    """Time ``env.step`` over ``repeats`` runs of ``episodes`` scripted episodes each.

    Returns a JSON-ready dict: ``steps_per_s`` (wall clock, median over repeats),
    ``steps_per_s_min``, ``steps_per_s_max``, the per-repeat figures, ``cpu_steps_per_s``
    (the same with the thread's CPU time, less sensitive to other processes on a shared
    machine), ``physics_only_steps_per_s`` and ``physics_only_cpu_steps_per_s`` (the same
    episode's actuator commands replayed with bare ``mj_step`` calls: the ceiling without the
    controller and the env) and the load average.
    """
    import mujoco

    from codesign_mb.control.scripted import ScriptedPickController
    from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace

    if int(repeats) < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    if int(episodes) < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    config = ConveyorConfig()
    env = ConveyorPickPlace(config)
    policy = ScriptedPickController(config)
    env.reset(seed=seed)
    env.step(np.zeros(4))  # compile the inner loop (numba) before timing
    rates: list[float] = []
    cpu_rates: list[float] = []
    for r in range(int(repeats)):
        elapsed, cpu, steps = 0.0, 0.0, 0
        for e in range(int(episodes)):
            episode_seed = seed + r * int(episodes) + e
            obs, _ = env.reset(seed=episode_seed)
            policy.reset(seed=episode_seed)
            done = False
            while not done:
                action = policy.act(obs)
                c0, t0 = time.thread_time(), time.perf_counter()
                obs, _, terminated, truncated, _ = env.step(action)
                elapsed += time.perf_counter() - t0
                cpu += time.thread_time() - c0
                steps += 1
                done = terminated or truncated
        rates.append(steps / elapsed)
        cpu_rates.append(steps / cpu)

    # Physics-only reference: replay the actuator commands of one scripted episode with
    # bare mj_step calls (the same trajectory, contacts included: MuJoCo is deterministic).
    sim = env.sim
    m, d = sim.model, sim.data
    recorded: list[np.ndarray] = []
    bare_step = sim._mj_step2  # the second half of each physics step, after the torques

    def recording_step() -> None:
        recorded.append(d.ctrl.copy())
        bare_step()

    obs, _ = env.reset(seed=seed)
    policy.reset(seed=seed)
    sim._mj_step2 = recording_step
    sim.compiled = False  # the Python loop calls _mj_step2: same torques, recorded
    try:
        done = False
        while not done:
            obs, _, terminated, truncated, _ = env.step(policy.act(obs))
            done = terminated or truncated
    finally:
        sim._mj_step2 = bare_step
        sim.compiled = True
    controls = np.array(recorded)
    env.reset(seed=seed)
    ctrl = d.ctrl
    c0, t0 = time.thread_time(), time.perf_counter()
    for u in controls:
        ctrl[:] = u
        mujoco.mj_step(m, d)
    wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
    n_steps = len(controls) / config.n_substeps
    physics, physics_cpu = n_steps / wall, n_steps / cpu
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
        "physics_only_steps_per_s": float(physics),
        "physics_only_cpu_steps_per_s": float(physics_cpu),
        "osc_model_period": config.osc_model_period,
        "seed": int(seed),
        "load_average_1min": float(os.getloadavg()[0]) if hasattr(os, "getloadavg") else None,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "mujoco": mujoco.__version__,
    }
