"""The ``conveyor`` sweep scenario: MuJoCo pick-and-place trials in a sweep grid."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from codesign_mb.cli import sweep as sweep_cli
from codesign_mb.core.results import ResultsDir
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.qos import QosRequest
from codesign_mb.studies import sweep_conveyor as conveyor
from codesign_mb.studies.sweep import GRID_COLUMNS, SweepConfig, plan_sweep, run_sweep
from codesign_mb.studies.table_rows import all_rows, model_based_rows, model_free_rows
from codesign_mb.studies.tuned import TUNED

TIMING = list(conveyor.TIMING_COLUMNS)

# 2 seeds x 1 belt speed x 2 robot counts of MPC + predictor; 40 steps (success at ~30).
_GRID = SweepConfig(
    scenario="conveyor",
    n_seeds=2,
    belt_speeds_mps=(0.6,),
    robot_counts=(1, 8),
    pipelines=("model-based-static",),
    params={"horizon": 40},
    seed=5,
)


@pytest.fixture(scope="module")
def serial_table(tmp_path_factory: pytest.TempPathFactory) -> pd.DataFrame:
    return run_sweep(_GRID, tmp_path_factory.mktemp("serial"), backend="serial").table


def test_pipelines_are_table_rows() -> None:
    rows = (*model_free_rows(), *model_based_rows(), *all_rows())
    assert set(conveyor.DEFAULT_PIPELINES) <= set(conveyor.PIPELINES)
    named = set(conveyor.PIPELINE_ROW_NAMES.values())
    for name in conveyor.PIPELINES:
        kinds = conveyor.PIPELINE_KINDS[name]
        if name in conveyor.PIPELINE_ROW_NAMES:  # picked by name: the row has its kinds
            assert conveyor.pipeline_row(name).name == conveyor.PIPELINE_ROW_NAMES[name]
            continue
        matches = [
            (r.controller, r.estimator, r.qos)
            for r in rows
            if (r.controller.kind, r.estimator.kind, r.qos.kind) == kinds and r.name not in named
        ]
        row = conveyor.pipeline_row(name)
        assert all(m == (row.controller, row.estimator, row.qos) for m in matches), (
            f"{name}: table rows with kinds {kinds} differ"
        )
    rule = conveyor.pipeline_row("model-based-rule")
    assert rule.qos.options["threshold_m"] == TUNED  # resolved for the plant by run_trial
    static = conveyor.pipeline_row("model-free-static")
    assert static.qos.options["reliability"] == 1.0
    assert conveyor.pipeline_row("model-free-codesign").qos.checkpoint == (
        "checkpoints/stage_d_model_free_lstm/qos"
    )
    assert conveyor.pipeline_row("hybrid-codesign").qos.checkpoint == "checkpoints/stage_d/qos"


def test_conveyor_grid_serial(serial_table: pd.DataFrame) -> None:
    table = serial_table
    assert len(table) == 4
    assert list(table.columns[: len(GRID_COLUMNS)]) == list(GRID_COLUMNS)
    assert table["success_rate"].between(0.0, 1.0).all()
    assert (table["steps"] == 40).all()
    assert (table["episodes"] == 1).all()
    assert (table["mean_reliability"] == 1.0).all()  # static QoS asks q = 1 always
    assert (table["cpu_time_s"] > 0).all()
    assert table["mpc_solve_cpu_ms_median"].notna().all()
    # The capacity share: 6 robots served in full, 8 get 6/8 of what they ask for.
    share = dict(zip(table["n_robots"], table["channel_share"], strict=False))
    assert share == {1: 1.0, 8: 0.75}
    alone = table[table["n_robots"] == 1]
    assert (alone["delivered_fraction"] == 1.0).all()
    crowded = table[table["n_robots"] == 8]
    assert (crowded["delivered_fraction"] < 1.0).all()


def test_serial_and_local_backends_identical(serial_table: pd.DataFrame, tmp_path: Path) -> None:
    local = run_sweep(_GRID, tmp_path, backend="local", workers=2).table
    pd.testing.assert_frame_equal(
        local.drop(columns=TIMING), serial_table.drop(columns=TIMING), check_exact=True
    )


def test_shared_link_delivers_the_share() -> None:
    # share = 1 is the paper's link, draw for draw.
    plain, shared = BernoulliLink(), conveyor.SharedBernoulliLink(1.0)
    plain.reset(seed=3, prior=[0.0])
    shared.reset(seed=3, prior=[0.0])
    qos = QosRequest(0.7, 1)
    for t in range(200):
        a, b = plain.step([t], qos), shared.step([t], qos)
        assert (a.delivered, a.age) == (b.delivered, b.age)
    link = conveyor.SharedBernoulliLink(0.5)
    link.reset(seed=0, prior=[0.0])
    delivered = np.mean([link.step([0.0], qos).delivered for _ in range(20_000)])
    assert abs(delivered - 0.35) < 0.015  # q * share, ~4.5 sigma
    with pytest.raises(ValueError, match="share must be in"):
        conveyor.SharedBernoulliLink(1.5)


def test_unknown_params_rejected() -> None:
    with pytest.raises(ValueError, match="unknown key 'horizn'"):
        plan_sweep(SweepConfig(scenario="conveyor", params={"horizn": 40}))
    with pytest.raises(ValueError, match=r"unknown key 'objct' in params\.plant_options"):
        plan_sweep(SweepConfig(scenario="conveyor", params={"plant_options": {"objct": "x"}}))
    with pytest.raises(ValueError, match="plant_options must not set 'belt_speed_mps'"):
        conveyor.Params(plant_options={"belt_speed_mps": 0.2})
    with pytest.raises(ValueError, match="belt_profile must be one of constant, variable"):
        conveyor.Params(belt_profile="wavy")
    with pytest.raises(ValueError, match="link must be one of bernoulli, wifi"):
        conveyor.Params(link="5g")
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        conveyor.Params(episodes=0)
    with pytest.raises(ValueError, match="unknown pipeline 'mpc'"):
        plan_sweep(SweepConfig(scenario="conveyor", pipelines=("mpc",)))
    trials = plan_sweep(SweepConfig(scenario="conveyor", params={"belt_profile": "variable"}))
    assert {t.pipeline for t, _ in trials} == set(conveyor.DEFAULT_PIPELINES)
    assert trials[0][0].params.plant_options_at(0.6) == {
        "belt_speed_mps": 0.6,
        "belt_profile": "variable",
    }


@pytest.fixture
def no_checkpoints(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """No checkpoint anywhere: an empty working directory and an empty models folder."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("codesign_mb.core.registry.models_dir", lambda: tmp_path)
    yield tmp_path


def _cli_app() -> typer.Typer:
    app = typer.Typer(pretty_exceptions_enable=False)
    sweep_cli.register(app)

    @app.callback()
    def _root() -> None:
        pass

    return app


def test_missing_checkpoint_is_a_readable_error(no_checkpoints: Path) -> None:
    cfg = SweepConfig(
        scenario="conveyor",
        n_seeds=1,
        belt_speeds_mps=(0.2,),
        pipelines=("model-free-codesign",),
        params={"horizon": 5},
    )
    with pytest.raises(
        ValueError,
        match=r"pipeline 'model-free-codesign' \(.+\): "
        r"checkpoint 'checkpoints/stage_a/model.zip' not found",
    ):
        run_sweep(cfg, no_checkpoints / "out", backend="serial")
    args = ["sweep", "--scenario", "conveyor", "-p", "model-free-static", "--seeds", "1"]
    result = CliRunner().invoke(_cli_app(), [*args, "-o", "out", "--backend", "serial"])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: pipeline 'model-free-static'")
    assert "checkpoint" in result.stderr and "train it with `codesign train`" in result.stderr
    assert result.stderr.count("\n") == 1


def test_cli_conveyor_params_and_wifi_link(tmp_path: Path) -> None:
    """--param reaches the scenario; the WiFi link runs n robots in lockstep on one cell."""
    args = ["sweep", "--scenario", "conveyor", "-p", "model-based-static", "-v", "0.6"]
    args += ["--robots", "2", "--seeds", "1", "--param", "horizon=30", "--param", "link=wifi"]
    args += ["-o", str(tmp_path), "--backend", "serial", "--json"]
    result = CliRunner().invoke(_cli_app(), args)
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["computed"] == 1
    assert ResultsDir(tmp_path).config("sweep")["params"] == {"horizon": 30, "link": "wifi"}
    row = ResultsDir(tmp_path).table("sweep").iloc[0]
    assert row["success_rate"] in (0.0, 0.5, 1.0)  # one episode of two robots
    assert row["mean_reliability"] == 1.0
    assert 0.0 < row["delivered_fraction"] <= 1.0
    assert np.isnan(row["channel_share"])


@pytest.mark.slow
def test_ray_backend_identical(serial_table: pd.DataFrame, tmp_path: Path) -> None:
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = run_sweep(_GRID, tmp_path, backend="ray").table
    finally:
        ray.shutdown()
    pd.testing.assert_frame_equal(
        on_ray.drop(columns=TIMING), serial_table.drop(columns=TIMING), check_exact=True
    )
