"""Benchmark of the full closed loop against the bare physics of the same episodes.

One step of the loop is what :func:`~codesign_mb.rollout.rollout` does per control
step: ``MpcController.act`` on the estimate, ``env.step`` through the
:class:`~codesign_mb.network.wrapper.LinkObservationWrapper` (a :class:`BernoulliLink` under a
static QoS), ``DelayCompensatingPredictor.estimate`` and the per-step record. Like
:func:`codesign_mb.bench.env.bench_env`, each timed repeat is paired with a replay of its own
actuator commands by bare ``mj_step`` calls, timed right after it under the same load; the
headline ``loop_physics_ratio`` is the loop's rate over the replay's (1 would mean everything
but the physics is free).
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import mujoco
import numpy as np

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.bench.physics import recording_controls, replay_physics
from codesign_mb.control.mpc import MpcController
from codesign_mb.estimation.predictor import DelayCompensatingPredictor
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace
from codesign_mb.rollout import rollout

__all__ = ["bench_loop"]


def _build(reliability: float, latency_steps: int) -> tuple[Any, Any, Any, Any]:
    """``(plant, wrapped env, estimator, controller)`` of the benchmarked loop."""

    plant = ConveyorPickPlace(ConveyorConfig())
    env = LinkObservationWrapper(plant, BernoulliLink(), StaticQos(reliability, latency_steps))
    controller = MpcController.from_env(plant)
    estimator = DelayCompensatingPredictor.from_env(plant)
    return plant, env, estimator, controller


@contextmanager
def _recording(plant: Any, controls: list[np.ndarray], actions: list[np.ndarray]) -> Iterator[None]:
    """Run the Python inner loop; keep every substep's ``ctrl`` and every action of the plant."""
    plant_step = plant.step

    def recording_plant_step(action: np.ndarray) -> Any:
        actions.append(np.array(action, dtype=float))
        return plant_step(action)

    plant.step = recording_plant_step
    try:
        with recording_controls(plant, controls):
            yield
    finally:
        del plant.step


def _timed(calls: dict[str, list[float]], name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` wrapped to append its thread CPU time to ``calls[name]``."""
    times = calls.setdefault(name, [])
    clock = time.thread_time

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = clock()
        out = fn(*args, **kwargs)
        times.append(clock() - t0)
        return out

    return wrapper


def _breakdown(
    plant: Any, env: Any, estimator: Any, controller: Any, seeds: list[int]
) -> dict[str, float]:
    """Mean microseconds of thread CPU time per control step of each part of the loop.

    A separate pass (CPU time: preemption by other processes on a shared machine is not
    counted).

    The env, wrapper, controller and estimator methods are timed by instance-level wrappers;
    ``wrapper_link`` is ``env.step`` through the wrapper minus the plant's ``step``, and
    ``record`` the rest of the rollout (its bookkeeping, the DataFrame, the timers' own cost).
    """

    calls: dict[str, list[float]] = {}
    patched = [
        (plant, "step", "env_step"),
        (env, "step", "wrapped_step"),
        (controller, "act", "controller_act"),
        (estimator, "estimate", "estimator_estimate"),
    ]
    for obj, method, name in patched:
        setattr(obj, method, _timed(calls, name, getattr(obj, method)))
    total = 0.0
    steps = 0
    try:
        for s in seeds:
            t0 = time.thread_time()
            steps += len(rollout(env, estimator, controller, seed=s))
            total += time.thread_time() - t0
    finally:
        for obj, method, _ in patched:
            delattr(obj, method)
    us = {k: 1e6 * sum(v) / steps for k, v in calls.items()}
    out = {
        "env_step": us["env_step"],
        "controller_act": us["controller_act"],
        "estimator_estimate": us["estimator_estimate"],
        "wrapper_link": us["wrapped_step"] - us["env_step"],
    }
    out["record"] = 1e6 * total / steps - sum(out.values())
    out["total"] = 1e6 * total / steps
    out["non_env"] = out["total"] - out["env_step"]
    return {k: round(v, 1) for k, v in out.items()}


def _repeat(
    plant: Any, env: Any, estimator: Any, controller: Any, seeds: list[int]
) -> tuple[int, float, float, float, float, float]:
    """One repeat: record, time the loop, replay the physics and the env of ``seeds``.

    Returns the steps, the loop's wall and CPU time, the bare physics' wall and CPU time
    and the bare env's wall time.
    """
    recorded, actions = [], []
    for s in seeds:
        controls: list[np.ndarray] = []
        episode_actions: list[np.ndarray] = []
        with _recording(plant, controls, episode_actions):
            rollout(env, estimator, controller, seed=s)
        recorded.append(np.array(controls))
        actions.append(episode_actions)
    wall, cpu, steps = 0.0, 0.0, 0
    for s in seeds:
        c0, t0 = time.thread_time(), time.perf_counter()
        steps += len(rollout(env, estimator, controller, seed=s))
        wall += time.perf_counter() - t0
        cpu += time.thread_time() - c0
    p_wall = p_cpu = e_wall = 0.0
    for s, controls_s in zip(seeds, recorded, strict=True):
        w, c = replay_physics(plant, s, controls_s)
        p_wall, p_cpu = p_wall + w, p_cpu + c
    for s, episode_actions in zip(seeds, actions, strict=True):
        plant.reset(seed=s)
        step = plant.step
        t0 = time.perf_counter()
        for a in episode_actions:
            step(a)
        e_wall += time.perf_counter() - t0
    n_replayed = sum(len(c) for c in recorded) / plant.config.n_substeps
    if n_replayed != steps:
        raise RuntimeError(f"recorded {n_replayed} steps but timed {steps}: not deterministic")
    return steps, wall, cpu, p_wall, p_cpu, e_wall


def bench_loop(
    *,
    repeats: int = 5,
    seed: int = 0,
    episodes: int = 1,
    reliability: float = 1.0,
    latency_steps: int = 1,
) -> dict[str, Any]:
    """Time whole :func:`rollout` calls of MPC + predictor + link against the bare physics.

    Per repeat: ``episodes`` seeded episodes are first recorded (Python inner loop, the
    substeps' actuator commands kept), then timed through the normal compiled path, then
    their commands are replayed with bare ``mj_step``. Returns a JSON-ready dict:
    ``steps_per_s`` (median over repeats), ``physics_only_steps_per_s`` (median of the
    replays), ``loop_physics_ratio`` (median over repeats of loop rate / replay rate, the
    headline), ``loop_physics_cpu_ratio`` (the same with the thread's CPU time, less
    sensitive to other processes), ``env_only_steps_per_s`` and ``env_physics_ratio`` (the
    recorded actions replayed through the bare env: the ceiling), the per-repeat figures,
    ``breakdown_us_per_step`` (mean CPU microseconds per step of ``env_step``,
    ``controller_act``, ``estimator_estimate``, ``wrapper_link``, ``record``, from a
    separate pass over the last repeat's episodes) and the load average.
    """
    if int(repeats) < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    if int(episodes) < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    plant, env, estimator, controller = _build(reliability, latency_steps)
    rollout(env, estimator, controller, seed=seed, max_steps=2)  # compile (numba), warm up
    rates: list[float] = []
    cpu_ratios: list[float] = []
    physics_rates: list[float] = []
    env_rates: list[float] = []
    steps_total = 0
    for r in range(int(repeats)):
        seeds = [seed + r * int(episodes) + e for e in range(int(episodes))]
        steps, wall, cpu, p_wall, p_cpu, e_wall = _repeat(plant, env, estimator, controller, seeds)
        rates.append(steps / wall)
        cpu_ratios.append(p_cpu / cpu)
        physics_rates.append(steps / p_wall)
        env_rates.append(steps / e_wall)
        steps_total += steps
    ratios = [e / p for e, p in zip(rates, physics_rates, strict=True)]
    env_ratios = [e / p for e, p in zip(env_rates, physics_rates, strict=True)]
    breakdown = _breakdown(plant, env, estimator, controller, seeds)
    env.close()
    return {
        "name": "loop",
        "steps_per_s": float(np.median(rates)),
        "steps_per_s_repeats": [round(float(x), 1) for x in rates],
        "physics_only_steps_per_s": float(np.median(physics_rates)),
        "physics_only_steps_per_s_repeats": [round(float(x), 1) for x in physics_rates],
        "loop_physics_ratio": float(np.median(ratios)),
        "loop_physics_ratio_repeats": [round(float(x), 3) for x in ratios],
        "loop_physics_cpu_ratio": float(np.median(cpu_ratios)),
        "loop_physics_cpu_ratio_repeats": [round(float(x), 3) for x in cpu_ratios],
        "env_only_steps_per_s": float(np.median(env_rates)),
        "env_physics_ratio": float(np.median(env_ratios)),
        "env_physics_ratio_repeats": [round(float(x), 3) for x in env_ratios],
        "breakdown_us_per_step": breakdown,
        "repeats": int(repeats),
        "episodes_per_repeat": int(episodes),
        "steps_timed": int(steps_total),
        "reliability": float(reliability),
        "latency_steps": int(latency_steps),
        "solver": controller.config.solver,
        "seed": int(seed),
        "load_average_1min": float(os.getloadavg()[0]) if hasattr(os, "getloadavg") else None,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "mujoco": mujoco.__version__,
    }
