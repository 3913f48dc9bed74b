"""The evaluation harness: seeded episodes in parallel, same table for the same seed, Wilson."""

from __future__ import annotations

import math
import pickle

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.core import registry
from codesign_mb.core.registry import ComponentSpec, Factory
from codesign_mb.core.seeds import episode_seeds
from codesign_mb.core.stats import wilson_interval
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.evaluation.evaluate import TIMING_COLUMNS, evaluate, summarize


class CatchEnv(gym.Env):
    """A tiny networked plant: a point must catch an object drifting at a random speed.

    Observation ``(gripper, object)``; the object is remote. Success: within 2 cm.
    """

    control_period_s = 0.04
    horizon = 40
    remote_slice = slice(1, 2)

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float64)

    def remote_prior(self) -> np.ndarray:
        return np.array([0.5])

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._g = 0.0
        self._o = 0.3 + 0.4 * self.np_random.random()
        self._w = self.np_random.uniform(-0.5, 0.5)
        self._t = 0
        return np.array([self._g, self._o]), {}

    def step(self, action):
        self._g += 0.04 * float(np.clip(action[0], -1, 1))
        self._o += 0.04 * self._w + 0.002 * self.np_random.standard_normal()
        self._t += 1
        success = abs(self._g - self._o) < 0.02
        obs = np.array([self._g, self._o])
        return obs, float(success), bool(success), self._t >= self.horizon, {"success": success}


def make_catch_env() -> CatchEnv:
    return CatchEnv()


class ProportionalController:
    def reset(self, *, seed=None) -> None:
        self.calls = 0

    def act(self, observation):
        self.calls += 1
        return np.array([np.clip(8.0 * (observation[1] - observation[0]), -1, 1)])

    def episode_metrics(self) -> dict[str, float]:
        return {"controller_calls": float(self.calls)}


class CrashOnceController(ProportionalController):
    """Kills its worker process the first time it runs (a marker file remembers)."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def act(self, observation):
        import os

        if not os.path.exists(self.marker):
            with open(self.marker, "w") as fh:
                fh.write("crashed")
            os._exit(1)
        return super().act(observation)


def _table(workers: int, seed: int = 3, trials: int = 6) -> pd.DataFrame:
    return evaluate(
        ProportionalController(),
        PassThroughEstimator,
        StaticQos(reliability=0.6, latency_steps=1),
        make_catch_env,
        trials,
        seed,
        workers=workers,
    )


def test_wilson_interval_known_values() -> None:
    low, high = wilson_interval(8, 10)
    assert low == pytest.approx(0.4902, abs=1e-4)
    assert high == pytest.approx(0.9433, abs=1e-4)
    # k = n: the lower end is n / (n + z^2)
    low, high = wilson_interval(100, 100)
    assert high == 1.0
    assert low == pytest.approx(100 / (100 + 1.959963985**2), abs=1e-9)
    low, high = wilson_interval(0, 20, confidence=0.9)
    assert low == 0.0 and 0.0 < high < 0.2
    with pytest.raises(ValueError, match="k must be"):
        wilson_interval(11, 10)
    with pytest.raises(ValueError, match="confidence"):
        wilson_interval(1, 10, confidence=1.0)


def test_episode_seeds_are_spawned_and_stable() -> None:
    seeds = episode_seeds(7, 5)
    assert seeds == episode_seeds(7, 5)
    assert len(set(seeds)) == 5
    assert episode_seeds(7, 6)[:5] == seeds  # spawning more keeps the first ones
    expected = int(np.random.SeedSequence(7).spawn(5)[2].generate_state(1, dtype=np.uint32)[0])
    assert seeds[2] == expected
    with pytest.raises(ValueError, match="trials"):
        episode_seeds(0, 0)


def test_same_seed_same_table_in_process() -> None:
    a = _table(workers=1)
    b = _table(workers=1)
    keep = [c for c in a.columns if c not in TIMING_COLUMNS]
    pd.testing.assert_frame_equal(a[keep], b[keep])
    assert list(a["episode"]) == list(range(6))
    assert (a["controller_calls"] == a["steps"]).all()
    c = _table(workers=1, seed=4)
    assert not a[keep].equals(c[keep])


def test_same_table_for_any_worker_count() -> None:
    one = _table(workers=1)
    two = _table(workers=2)
    keep = [c for c in one.columns if c not in TIMING_COLUMNS]
    pd.testing.assert_frame_equal(one[keep], two[keep])


def test_table_columns_and_summary() -> None:
    table = _table(workers=1, trials=8)
    for column in (
        "success",
        "mean_requested_reliability",
        "delivered_fraction",
        "mean_age",
        "max_age",
        "mean_estimation_error",
        "wall_time_s",
    ):
        assert column in table
    assert np.allclose(table["mean_requested_reliability"], 0.6)
    assert (table["mean_age"] >= 1.0).all()  # latency 1: never fresher than one step
    s = summarize(table)
    k = int(table["success"].sum())
    assert s["successes"] == k and s["trials"] == 8
    assert (s["success_ci_low"], s["success_ci_high"]) == wilson_interval(k, 8)


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ValueError, match="workers"):
        _table(workers=0)
    with pytest.raises(ValueError, match="unknown estimator kind 'kalmn'"):
        registry.factory("estimator", ComponentSpec("kalmn"))
    with pytest.raises(ValueError, match="no env known"):
        evaluate(ProportionalController(), PassThroughEstimator, None, object(), 1, 0)


def test_factories_pickle() -> None:
    f = registry.factory("estimator", ComponentSpec("none"))
    assert isinstance(pickle.loads(pickle.dumps(f)), Factory)
    assert isinstance(f(None), PassThroughEstimator)
    assert math.isfinite(StaticQos(0.5).reliability)


# ------------------------------------------------------------------ on the conveyor, CLI, fig_cn
def _conveyor_table(workers: int) -> pd.DataFrame:
    from codesign_mb.plants.conveyor import ConveyorConfig

    return evaluate(
        registry.factory("controller", ComponentSpec("mpc")),
        registry.factory("estimator", ComponentSpec("predictor")),
        StaticQos(0.5, 2),
        ConveyorConfig(belt_speed_mps=0.6),
        2,
        5,
        workers=workers,
        max_steps=20,
    )


def test_conveyor_same_seed_same_table() -> None:
    one = _conveyor_table(1)
    again = _conveyor_table(1)
    keep = [c for c in one.columns if c not in TIMING_COLUMNS]
    pd.testing.assert_frame_equal(one[keep], again[keep])
    assert (one["steps"] == 20).all() and (one["mpc_solves"] == 20).all()
    assert one["mpc_solve_ms_median"].gt(0).all()


@pytest.mark.slow
def test_conveyor_same_table_for_any_worker_count() -> None:
    one = _conveyor_table(1)
    two = _conveyor_table(2)
    keep = [c for c in one.columns if c not in TIMING_COLUMNS]
    pd.testing.assert_frame_equal(one[keep], two[keep])


def _cli(args: list[str]):
    from typer.testing import CliRunner

    from codesign_mb.cli import app

    return CliRunner().invoke(app, args)


def test_cli_evaluate_writes_table_and_summary(tmp_path) -> None:
    import json

    out = tmp_path / "res"
    result = _cli(
        [
            *("evaluate", "--belt-speed", "0.6", "-q", "0.8", "--delay", "1", "-n", "2"),
            *("--max-steps", "20", "-j", "1", "--seed", "2", "-o", str(out), "--json"),
        ]
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["trials"] == 2 and 0.0 <= summary["success_ci_low"] <= 1.0
    for name in ("evaluate.parquet", "evaluate.csv", "evaluate.json", "evaluate_summary.json"):
        assert (out / name).is_file()
    table = pd.read_parquet(out / "evaluate.parquet")
    # q = 0.8 asked on every step with a detection at the edge, nothing on the others; the
    # per-step record's request follows the detection one step later (rollout's columns
    # qos_reliability and perceived), so per episode they agree to within one step
    expected = 0.8 * table["perceived_fraction"].mean()
    one_step = 0.8 / table["steps"].min()
    assert abs(summary["mean_requested_reliability"] - expected) <= one_step + 1e-9
    assert 0.0 < summary["mean_requested_reliability"] <= 0.8
    assert len(table) == 2 and table["steps"].eq(20).all()
    assert json.loads((out / "evaluate_summary.json").read_text())["trials"] == 2


def test_cli_evaluate_config_file_and_errors(tmp_path) -> None:
    cfg = tmp_path / "eval.toml"
    cfg.write_text(
        "[evaluate]\nestimator = 'none'\ntrials = 1\nmax_steps = 5\nworkers = 1\n"
        "[evaluate.mpc]\nhorizon = 12\n"
    )
    result = _cli(["evaluate", "-c", str(cfg), "-o", str(tmp_path / "o"), "--json"])
    assert result.exit_code == 0, result.output
    bad = _cli(["evaluate", "--estimator", "kalmn", "-o", str(tmp_path / "o")])
    assert bad.exit_code == 2 and bad.stderr.startswith("error: estimator must be one of")
    cfg.write_text("[evaluate]\n[evaluate.mpc]\nhorizn = 12\n")
    bad = _cli(["evaluate", "-c", str(cfg), "-n", "1", "-o", str(tmp_path / "o")])
    assert bad.exit_code == 2 and "unknown key 'horizn' in mpc" in bad.stderr
    bad = _cli(["evaluate", "-q", "1.5", "-o", str(tmp_path / "o")])
    assert bad.exit_code == 2 and bad.stderr.startswith("error: reliability must be in [0, 1]")


def test_fig_cn_tiny_grid_and_plot(tmp_path) -> None:
    from codesign_mb.studies.fig_cn import FigCnConfig, plot_fig_cn, run_fig_cn

    cfg = FigCnConfig(
        trials=1,
        workers=1,
        delays=(0, 3),
        belt_speeds_mps=(0.6,),
        reliabilities=(0.5,),
        estimators=("predictor", "none"),
        max_steps=10,
    )
    table = run_fig_cn(cfg)
    assert len(table) == 2 * (2 + 1)
    assert set(table["sweep"]) == {"delay", "reliability"}
    assert table.loc[table["sweep"] == "reliability", "latency_steps"].eq(1).all()
    assert table["mpc_failures"].ge(0).all()  # the MPC's failed solves, summed per point
    png = plot_fig_cn(table, tmp_path / "fig.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="delays must be integers >= 0"):
        FigCnConfig(delays=(-1,))


def test_cli_fig_cn_writes_table_and_figure(tmp_path) -> None:
    import json

    cfg = tmp_path / "fig_cn.toml"
    cfg.write_text("[fig_cn]\nmax_steps = 8\nworkers = 1\n")
    out = tmp_path / "fig_cn"
    args = ["evaluate", "fig-cn", "-c", str(cfg), "-n", "1", "--delay", "0", "--belt-speed", "0.6"]
    result = _cli([*args, "-q", "0.5", "-o", str(out), "--json"])
    assert result.exit_code == 0, result.output
    rows = json.loads(result.stdout)
    assert [(r["sweep"], r["estimator"]) for r in rows] == [
        ("delay", "predictor"),
        ("reliability", "predictor"),
        ("delay", "none"),
        ("reliability", "none"),
    ]
    assert all(r["trials"] == 1 and r["mpc_failures"] >= 0 for r in rows)
    for name in ("fig_cn.parquet", "fig_cn.csv", "fig_cn.json"):
        assert (out / name).is_file()
    assert (out / "fig_cn.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_demo_runs_the_robot_by_default(tmp_path) -> None:
    import json

    cfg = tmp_path / "demo.toml"
    cfg.write_text("[robot_demo]\nworkers = 1\nestimators = ['predictor']\n")
    result = _cli(["demo", "-n", "1", "-q", "1", "-q", "0.5", "-c", str(cfg), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["scenario"] == "robot" and data["latency_steps"] == 1
    assert [(r["estimator"], r["reliability"]) for r in data["rows"]] == [
        ("predictor", 1.0),
        ("predictor", 0.5),
    ]
    assert data["rows"][0]["delivered_fraction"] == 1.0
    bad = _cli(["demo", "--episodes", "0"])
    assert bad.exit_code == 2 and bad.stderr.startswith("error: episodes ")


def test_a_dead_worker_is_replaced_and_the_table_unchanged(tmp_path) -> None:
    import json

    from codesign_mb.core.records import RecordStore

    qos = StaticQos(reliability=0.6, latency_steps=1)
    marker = str(tmp_path / "crashed")
    store = RecordStore(tmp_path / ".records")
    with pytest.warns(RuntimeWarning, match="worker process died"):
        crashed = evaluate(
            CrashOnceController(marker),
            PassThroughEstimator,
            qos,
            make_catch_env,
            6,
            3,
            workers=2,
            store=store,
        )
    reference = _table(workers=1)
    keep = [c for c in reference.columns if c not in TIMING_COLUMNS]
    pd.testing.assert_frame_equal(crashed[keep], reference[keep])
    # every episode stored once, as finished: none lost to the dead worker, none twice
    [path] = (tmp_path / ".records").glob("*.jsonl")
    items = [json.loads(line)["item"] for line in path.read_text().splitlines()]
    episodes = zip(crashed["episode"], crashed["seed"], strict=True)
    assert sorted(items) == sorted(f"{i}:{s}" for i, s in episodes)
