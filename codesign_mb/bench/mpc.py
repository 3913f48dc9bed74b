"""MPC solve-time benchmark on recorded problems (``codesign bench mpc``, ``solvers/bench_mpc.py``).

The QP parameter vectors the MPC actually met are recorded from closed-loop conveyor episodes
(both belt speeds, perfect link), then replayed in episode order, each episode from a cold
solver so the warm start behaves as in closed loop. A solve's time is the whole
:meth:`~codesign_mb.control.mpc.MpcQp.solve` call: building the QP data from the parameters,
the solver, the feasibility check and the warm-start bookkeeping.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.mpc import MpcConfig, MpcController, MpcQp
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.evaluation.evaluate import episode_seeds
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace
from codesign_mb.rollout import rollout

__all__ = ["bench_mpc", "record_problems"]


def record_problems(
    *,
    seed: int = 0,
    episodes_per_speed: int = 2,
    belt_speeds_mps: tuple[float, ...] = (0.2, 0.6),
    mpc_config: Any = None,
) -> tuple[list[list[NDArray[np.float64]]], dict[str, Any]]:
    """Run seeded MPC episodes on the conveyor and record every QP parameter vector.

    Returns the per-episode lists of parameter vectors and what is needed to rebuild the QP
    (``config``, ``dt``, ``max_speed_mps``).
    """

    problems: list[list[NDArray[np.float64]]] = []
    qp_args: dict[str, Any] = {}
    seeds = episode_seeds(seed, episodes_per_speed * len(belt_speeds_mps))
    k = 0
    for speed in belt_speeds_mps:
        plant = ConveyorPickPlace(ConveyorConfig(belt_speed_mps=speed))
        env = LinkObservationWrapper(plant, BernoulliLink(), StaticQos(1.0, 0))
        controller = MpcController.from_env(plant, mpc_config)
        qp_args = {
            "config": controller.config,
            "dt": controller.control_period_s,
            "max_speed_mps": controller.max_speed_mps,
        }
        for _ in range(episodes_per_speed):
            controller.recorder = []
            rollout(env, PassThroughEstimator(), controller, seed=seeds[k])
            problems.append(controller.recorder)
            k += 1
        env.close()
    return problems, qp_args


def _time_solver(
    problems: list[list[NDArray[np.float64]]],
    qp_args: dict[str, Any],
    solver: str,
    repeats: int,
) -> dict[str, Any]:

    config = dataclasses.replace(qp_args["config"], solver=solver)
    qp = MpcQp(config, dt=qp_args["dt"], max_speed_mps=qp_args["max_speed_mps"])
    total, cpu, inner = [], [], []
    failures = 0
    for _ in range(repeats):
        for episode in problems:
            qp.reset()
            for theta in episode:
                start_cpu = time.thread_time()
                start = time.perf_counter()
                solution = qp.solve(theta)
                total.append(time.perf_counter() - start)
                cpu.append(time.thread_time() - start_cpu)
                inner.append(solution.solve_time_s)
                failures += not solution.success
    t = np.asarray(total) * 1e3
    c = np.asarray(cpu) * 1e3
    s = np.asarray(inner) * 1e3
    return {
        "solver": solver,
        "solves": int(t.size),
        "failures": int(failures),
        "median_ms": float(np.median(t)),
        "p99_ms": float(np.percentile(t, 99)),
        "max_ms": float(np.max(t)),
        "mean_ms": float(np.mean(t)),
        "cpu_median_ms": float(np.median(c)),
        "cpu_p99_ms": float(np.percentile(c, 99)),
        "solver_call_median_ms": float(np.median(s)),
        "solver_call_p99_ms": float(np.percentile(s, 99)),
    }


def bench_mpc(
    *,
    repeats: int = 20,
    seed: int = 0,
    solvers: tuple[str, ...] = ("daqp_native", "qpoases", "daqp", "osqp"),
    episodes_per_speed: int = 2,
) -> dict[str, Any]:
    """Median and p99 MPC solve time on recorded problems, per QP solver.

    Wall-clock figures (``median_ms``, ``p99_ms``) are what the control loop sees; on a shared
    machine they include preemption by other processes, so the thread's CPU time
    (``cpu_median_ms``, ``cpu_p99_ms``) and the 1-minute load average are reported too.

    Parameters
    ----------
    repeats:
        Times every recorded episode is replayed (per solver).
    seed:
        Root seed of the recorded episodes.
    solvers:
        QP solvers to time; the first is the MPC's default and gives the top-level figures.
    episodes_per_speed:
        Episodes recorded at each belt speed (0.2 and 0.6 m/s).

    Returns
    -------
    dict
        ``median_ms``, ``p99_ms``, ``max_ms`` (wall) and ``cpu_median_ms``, ``cpu_p99_ms`` of
        the default solver, the 1-minute load average, the targets
        (median <= 2 ms, p99 <= 10 ms), the number of recorded problems, and ``solvers``: the
        figures of every solver (whole solve and the solver call alone).
    """

    if isinstance(repeats, bool) or int(repeats) != repeats or repeats < 1:
        raise ValueError(f"repeats must be an integer >= 1, got {repeats!r}")
    default = MpcConfig().solver
    order = [default, *[s for s in solvers if s != default]]
    problems, qp_args = record_problems(seed=seed, episodes_per_speed=episodes_per_speed)
    results = {name: _time_solver(problems, qp_args, name, int(repeats)) for name in order}
    best = results[default]
    return {
        "benchmark": "mpc",
        "solver": default,
        "median_ms": best["median_ms"],
        "p99_ms": best["p99_ms"],
        "max_ms": best["max_ms"],
        "cpu_median_ms": best["cpu_median_ms"],
        "cpu_p99_ms": best["cpu_p99_ms"],
        "load_average_1min": _load_average(),
        "target_median_ms": 2.0,
        "target_p99_ms": 10.0,
        "meets_targets": bool(best["median_ms"] <= 2.0 and best["p99_ms"] <= 10.0),
        "problems": int(sum(len(e) for e in problems)),
        "episodes": len(problems),
        "repeats": int(repeats),
        "seed": int(seed),
        "horizon": int(qp_args["config"].horizon),
        "variables": 3 * int(qp_args["config"].horizon) + 1,
        "constraints": 11 * int(qp_args["config"].horizon),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "solvers": list(results.values()),
    }


def _load_average() -> float | None:
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):  # pragma: no cover - not on POSIX
        return None
