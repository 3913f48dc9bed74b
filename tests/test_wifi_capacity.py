"""Fig. 6 machinery: QoS rules, the capacity sweep on the real stack, LP dual prices."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy.stats import binomtest

from codesign_mb.core.records import RecordStore
from codesign_mb.core.registry import ComponentSpec
from codesign_mb.plants.scenarios import scenario_options
from codesign_mb.rollout.compose import covariance_rule_on
from codesign_mb.studies import fig_wifi
from codesign_mb.studies.fig_wifi import (
    CHANNEL_PRESETS,
    CapacityConfig,
    capacity_ratios,
    capacity_table,
    run_capacity,
    run_point,
)
from codesign_mb.studies.fig_wifi_figures import plot_capacity
from codesign_mb.studies.table_rows import PLANNER_ROW, model_based_rows
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
    with pytest.raises(ValueError, match="stop_below must be in"):
        CapacityConfig(stop_below=0.96)  # above the 95 % target: it could hide a capacity
    with pytest.raises(ValueError, match="a conveyor stack"):
        CapacityConfig(stack="toy", scenario="realistic")
    assert CapacityConfig(robots=(1, 4), channels=("paper",)).robot_episodes() == 2 * 2 * 5 * 4


def test_the_realistic_stack_is_the_tables_planner_row_on_the_realistic_scenario():
    cfg = CapacityConfig(stack="realistic")
    assert cfg.plant.name == "conveyor" and cfg.plant.options == scenario_options("realistic")
    row = next(r for r in model_based_rows() if r.name == PLANNER_ROW)
    for pipeline in cfg.pipelines.values():
        assert (pipeline.controller, pipeline.estimator) == (row.controller, row.estimator)
    assert cfg.pipelines["codesign"].qos == row.qos
    static = ComponentSpec("static", options={"reliability": 1.0, "latency_steps": 1})
    assert cfg.pipelines["static"].qos == static


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


def test_capacity_table_pools_robot_episodes_with_a_wilson_interval():
    """Per point: success over trials x N robot-episodes, its Wilson interval (scipy's, an
    independent computation), the capacity, whether it is censored and where a curve stopped."""
    rows = [
        {"channel": "paper", "scheduler": "greedy", "pipeline": p, "robots": n, "trial": k,
         "successes": s, "success_rate": s / n, "delivered_fraction": 0.1 * k}
        for p, by_n in (("static", {1: (1, 1), 4: (4, 3), 8: (2, 1)}),
                        ("codesign", {1: (1, 1), 4: (4, 4), 8: (8, 8)}))
        for n, successes in by_n.items()
        for k, s in enumerate(successes)
    ]  # fmt: skip
    table = capacity_table(pd.DataFrame(rows), stop_below=0.5).set_index(["pipeline", "robots"])
    for (pipeline, n), point in table.iterrows():
        k = sum(r["successes"] for r in rows if (r["pipeline"], r["robots"]) == (pipeline, n))
        ci = binomtest(k, 2 * n).proportion_ci(confidence_level=0.95, method="wilson")
        assert (point["successes"], point["robot_episodes"]) == (k, 2 * n)
        assert point["success_rate"] == pytest.approx(k / (2 * n))
        assert point["success_ci_low"] == pytest.approx(ci.low, abs=1e-9)
        assert point["success_ci_high"] == pytest.approx(ci.high, abs=1e-9)
        assert point["delivered_fraction"] == pytest.approx(0.05)
    static, codesign = table.loc["static"], table.loc["codesign"]
    assert static["capacity_robots"].iloc[0] == 1 and not static["capacity_censored"].iloc[0]
    assert static["stopped_at_robots"].iloc[0] == 8  # 3/16 < 50 %
    assert codesign["capacity_robots"].iloc[0] == 8 and codesign["capacity_censored"].iloc[0]
    assert math.isnan(codesign["stopped_at_robots"].iloc[0])
    # Without the successes column: round(success_rate * robots), the same table.
    legacy = pd.DataFrame(rows).drop(columns="successes")
    pd.testing.assert_frame_equal(
        capacity_table(legacy, stop_below=0.5).drop(columns="successes"),
        capacity_table(pd.DataFrame(rows), stop_below=0.5).drop(columns="successes"),
    )


def test_capacity_ratios_say_whether_the_ratio_is_a_bound():
    def curve(channel, scheduler, pipeline, capacity, censored):
        names = {"channel": channel, "scheduler": scheduler, "pipeline": pipeline}
        return {**names, "robots": 1, "capacity_robots": capacity, "capacity_censored": censored}

    curves = pd.DataFrame(
        [
            curve("paper", "greedy", "static", 6, False),
            curve("paper", "greedy", "codesign", 24, False),
            curve("paper", "convex", "static", 12, False),
            curve("paper", "convex", "codesign", 48, True),
            curve("better", "greedy", "static", 0, False),
            curve("better", "greedy", "codesign", 8, False),
        ]
    )
    ratios = capacity_ratios(curves).set_index(["channel", "scheduler"])
    assert ratios.loc[("paper", "greedy"), "ratio"] == 4.0
    assert ratios.loc[("paper", "greedy"), "bound"] == "exact"
    assert ratios.loc[("paper", "convex"), "ratio"] == 4.0
    assert ratios.loc[("paper", "convex"), "bound"] == "at least"
    assert ratios.loc[("better", "greedy"), "ratio"] == math.inf
    assert capacity_ratios(curves[curves["pipeline"] == "static"]).empty


def test_early_stop_runs_no_count_above_a_curve_below_stop_below(
    tmp_path, monkeypatch: pytest.MonkeyPatch
):
    """A curve whose mean success at a count is below ``stop_below`` runs none of its larger
    counts: the table is the full sweep's up to each curve's first such count, computed or
    reused from a store that holds the full sweep."""
    base = dict(
        robots=(1, 8, 12), channels=("paper",), schedulers=("greedy",), stack="toy", trials=2,
        max_steps=20,
    )  # fmt: skip
    store = RecordStore(tmp_path, what="trial")
    full = run_capacity(CapacityConfig(**base), store=store)
    means = full.groupby(["pipeline", "robots"])["success_rate"].mean()
    keep = []
    for pipeline in ("static", "codesign"):  # the rule, by hand
        for n in base["robots"]:
            keep.append((pipeline, n))
            if means[(pipeline, n)] < 0.5:
                break
    assert ("static", 12) not in keep  # this toy cell: static fails at 8 robots
    points = zip(full["pipeline"], full["robots"], strict=True)
    expected = full[[(p, n) in keep for p, n in points]]
    stopped_cfg = CapacityConfig(**base, stop_below=0.5)
    calls: list[tuple[str, int]] = []
    run = fig_wifi.run_point

    def counted(config, **point):
        calls.append((point["pipeline_name"], point["n_robots"]))
        return run(config, **point)

    monkeypatch.setattr(fig_wifi, "run_point", counted)
    fresh = run_capacity(stopped_cfg)
    assert sorted(set(calls)) == sorted(keep) and len(calls) == 2 * len(keep)
    reuse = RecordStore(tmp_path, what="trial")
    resumed = run_capacity(stopped_cfg, store=reuse)
    assert reuse.computed == 0 and reuse.reused == len(full)  # the rows past a stop: unused
    for table in (fresh, resumed):
        pd.testing.assert_frame_equal(
            table.reset_index(drop=True), expected.reset_index(drop=True), check_exact=True
        )
    curves = capacity_table(fresh, stop_below=0.5).drop_duplicates("pipeline")
    stopped = dict(zip(curves["pipeline"], curves["stopped_at_robots"], strict=True))
    assert stopped["static"] == 8


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


def test_capacity_not_significantly_below_the_target_reads_the_wilson_upper_bound():
    # 20 trials per point: N = 1 19/20 (95 %), N = 2 37/40 (92.5 %), N = 4 70/80 (87.5 %)
    per_trial = {1: [1] * 19 + [0], 2: [2] * 17 + [1] * 3, 4: [4] * 10 + [3] * 10}
    rows = [
        {
            "channel": "c",
            "scheduler": "greedy",
            "pipeline": p,
            "robots": n,
            "trial": t,
            "success_rate": k / n,
            "successes": k,
        }
        for p in ("codesign", "static")
        for n, ks in per_trial.items()
        for t, k in enumerate(ks)
    ]
    curves = capacity_table(pd.DataFrame(rows))
    high = {
        n: binomtest(sum(ks), n * len(ks)).proportion_ci(0.95, method="wilson").high
        for n, ks in per_trial.items()
    }
    line = curves[curves["pipeline"] == "codesign"]
    assert list(line["robot_episodes"]) == [20, 40, 80]
    assert line["capacity_robots"].iloc[0] == 1  # the mean, 92.5 %, is below 95 % at N = 2
    held = [n for n in (1, 2, 4) if all(high[m] >= 0.95 for m in (1, 2, 4) if m <= n)]
    assert high[2] >= 0.95 > high[4] and held == [1, 2]
    assert line["capacity_interval_robots"].iloc[0] == 2
    ratios = capacity_ratios(curves)
    assert set(ratios["measure"]) == {"mean", "interval"}
    assert (ratios["ratio"] == 1.0).all()


def test_capacity_table_pools_the_counted_episodes_of_continuous_operation():
    # trials whose robots ran 3 counted episodes each: N x 3 robot-episodes per trial
    rows = [
        {"channel": "paper", "scheduler": "convex", "pipeline": "codesign", "robots": 4,
         "trial": k, "successes": s, "robot_episodes": 12, "success_rate": s / 12}
        for k, s in enumerate((12, 11, 9))
    ]  # fmt: skip
    point = capacity_table(pd.DataFrame(rows)).iloc[0]
    ci = binomtest(32, 36).proportion_ci(confidence_level=0.95, method="wilson")
    assert (point["successes"], point["robot_episodes"]) == (32, 36)
    assert point["success_ci_low"] == pytest.approx(ci.low, abs=1e-9)
    assert point["success_ci_high"] == pytest.approx(ci.high, abs=1e-9)


def test_run_point_counts_each_robots_episodes_after_the_warm_up():
    cfg = CapacityConfig(
        stack="toy",
        robots=(3,),
        channels=("paper",),
        schedulers=("convex",),
        trials=1,
        episodes_per_robot=2,
        warmup_episodes=1,
    )
    assert cfg.robot_episodes() == 2 * 3 * 3  # two pipelines, 3 robots, 3 episodes each
    row = run_point(
        cfg, channel_name="paper", scheduler="convex", pipeline_name="static", n_robots=3,
        trial=0,
    )  # fmt: skip
    assert row["robot_episodes"] == 6
    assert row["success_rate"] == pytest.approx(row["successes"] / 6)
