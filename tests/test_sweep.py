"""Sweeps: strict configs, resume without recomputation, identical tables on every backend."""

from __future__ import annotations

import importlib.util
import json
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from codesign_mb.cli import sweep as sweep_cli
from codesign_mb.core.results import ResultsDir
from codesign_mb.core.seeds import episode_seeds
from codesign_mb.studies.sweep import (
    GRID_COLUMNS,
    SweepConfig,
    plan_sweep,
    run_sweep,
)

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

    with pytest.raises(KeyboardInterrupt):
        run_sweep(cfg, tmp_path / "out", backend="serial", progress=interrupt_after(7))
    assert _calls(calls) == 8  # the 8th ran but was interrupted before being stored
    assert "sweep" not in ResultsDir(tmp_path / "out")  # no table from a partial sweep

    result = run_sweep(cfg, tmp_path / "out", backend="serial")
    assert (result.computed, result.reused) == (total - 7, 7)
    assert _calls(calls) == 8 + total - 7
    # A complete sweep is not recomputed at all, on any backend.
    again = run_sweep(cfg, tmp_path / "out", backend="local", workers=2)
    assert (again.computed, again.reused) == (0, total)
    assert _calls(calls) == 8 + total - 7
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
    assert result.stderr == "error: reliability must be in [0, 1], got 1.5\n"

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
