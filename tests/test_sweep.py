"""Sweeps: strict configs, resume without recomputation, identical tables on every backend."""

from __future__ import annotations

import importlib.util
import json
import math
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import typer
from numpy.typing import NDArray
from typer.testing import CliRunner

from codesign_mb.cli import sweep as sweep_cli
from codesign_mb.core.results import ResultsDir
from codesign_mb.core.seeds import episode_seeds
from codesign_mb.estimation.kalman import IntermittentKalmanFilter
from codesign_mb.network import BernoulliLink, QosRequest
from codesign_mb.studies import sweep_linear
from codesign_mb.studies.sweep import (
    GRID_COLUMNS,
    SweepConfig,
    TrialConfig,
    plan_sweep,
    run_sweep,
)
from codesign_mb.studies.sweep_linear import channel_reliability

# --- a counting scenario: this module is itself a scenario (run_trial, Params, PIPELINES) ---

PIPELINES = ("a", "b")


@dataclass(frozen=True)
class Params:
    calls_dir: str = ""
    scale: float = 1.0


def run_trial(config: Any, seed: int) -> dict[str, float]:
    if config.params.calls_dir:
        Path(config.params.calls_dir, uuid.uuid4().hex).touch()
    return {"value": config.params.scale * (seed % 1000) + config.belt_speed_mps}


def _counting_config(calls: Path, **kwargs: Any) -> SweepConfig:
    return SweepConfig(
        scenario=__name__,
        n_seeds=3,
        belt_speeds_mps=(0.2, 0.6),
        robot_counts=(1, 2),
        params={"calls_dir": str(calls)},
        **kwargs,
    )


def _calls(calls: Path) -> int:
    return len(list(calls.iterdir()))


def test_interrupted_sweep_resumes_without_recomputing(tmp_path: Path) -> None:
    calls = tmp_path / "calls"
    calls.mkdir()
    cfg = _counting_config(calls)
    total = len(plan_sweep(cfg))
    assert total == 2 * 2 * 2 * 3

    def interrupt_after(k: int):
        def progress(stream: Iterator[Any], n: int) -> Iterator[Any]:
            for i, item in enumerate(stream):
                if i == k:
                    raise KeyboardInterrupt  # Ctrl-C after k trials were stored
                yield item

        return progress

    with pytest.raises(KeyboardInterrupt, match="8 finished trials kept in"):
        run_sweep(cfg, tmp_path / "out", backend="serial", progress=interrupt_after(7))
    assert _calls(calls) == 8  # the 8th was stored as it finished, then Ctrl-C came
    assert "sweep" not in ResultsDir(tmp_path / "out")  # no table from a partial sweep

    result = run_sweep(cfg, tmp_path / "out", backend="serial")
    assert (result.computed, result.reused) == (total - 8, 8)
    assert _calls(calls) == total  # no trial computed twice
    # A complete sweep is not recomputed at all, on any backend.
    again = run_sweep(cfg, tmp_path / "out", backend="local", workers=2)
    assert (again.computed, again.reused) == (0, total)
    assert _calls(calls) == total
    pd.testing.assert_frame_equal(again.table, result.table)
    # Changing a scenario parameter invalidates the stored rows.
    changed = run_sweep(
        SweepConfig(**{**cfg.__dict__, "params": {"calls_dir": str(calls), "scale": 2.0}}),
        tmp_path / "out",
        backend="serial",
    )
    assert changed.computed == total


def test_table_layout_and_seeds(tmp_path: Path) -> None:
    cfg = _counting_config(tmp_path, pipelines=("b", "a"))
    result = run_sweep(cfg, tmp_path / "out", backend="serial")
    table = ResultsDir(tmp_path / "out").table("sweep")
    assert list(table.columns) == [*GRID_COLUMNS, "value"]
    assert table["pipeline"].tolist()[:12] == ["b"] * 12  # grid order as configured
    seeds = episode_seeds(0, 3)
    assert len(set(seeds)) == 3
    # Common random numbers: replicate r has the same seed at every grid point.
    assert (table["seed"] == table["replicate"].map(dict(enumerate(seeds)))).all()
    meta = ResultsDir(tmp_path / "out").meta("sweep")
    assert meta["config"]["robot_counts"] == [1, 2]
    assert meta["extra"]["n_trials"] == result.n_trials == 24


def test_unknown_keys_rejected(tmp_path: Path) -> None:
    with pytest.raises(TypeError):
        SweepConfig(belt_speed=(0.2,))  # type: ignore[call-arg]
    with pytest.raises(ValueError, match="unknown key 'reliabilty'"):
        plan_sweep(SweepConfig(params={"reliabilty": 0.5}))
    with pytest.raises(ValueError, match="unknown pipeline 'mpc'"):
        plan_sweep(SweepConfig(pipelines=("mpc",)))
    with pytest.raises(ValueError, match="belt_speeds_mps must be >= 0"):
        SweepConfig(belt_speeds_mps=(-0.2,))
    with pytest.raises(ValueError, match="unknown scenario 'nope'"):
        plan_sweep(SweepConfig(scenario="nope"))


def _cli_app() -> typer.Typer:
    app = typer.Typer(pretty_exceptions_enable=False)
    sweep_cli.register(app)

    @app.callback()
    def _root() -> None:  # keep "sweep" a subcommand, as in the real app
        pass

    return app


def test_cli_sweep_config_file_and_errors(tmp_path: Path) -> None:
    runner = CliRunner()
    cfg = tmp_path / "sweep.toml"
    cfg.write_text(
        "[sweep]\nn_seeds = 1\nbelt_speeds_mps = [0.2]\npipelines = ['none', 'predictor']\n"
        "[sweep.params]\nhorizon_steps = 20\nreliability = 0.5\n"
    )
    out = tmp_path / "out"
    args = ["sweep", "-c", str(cfg), "-o", str(out), "--backend", "serial", "--json"]
    result = runner.invoke(_cli_app(), [*args, "--robots", "2"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["n_trials"] == summary["computed"] == 2
    assert summary["results_dir"] == str(out)
    table = ResultsDir(out).table("sweep")
    assert table["n_robots"].tolist() == [2, 2]
    assert ResultsDir(out).config("sweep")["params"] == {"horizon_steps": 20, "reliability": 0.5}
    # Rerun: everything reused.
    result = runner.invoke(_cli_app(), [*args, "--robots", "2"])
    assert json.loads(result.stdout)["reused"] == 2

    bad = tmp_path / "bad.toml"
    bad.write_text("[sweep]\nn_seed = 1\n")
    result = runner.invoke(_cli_app(), ["sweep", "-c", str(bad), "-o", str(out)])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: unknown key 'n_seed'")
    assert result.stderr.count("\n") == 1

    bad.write_text("[sweep.params]\nreliability = 1.5\n")
    result = runner.invoke(_cli_app(), ["sweep", "-c", str(bad), "-o", str(out)])
    assert result.exit_code == 2
    assert result.stderr == (
        f"error: params.reliability must be in [0, 1], got 1.5 (config file [sweep] of {bad})\n"
    )

    result = runner.invoke(_cli_app(), ["sweep", "--help"])
    assert result.exit_code == 0
    for option in ("--config", "--seed", "--json", "--backend", "--address", "m/s"):
        assert option in result.stdout


# --- backends: the same table whichever ran it -----------------------------------------

_GRID = SweepConfig(
    n_seeds=2,
    belt_speeds_mps=(0.2, 0.6),
    robot_counts=(1, 5),
    pipelines=("none", "predictor"),
    params={"horizon_steps": 30},
    seed=11,
)


@pytest.fixture(scope="module")
def ray_local() -> Iterator[None]:
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield
    finally:
        ray.shutdown()


@pytest.mark.slow  # Ray's start and Tune: ~1 min each on 2 cores
def test_local_and_ray_backends_identical(tmp_path: Path, ray_local: None) -> None:
    serial = run_sweep(_GRID, tmp_path / "serial", backend="serial").table
    local = run_sweep(_GRID, tmp_path / "local", backend="local", workers=2).table
    on_ray = run_sweep(_GRID, tmp_path / "ray", backend="ray").table
    assert len(serial) == 16
    pd.testing.assert_frame_equal(local, serial, check_exact=True)
    pd.testing.assert_frame_equal(on_ray, serial, check_exact=True)
    for name in ("local", "ray"):
        on_disk = ResultsDir(tmp_path / name).table("sweep")
        pd.testing.assert_frame_equal(on_disk, serial, check_exact=True)
    # The pipelines differ where they should: prediction helps at the faster belt.
    fast = serial[serial["belt_speed_mps"] == 0.6].groupby("pipeline")["rms_error_m"].mean()
    assert fast["predictor"] < fast["none"]


@pytest.mark.slow  # Ray's start and Tune: ~1 min each on 2 cores
def test_tune_hyperparameters(tmp_path: Path, ray_local: None) -> None:
    from ray import tune

    from codesign_mb.studies.sweep_ray import tune_hyperparameters

    def trainable(config: dict[str, Any]) -> dict[str, float]:
        return {"loss": (config["lr"] - 0.01) ** 2, "seed_seen": float(config["seed"])}

    frame = tune_hyperparameters(
        trainable,
        {"lr": tune.grid_search([0.1, 0.01, 0.001])},
        metric="loss",
        mode="min",
        seed=3,
        storage_path=tmp_path / "tune",
    )
    assert frame["config/lr"].tolist() == [0.01, 0.001, 0.1]
    assert frame["loss"].iloc[0] == 0.0
    assert "seed_seen" in frame.columns


@pytest.mark.skipif(
    importlib.util.find_spec("codesign_mb.estimation.kalman") is None, reason="needs part LINEAR"
)
def test_linear_scenario_orders_pipelines(tmp_path: Path) -> None:
    """Ground truth of the linear scenario: ideal >= model-based estimation >= stale data."""
    cfg = SweepConfig(n_seeds=4, belt_speeds_mps=(0.6,), robot_counts=(1,))
    table = run_sweep(cfg, tmp_path, backend="serial").table
    within = table.groupby("pipeline")["within_radius_fraction"].mean()
    assert set(within.index) == {"ideal", "none", "predictor", "kalman"}
    assert within["ideal"] > within["kalman"] > within["none"]
    assert within["ideal"] > within["predictor"] > within["none"]
    assert (table["mean_reliability"] == 0.8).all()


# --- the linear scenario reproduces the hand-written loop it replaced ----------------------


# The scenario's own episode loop before it ran through ``codesign_mb.rollout``, verbatim but
# for its names (``_ref_`` prefix, ``sweep_linear.Params``) and the gain's cache.


def _ref_object_matrix(dt: float) -> NDArray[np.float64]:
    return np.array([[1.0, dt], [0.0, 1.0]])


def _ref_lqr_gain(dt: float, velocity_weight: float, control_weight: float) -> NDArray[np.float64]:
    """Infinite-horizon discrete LQR gain of the double-integrator error dynamics."""
    from scipy.linalg import solve_discrete_are

    a = _ref_object_matrix(dt)
    b = np.array([[0.5 * dt * dt], [dt]])
    q = np.diag([1.0, velocity_weight])
    r = np.array([[control_weight]])
    p = solve_discrete_are(a, b, q, r)
    gain = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
    gain.setflags(write=False)
    return gain


def _reference_robot(
    params: sweep_linear.Params,
    pipeline: str,
    belt_speed_mps: float,
    n_robots: int,
    seed_seq: np.random.SeedSequence,
) -> dict[str, float]:
    plant_ss, link_ss = seed_seq.spawn(2)
    rng = np.random.default_rng(plant_ss)
    dt = params.control_period_s
    a_obj = _ref_object_matrix(dt)
    b_grip = np.array([0.5 * dt * dt, dt])
    gain = _ref_lqr_gain(dt, float(params.velocity_weight), float(params.control_weight))[0]
    q_weight = np.diag([1.0, params.velocity_weight])
    noise_std = np.array([params.measurement_noise_m, params.measurement_noise_mps])

    prior = np.array([params.start_offset_m, belt_speed_mps])
    obj = prior + np.array([rng.normal(0.0, params.start_spread_m), 0.0])
    grip = np.zeros(2)
    qos = QosRequest(channel_reliability(params, n_robots), params.latency_steps)
    link = BernoulliLink()
    link.reset(seed=int(link_ss.generate_state(1)[0]), prior=prior)
    kalman = _ref_make_kalman(params, prior) if pipeline == "kalman" else None

    errors, costs, ages, delivered = [], [], [], []
    within = 0
    for _ in range(params.horizon_steps):
        measured = obj + rng.normal(0.0, 1.0, size=2) * noise_std
        rx = link.step(measured, qos)
        if pipeline == "ideal":
            estimate = obj
        elif pipeline == "none":
            estimate = rx.observation
        elif pipeline == "predictor":
            estimate = np.linalg.matrix_power(a_obj, rx.age) @ rx.observation
        else:
            assert kalman is not None
            for packet in rx.arrivals:
                kalman.update(packet.value, packet.timestamp)
            estimate = np.asarray(kalman.x, dtype=float)
        error = grip - obj
        u = float(np.clip(-gain @ (grip - estimate), -params.max_accel_mps2, params.max_accel_mps2))
        errors.append(error[0])
        costs.append(float(error @ q_weight @ error + params.control_weight * u * u))
        ages.append(rx.age)
        delivered.append(rx.delivered)
        within += abs(error[0]) <= params.success_radius_m
        # Advance: gripper under u, object along the belt with a velocity random walk.
        grip = a_obj @ grip + b_grip * u
        obj = a_obj @ obj + np.array([0.0, rng.normal(0.0, params.velocity_noise_mps)])
        if kalman is not None:
            kalman.predict()
    final_error = float(np.mean(np.abs(errors[-params.grasp_window_steps :])))
    return {
        "success_rate": float(final_error <= params.success_radius_m),
        "within_radius_fraction": within / params.horizon_steps,
        "rms_error_m": float(np.sqrt(np.mean(np.square(errors)))),
        "final_error_m": float(final_error),
        "lqg_cost": float(np.mean(costs)),
        "mean_reliability": qos.reliability,
        "delivered_fraction": float(np.mean(delivered)),
        "mean_age_steps": float(np.mean(ages)),
    }


def _ref_make_kalman(params: sweep_linear.Params, prior: NDArray[np.float64]) -> Any:
    dt = params.control_period_s
    process = np.diag([1e-12, params.velocity_noise_mps**2])
    noise = np.diag(
        [max(params.measurement_noise_m, 1e-6) ** 2, max(params.measurement_noise_mps, 1e-6) ** 2]
    )
    kf = IntermittentKalmanFilter(
        _ref_object_matrix(dt),
        np.eye(2),
        process,
        noise,
        max_delay_steps=max(64, params.latency_steps + 1),
    )
    kf.reset(prior, np.diag([max(params.start_spread_m, 1e-6) ** 2, 1e-6]))
    return kf


def test_linear_scenario_reproduces_the_reference_loop() -> None:
    """Through the closed loop, every pipeline keeps the statistics of the old episode loop.

    50 robots each on independent seeds (the random streams are consumed differently, so the
    numbers are not bit-identical): the means agree within 4 standard errors of their
    difference. A lossy channel (q = 0.4, tau = 2) at the fast belt, where the pipelines are
    far apart (e.g. the rms error of ``none`` is about twice that of the others).
    """
    params = sweep_linear.Params(capacity_robots=0.5)  # q = 0.8 * 0.5 for a single robot
    n = 50
    metrics = (
        "success_rate",
        "within_radius_fraction",
        "rms_error_m",
        "final_error_m",
        "lqg_cost",
        "delivered_fraction",
        "mean_age_steps",
    )
    for pipeline in sweep_linear.PIPELINES:
        config = TrialConfig("linear", pipeline, 0.6, 1, 0, params)
        new = [sweep_linear.run_trial(config, seed) for seed in range(1000, 1000 + n)]
        old = [
            _reference_robot(params, pipeline, 0.6, 1, ss)
            for ss in np.random.SeedSequence(7).spawn(n)
        ]
        for metric in metrics:
            a = np.array([row[metric] for row in new])
            b = np.array([row[metric] for row in old])
            se = math.sqrt(a.var(ddof=1) / n + b.var(ddof=1) / n)
            gap = abs(a.mean() - b.mean())
            assert gap <= 4 * se + 1e-12, (pipeline, metric, a.mean(), b.mean(), se)
        assert {row["mean_reliability"] for row in new + old} == {0.4}
