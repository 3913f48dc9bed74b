"""Fig. 6 machinery: QoS rules, the capacity sweep on the real stack, LP dual prices."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from codesign_mb.rollout.compose import covariance_rule_on
from codesign_mb.studies.fig_wifi import (
    CHANNEL_PRESETS,
    CapacityConfig,
    capacity_table,
    run_capacity,
)
from codesign_mb.studies.fig_wifi_figures import plot_capacity
from codesign_mb.wifi import WifiConfig, generate_trace
from codesign_mb.wifi.offline import airtime_prices

LAYOUT = {"object_pos": slice(0, 3), "object_vel": slice(3, 6)}


def _state(t: int, z: float = 0.08) -> np.ndarray:
    return np.array([0.5, -0.45 + 0.2 * 0.04 * t, z, 0.0, 0.2, 0.0])


def test_covariance_rule_asks_when_the_prediction_drifts():
    rule = covariance_rule_on(LAYOUT, 0.04, threshold_m=0.01, low=0.2)
    rule.reset(seed=0)
    asked = [rule.request(_state(0), 0).reliability]  # t = 0: only the prior is held
    for t in range(1, 10):  # a fresh state every step (age 1)
        asked.append(rule.request(_state(max(t - 2, 0)), 1).reliability)
    assert asked[0] == 1.0 and asked[-5:] == [0.2] * 5
    stds, asked = [], []
    for k in range(1, 12):  # nothing new arrives: the held state ages
        asked.append(rule.request(_state(7), 9 + k - 1 - 7).reliability)
        stds.append(rule.position_std_ahead(2))
    assert np.all(np.diff(stds) > 0)
    assert asked[0] == 0.2 and asked[-1] == 1.0
    assert all(q == (1.0 if s > 0.01 else 0.2) for q, s in zip(asked, stds, strict=True))


def test_covariance_rule_goes_low_once_the_object_is_lifted():
    rule = covariance_rule_on(LAYOUT, 0.04, threshold_m=1e-6, low=0.1)
    rule.reset()
    rule.request(_state(0), 0)
    assert rule.request(_state(0), 1).reliability == 1.0  # tiny threshold: always high
    assert rule.request(_state(1, z=0.2), 1).reliability == 0.1  # lifted: low for good
    assert rule.request(_state(2), 1).reliability == 0.1
    with pytest.raises(ValueError, match="threshold_m"):
        covariance_rule_on(LAYOUT, 0.04, threshold_m=0.0)


def test_capacity_config_validates_and_picks_the_stack():
    cfg = CapacityConfig(robots_by_channel={"better": [8, 16]})
    assert cfg.plant.name == "conveyor" and set(cfg.pipelines) == {"static", "codesign"}
    assert cfg.pipelines["codesign"].qos.kind == "covariance_triggered"
    assert cfg.robots_of("better") == (8, 16) and cfg.robots_of("paper") == cfg.robots
    toy = CapacityConfig(stack="toy")
    assert toy.plant.name == "toy" and toy.pipelines["codesign"].qos.kind == "age_triggered"
    with pytest.raises(ValueError, match="stack must be one of"):
        CapacityConfig(stack="mujoco")
    with pytest.raises(ValueError, match="robots_by_channel"):
        CapacityConfig(robots_by_channel={"better": [0]})
    with pytest.raises(ValueError, match="workers"):
        CapacityConfig(workers=0)


def test_capacity_runs_the_conveyor_with_mpc_predictor_and_both_qos(tmp_path):
    """The real stack: MuJoCo conveyor, MPC, delay-compensating predictor, static/rule QoS."""
    pytest.importorskip("mujoco")
    cfg = CapacityConfig(
        robots=(2,), channels=("paper",), schedulers=("convex",), trials=1, max_steps=4
    )
    results = run_capacity(cfg)
    assert list(results["pipeline"]) == ["static", "codesign"]
    assert (results["robots"] == 2).all() and results["success_rate"].between(0, 1).all()
    static, codesign = results["mean_reliability"]
    assert static == 1.0 and codesign < 1.0  # the rule asks for less once it holds a state
    png = plot_capacity(results, tmp_path / "fig.png")
    assert png.stat().st_size > 1000
    table = capacity_table(results)
    assert set(table.columns) >= {"success_rate", "capacity_robots", "trials"}
    assert results["mpc_failures"].ge(0).all()  # the MPC's failed solves, per trial
    assert table["mpc_failures"].sum() == results["mpc_failures"].sum()
    assert (results["allocator_fallbacks"] == 0).all()  # healthy convex QPs: none, and counted
    assert table["allocator_fallbacks"].sum() == 0


def test_capacity_table_sums_mpc_failures_over_trials():
    results = pd.DataFrame(
        [
            {"channel": "paper", "scheduler": "greedy", "pipeline": p, "robots": 2, "trial": k,
             "success_rate": 1.0, "mpc_failures": f}
            for p, failures in (("mpc", (1, 2)), ("toy", (np.nan, np.nan)))
            for k, f in enumerate(failures)
        ]
    )  # fmt: skip
    table = capacity_table(results).set_index("pipeline")
    assert table.loc["mpc", "mpc_failures"] == 3 and table.loc["mpc", "trials"] == 2
    assert np.isnan(table.loc["toy", "mpc_failures"])  # no MPC in that pipeline
    assert np.isnan(table.loc["mpc", "mean_reliability"])  # not in the results


@pytest.mark.slow
def test_capacity_table_does_not_depend_on_workers():
    cfg = dict(robots=(1, 3), channels=("paper",), stack="toy", trials=2, max_steps=6)
    serial = run_capacity(CapacityConfig(**cfg))
    parallel = run_capacity(CapacityConfig(**cfg, workers=2))
    assert serial.equals(parallel)


def test_airtime_prices_separate_the_frames_the_optimum_sends():
    light = generate_trace(WifiConfig(), 3, steps=2, seed=0)
    assert airtime_prices(light).ticks["ul_price"].abs().max() < 1e-9  # spare airtime: free
    trace = generate_trace(CHANNEL_PRESETS["better"], 60, steps=2, seed=1)  # congested
    prices = airtime_prices(trace)
    f = prices.frames
    assert prices.optimum == pytest.approx(f["delivered"].sum(), abs=1e-6)
    assert prices.ticks["ul_price"].max() > 0
    # LP duality: a frame whose cheapest airtime costs more than the frame is worth is dropped
    assert (f["ul_bill"] > 1 + 1e-6).any()
    assert (f.loc[f["ul_bill"] > 1 + 1e-6, "delivered"] < 1e-6).all()
    assert (f.loc[f["delivered"] > 1 - 1e-6, "ul_bill"] <= 1 + 1e-6).all()
