"""MPC benchmark (``codesign bench mpc``, ``solvers/bench_mpc.py``): solve time, model error.

Solve time: the QPs the MPC actually met (parameter vectors and the arm's joint
linearisation) are recorded from closed-loop conveyor episodes (both belt speeds, perfect
link), then replayed in episode order, each episode from a cold solver so the warm start
behaves as in closed loop. A solve's time is the whole
:meth:`~codesign_mb.control.mpc.MpcQp.solve` call: building the QP data (joint-limit rows
included), the solver (which redoes its matrix setup when the joint rows change), the
feasibility check and the warm-start bookkeeping.

Model error (:func:`one_step_model_error`): in closed loop on the ``realistic`` scenario
(oracle link, delay-compensating predictor, ``dev`` seeds), the distance between the
gripper position measured after each step (MuJoCo) and the MPC model's one-step prediction
from the measured position and velocity and the command it sent.
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
from codesign_mb.control.mpc_qp_problem import lag_discretisation
from codesign_mb.core.seeds import seed_set
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.estimation.predictor import DelayCompensatingPredictor
from codesign_mb.evaluation.evaluate import episode_seeds
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace
from codesign_mb.plants.scenarios import scenario_config
from codesign_mb.rollout import rollout

__all__ = ["bench_mpc", "one_step_model_error", "record_problems"]

TARGET_MEDIAN_MS, TARGET_P99_MS = 0.5, 2.0
"""Solve-time targets of the MPC with the arm's joint limits (issue #15, item 4)."""

Problem = tuple[NDArray[np.float64], Any]
"""A recorded QP: the parameter vector and the joint linearisation (or None)."""


def record_problems(
    *,
    seed: int = 0,
    episodes_per_speed: int = 2,
    belt_speeds_mps: tuple[float, ...] = (0.2, 0.6),
    mpc_config: Any = None,
) -> tuple[list[list[Problem]], dict[str, Any]]:
    """Run seeded MPC episodes on the conveyor and record every QP it solved.

    Returns the per-episode lists of ``(theta, joints)`` and what is needed to rebuild the QP
    (``config``, ``dt``, ``max_speed_mps``, ``joint_limits``).
    """

    problems: list[list[Problem]] = []
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
            "joint_limits": controller.qp.joint_limits,
        }
        for _ in range(episodes_per_speed):
            controller.recorder = []
            rollout(env, PassThroughEstimator(), controller, seed=seeds[k])
            problems.append(controller.recorder)
            k += 1
        env.close()
    return problems, qp_args


def one_step_model_error(
    *,
    episodes: int = 10,
    seed: int | None = None,
    scenario: str = "realistic",
    mpc_config: Any = None,
) -> dict[str, Any]:
    """The MPC model's one-step position prediction error against MuJoCo, in closed loop.

    ``p[t+1] - (p[t] + bp_v v[t] + bp_u u[t])`` (:func:`lag_discretisation` of the
    controller's config) over every step of ``episodes`` episodes of ``scenario`` (oracle
    link, delay-compensating predictor; ``seed``: the ``dev`` set by default). Figures in mm
    over all steps and over the steps where the gripper moves (``|v| > 1 cm/s``), and
    ``position_blend_fit``: the least-squares ``beta`` of ``p+ - p - dt u = beta dt (v - u)``
    on the same steps (how :attr:`MpcConfig.position_blend` is identified).
    """
    seed = seed_set("dev") if seed is None else seed
    plant = ConveyorPickPlace(scenario_config(scenario))
    env = LinkObservationWrapper(plant, BernoulliLink(), StaticQos(1.0, 0))
    controller = MpcController.from_env(plant, mpc_config)
    estimator = DelayCompensatingPredictor.from_env(plant)
    cfg, dt = controller.config, controller.control_period_s
    _, bp_v, bp_u = lag_discretisation(dt, cfg.lag_time_constant_s, cfg.position_blend)
    errors, moving, fit_x, fit_y = [], [], [], []
    for episode_seed in episode_seeds(seed, episodes):
        controller.recorder = []
        rollout(env, estimator, controller, seed=episode_seed)
        theta = np.array([t for t, _ in controller.recorder])
        p, v, u = theta[:-1, 0:3], theta[:-1, 3:6], theta[1:, 6:9]  # u[t]: next step's u_prev
        error = theta[1:, 0:3] - (p + bp_v * v + bp_u * u)
        errors.append(np.linalg.norm(error, axis=1))
        moving.append(np.linalg.norm(v, axis=1) > 0.01)
        fit_x.append((dt * (v - u)).ravel())
        fit_y.append((theta[1:, 0:3] - p - dt * u).ravel())
    env.close()
    e, m = np.concatenate(errors) * 1e3, np.concatenate(moving)
    x, y = np.concatenate(fit_x), np.concatenate(fit_y)
    return {
        "scenario": scenario,
        "episodes": int(episodes),
        "steps": int(e.size),
        "position_blend": float(cfg.position_blend),
        "median_mm": float(np.median(e)),
        "p99_mm": float(np.percentile(e, 99)),
        "max_mm": float(np.max(e)),
        "moving_steps": int(m.sum()),
        "moving_median_mm": float(np.median(e[m])),
        "moving_p99_mm": float(np.percentile(e[m], 99)),
        "position_blend_fit": float(x @ y / (x @ x)),
        "target_p99_mm": 3.0,
    }


def _time_solver(
    problems: list[list[Problem]],
    qp_args: dict[str, Any],
    solver: str,
    repeats: int,
) -> dict[str, Any]:

    config = dataclasses.replace(qp_args["config"], solver=solver)
    qp = MpcQp(
        config,
        dt=qp_args["dt"],
        max_speed_mps=qp_args["max_speed_mps"],
        joint_limits=qp_args["joint_limits"],
    )
    total, cpu, inner, changed = [], [], [], []
    failures = 0
    for _ in range(repeats):
        for episode in problems:
            qp.reset()
            for theta, joints in episode:
                start_cpu = time.thread_time()
                start = time.perf_counter()
                solution = qp.solve(theta, joints)
                total.append(time.perf_counter() - start)
                cpu.append(time.thread_time() - start_cpu)
                inner.append(solution.solve_time_s)
                changed.append(qp._matrix_changed)  # the joint rows were rewritten
                failures += not solution.success
    t = np.asarray(total) * 1e3
    c = np.asarray(cpu) * 1e3
    s = np.asarray(inner) * 1e3
    rows = np.asarray(changed, dtype=bool)
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
        # Solves after a relinearisation (the solver redoes its matrix setup) and the others.
        "matrix_update_fraction": float(rows.mean()),
        "cpu_median_ms_matrix_update": float(np.median(c[rows])) if rows.any() else None,
        "cpu_median_ms_same_matrix": float(np.median(c[~rows])) if (~rows).any() else None,
    }


def bench_mpc(
    *,
    repeats: int = 20,
    seed: int = 0,
    solvers: tuple[str, ...] = ("daqp_native", "qpoases", "daqp", "osqp"),
    episodes_per_speed: int = 2,
    model_error_episodes: int = 10,
) -> dict[str, Any]:
    """Median and p99 MPC solve time on recorded problems, per QP solver; the model's error.

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
    model_error_episodes:
        Episodes of :func:`one_step_model_error` (``dev`` seeds; 0: not measured).

    Returns
    -------
    dict
        ``median_ms``, ``p99_ms``, ``max_ms`` (wall) and ``cpu_median_ms``, ``cpu_p99_ms`` of
        the default solver, the 1-minute load average, the targets (median <= 0.5 ms, p99 <=
        2 ms), the number of recorded problems and the QP's size, ``solvers``: the figures of
        every solver (whole solve and the solver call alone), and ``model_error``
        (:func:`one_step_model_error`; target p99 <= 3 mm).
    """

    if isinstance(repeats, bool) or int(repeats) != repeats or repeats < 1:
        raise ValueError(f"repeats must be an integer >= 1, got {repeats!r}")
    default = MpcConfig().solver
    order = [default, *[s for s in solvers if s != default]]
    problems, qp_args = record_problems(seed=seed, episodes_per_speed=episodes_per_speed)
    results = {name: _time_solver(problems, qp_args, name, int(repeats)) for name in order}
    best = results[default]
    qp = MpcQp(
        qp_args["config"],
        dt=qp_args["dt"],
        max_speed_mps=qp_args["max_speed_mps"],
        joint_limits=qp_args["joint_limits"],
    )
    model_error = (
        one_step_model_error(episodes=model_error_episodes) if model_error_episodes else None
    )
    return {
        "benchmark": "mpc",
        "solver": default,
        "median_ms": best["median_ms"],
        "p99_ms": best["p99_ms"],
        "max_ms": best["max_ms"],
        "cpu_median_ms": best["cpu_median_ms"],
        "cpu_p99_ms": best["cpu_p99_ms"],
        "load_average_1min": _load_average(),
        "target_median_ms": TARGET_MEDIAN_MS,
        "target_p99_ms": TARGET_P99_MS,
        "meets_targets": bool(
            best["median_ms"] <= TARGET_MEDIAN_MS and best["p99_ms"] <= TARGET_P99_MS
        ),
        "problems": int(sum(len(e) for e in problems)),
        "episodes": len(problems),
        "repeats": int(repeats),
        "seed": int(seed),
        "horizon": int(qp_args["config"].horizon),
        "variables": qp.n_var,
        "constraints": qp.n_con,
        "joint_limited_steps": list(qp.joint_steps),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "solvers": list(results.values()),
        "model_error": model_error,
    }


def _load_average() -> float | None:
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):  # pragma: no cover - not on POSIX
        return None
