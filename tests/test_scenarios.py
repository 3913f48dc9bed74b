"""Conveyor scenarios: the presets, the belt schedule, the object's spawn and disturbances, edge
perception errors and missed detections, and why failed episodes failed."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from gymnasium.utils.env_checker import check_env

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.cli.common import SCENARIO_NAMES
from codesign_mb.control.mpc import MpcController
from codesign_mb.core.config import from_mapping
from codesign_mb.estimation.predictor import DelayCompensatingPredictor
from codesign_mb.evaluation.evaluate import EvaluateConfig, episode_row, summarize
from codesign_mb.network import BernoulliLink, LinkObservationWrapper
from codesign_mb.plants.belt_profiles import belt_speed_schedule
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace
from codesign_mb.plants.object_events import PARK_Y_M
from codesign_mb.plants.outcomes import FAILURE_REASONS, OutcomeTracker, failure_reason
from codesign_mb.plants.perception import GaussianPerception, PerceptionErrorModel
from codesign_mb.plants.scenarios import (
    DEFAULT_SCENARIO,
    SCENARIOS,
    get_scenario,
    scenario_config,
    scenario_toml,
)
from codesign_mb.studies.table import TableConfig

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "scenarios"


# ----------------------------------------------------------------------------- presets
def test_realistic_is_the_default_and_paper_the_configs_defaults() -> None:
    assert DEFAULT_SCENARIO == "realistic"
    assert scenario_config("paper") == ConveyorConfig()
    assert scenario_config("constant-0.2") == ConveyorConfig()
    assert scenario_config("constant-0.6") == ConveyorConfig(belt_speed_mps=0.6)
    assert scenario_config("variable") == ConveyorConfig(
        belt_speed_mps=0.6, belt_profile="variable"
    )
    assert EvaluateConfig().env_config() == scenario_config("realistic")


def test_realistic_expands_to_the_documented_fields() -> None:
    cfg = scenario_config("realistic")
    assert cfg.belt_speed_range_mps == (0.1, 0.6)
    assert cfg.belt_speed_mps == pytest.approx(0.35)  # the nominal speed: the range's middle
    assert cfg.belt_profile == "variable" and cfg.belt_stop_probability > 0
    assert cfg.spawn_along_range_m > 0 and cfg.spawn_lateral_range_m > 0
    assert cfg.spawn_delay_steps[1] > 0
    assert cfg.disturbance_probability > 0
    assert cfg.perceive_velocity is False
    assert cfg.perception_noise_std_m > 0 and cfg.perception_bias_std_m > 0
    assert 0 < cfg.perception_miss_probability < 0.5


def test_config_files_are_the_presets() -> None:
    assert {p.stem for p in CONFIGS.glob("*.toml")} == set(SCENARIOS)
    for name, scenario in SCENARIOS.items():
        text = (CONFIGS / f"{name}.toml").read_text()
        assert text == scenario_toml(name), f"regenerate configs/scenarios/{name}.toml"
        env = tomllib.loads(text)["env"]
        assert from_mapping(ConveyorConfig, env) == scenario.config()


def test_cli_knows_every_scenario_and_rejects_unknown_ones() -> None:
    assert tuple(SCENARIOS) == SCENARIO_NAMES
    message = "unknown scenario 'fast'; expected one of paper, realistic, variable"
    with pytest.raises(ValueError, match=message):
        get_scenario("fast")
    with pytest.raises(ValueError, match=message):
        EvaluateConfig(scenario="fast")
    with pytest.raises(ValueError, match="unknown scenario"):
        TableConfig(scenario="fast")
    # the scenario first, then the env table and the belt speed on top of it (the episodes'
    # base speed: the scenario's per-episode range is cleared, unless env sets one)
    cfg = EvaluateConfig(scenario="realistic", env={"horizon": 50}, belt_speed_mps=0.3)
    assert cfg.env_config() == scenario_config(
        "realistic", horizon=50, belt_speed_mps=0.3, belt_speed_range_mps=()
    )
    ranged = {"horizon": 50, "belt_speed_range_mps": (0.2, 0.4)}
    cfg = EvaluateConfig(scenario="realistic", env=ranged, belt_speed_mps=0.3)
    assert cfg.env_config().belt_speed_range_mps == (0.2, 0.4)
    plants = TableConfig(scenario="realistic", pipeline="model-based").table_plants()
    assert [p.label for p in plants] == ["realistic"]
    assert from_mapping(ConveyorConfig, plants[0].options) == scenario_config("realistic")


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("belt_speed_range_mps", (0.6, 0.1), "belt_speed_range_mps must be 0 <= low <= high"),
        ("belt_speed_range_mps", (0.1, 1.2), "must stay below max_gripper_speed_mps"),
        ("spawn_delay_steps", (0, 100), "spawn_delay_steps must be two integers"),
        ("spawn_along_range_m", 0.5, "spawn_along_range_m must keep the start on the belt"),
        ("perception_miss_probability", 1.5, "perception_miss_probability must be <= 1"),
        ("perception_bias_m", (0.0, 0.0), "perception_bias_m must be 3 finite numbers"),
        ("perception_model", "camera2", "perception_model must be one of gaussian"),
    ],
)
def test_scenario_options_are_validated(field: str, value: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ConveyorConfig(**{field: value})


# ----------------------------------------------------------------------------- the belt
def test_paper_schedule_draws_nothing_and_a_range_bounds_every_step() -> None:
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert np.all(belt_speed_schedule(ConveyorConfig(), rng) == 0.2)
    assert rng.bit_generator.state == state

    cfg = scenario_config("realistic")
    low, high = cfg.belt_speed_range_mps
    schedules = np.array([belt_speed_schedule(cfg, np.random.default_rng(s)) for s in range(600)])
    base = schedules[:, 0]  # the episode's speed, U(low, high)
    assert base.min() >= low and base.max() <= high
    assert base.mean() == pytest.approx(
        (low + high) / 2, abs=4 * (high - low) / math.sqrt(12 * 600)
    )
    moving = schedules[schedules > 0]
    assert moving.min() >= low and moving.max() <= high
    # the documented draws, replayed: base ~ U(range); after U{lo..hi} steps a stop with
    # probability p, else base * U(1 - j, 1 + j) clipped into the range
    lo, hi = cfg.belt_change_steps
    for seed in range(20):
        rng = np.random.default_rng(seed)
        speed = rng.uniform(low, high)
        expected = np.full(cfg.horizon + 1, speed)
        t = int(rng.integers(lo, hi + 1))
        while t <= cfg.horizon:
            if rng.random() < cfg.belt_stop_probability:
                expected[t:] = 0.0
            else:
                jitter = rng.uniform(1 - cfg.belt_speed_jitter, 1 + cfg.belt_speed_jitter)
                expected[t:] = np.clip(speed * jitter, low, high)
            t += int(rng.integers(lo, hi + 1))
        assert np.array_equal(schedules[seed], expected)
    assert (schedules == 0).any(axis=1).mean() > 0.3  # stops do happen


def test_env_follows_its_seeded_schedule() -> None:
    cfg = scenario_config("realistic", spawn_delay_steps=(0, 0), horizon=40)
    env = ConveyorPickPlace(cfg)
    env.reset(seed=7)
    first = env.belt_speeds
    seen = [env.step(np.zeros(4))[4]["belt_speed"] for _ in range(cfg.horizon)]
    assert seen == pytest.approx(first[1:].tolist())
    env.reset(seed=7)
    assert np.array_equal(env.belt_speeds, first)
    env.reset(seed=8)
    assert not np.array_equal(env.belt_speeds, first)
    env.close()


# ----------------------------------------------------------------------------- the object
def test_spawn_delay_parks_the_object_then_puts_it_on_the_belt() -> None:
    cfg = scenario_config(
        "realistic", spawn_delay_steps=(6, 6), perception_miss_probability=0.0, horizon=12
    )
    env = ConveyorPickPlace(cfg)
    _, info = env.reset(seed=3)
    start = env.events.start
    assert abs(start[1] - cfg.spawn_y_m) <= cfg.spawn_along_range_m
    for t in range(1, 9):
        _, _, _, _, info = env.step(np.zeros(4))
        if t < 6:  # not in view: nothing perceived; the truth is where it will appear
            assert not info["perceived"] and info["object_pos"][1] < PARK_Y_M + 0.1
            assert np.array_equal(info["remote_true"], start)
            assert not info["off_belt"]
        elif t == 6:  # appears at its start, moving with the belt
            assert info["perceived"]
            assert np.allclose(info["object_pos"], start)
            assert info["object_vel"][1] == pytest.approx(env.belt_speeds[6])
    env.close()


def test_disturbance_kick_is_the_drawn_one() -> None:
    cfg = scenario_config(
        "realistic",
        disturbance_probability=1.0,
        disturbance_speed_std_mps=0.05,
        disturbance_spin_std_radps=0.5,
        spawn_delay_steps=(0, 0),
    )
    env = ConveyorPickPlace(cfg)
    env.reset(seed=0)
    env.step(np.zeros(4))  # let the object settle onto the belt
    before = env.sim.data.qvel[env.sim.scene.object_qvel].copy()
    rng = np.random.default_rng(11)
    expected = np.random.default_rng(11)
    env.events.before_step(1, rng, touched=False)
    after = env.sim.data.qvel[env.sim.scene.object_qvel]
    assert expected.random() < 1.0  # the probability draw
    slip = expected.normal(0.0, 0.05, 2)
    spin = expected.normal(0.0, 0.5)
    assert after[:2] - before[:2] == pytest.approx(slip)
    assert after[5] - before[5] == pytest.approx(spin)
    kicks = env.events.disturbances  # the env's own step kicked it too (probability 1)
    env.events.before_step(1, rng, touched=True)  # a finger on it: no kick
    assert env.events.disturbances == kicks
    env.close()


# ----------------------------------------------------------------------------- perception
def test_gaussian_perception_has_the_configured_statistics() -> None:
    model = GaussianPerception(0.003, bias_m=(0.001, -0.002, 0.0), miss_probability=0.05)
    assert isinstance(model, PerceptionErrorModel)
    rng = np.random.default_rng(0)
    model.reset(rng)
    truth = np.array([0.5, -0.2, 0.08])
    n = 20_000
    samples = [model.sample(truth, rng) for _ in range(n)]
    hits = np.array([s for s in samples if s is not None])
    misses = n - len(hits)
    assert abs(misses / n - 0.05) < 4 * math.sqrt(0.05 * 0.95 / n)
    errors = hits - truth
    assert errors.mean(axis=0) == pytest.approx([0.001, -0.002, 0.0], abs=4 * 0.003 / math.sqrt(n))
    assert errors.std(axis=0) == pytest.approx([0.003] * 3, rel=0.05)
    # the per-episode bias: N(bias_m, bias_std^2) across episodes
    episodic = GaussianPerception(0.0, bias_std_m=0.002)
    biases = []
    for _ in range(2000):
        episodic.reset(rng)
        biases.append(episodic.sample(truth, rng) - truth)
    assert np.std(biases, axis=0) == pytest.approx([0.002] * 3, rel=0.1)


def test_noise_only_perception_draws_what_the_paper_plant_drew() -> None:
    model = GaussianPerception(0.004)
    rng, reference = np.random.default_rng(5), np.random.default_rng(5)
    truth = np.array([0.5, 0.0, 0.08])
    model.reset(rng)
    for _ in range(5):
        assert np.array_equal(model.sample(truth, rng), truth + reference.normal(0.0, 0.004, 3))
    assert GaussianPerception().exact and not model.exact


def test_a_missed_detection_sends_nothing() -> None:
    cfg = scenario_config(
        "realistic", perception_miss_probability=1.0, spawn_delay_steps=(0, 0), horizon=5
    )
    env = LinkObservationWrapper(ConveyorPickPlace(cfg), BernoulliLink(), StaticQos(1.0, 0))
    obs, info = env.reset(seed=0)
    prior = env.unwrapped.remote_prior()
    for t in range(1, 5):
        obs, _, _, _, info = env.step(np.zeros(4))
        assert not info["perceived"] and not info["delivered"]
        # Nothing to send: the network is asked nothing; the policy's choice is kept apart.
        assert info["qos_reliability"] == 0.0 and info["qos_cost"] == 0.0
        assert info["qos_asked"] == 1.0
        assert info["age"] == t + 1  # the prior, held since before t = 0
        assert np.array_equal(obs[7:10], prior)
    env.close()


def test_env_perception_errors_against_the_truth() -> None:
    cfg = scenario_config(
        "realistic",
        spawn_delay_steps=(0, 0),
        disturbance_probability=0.0,
        perception_bias_std_m=0.0,
        perception_miss_probability=0.1,
    )
    env = ConveyorPickPlace(cfg)
    errors, perceived = [], []
    for seed in range(3):
        obs, info = env.reset(seed=seed)
        for _ in range(cfg.horizon):
            obs, _, _, _, info = env.step(np.zeros(4))
            perceived.append(info["perceived"])
            if info["perceived"]:
                errors.append(obs[7:10] - info["remote_true"])
    n = len(perceived)
    assert abs(1 - np.mean(perceived) - 0.1) < 4 * math.sqrt(0.1 * 0.9 / n)
    assert np.std(errors) == pytest.approx(cfg.perception_noise_std_m, rel=0.15)
    assert np.abs(np.mean(errors, axis=0)).max() < 4 * 0.003 / math.sqrt(len(errors))
    env.close()


def test_realistic_env_passes_the_gymnasium_checker() -> None:
    env = ConveyorPickPlace(scenario_config("realistic", horizon=20))
    check_env(env, skip_render_check=True)
    env.close()


def test_predictor_gives_the_controller_the_estimated_velocity() -> None:
    cfg = scenario_config(
        "realistic", belt_profile="constant", spawn_delay_steps=(0, 0), horizon=30
    )
    plant = ConveyorPickPlace(cfg)
    assert "object_vel" not in plant.observation_layout
    assert plant.state_layout["object_vel"] == slice(10, 13)
    env = LinkObservationWrapper(plant, BernoulliLink(), StaticQos(1.0, 0))
    predictor = DelayCompensatingPredictor.from_env(env)
    mpc = MpcController.from_env(env)
    obs, _ = env.reset(seed=4)
    estimate = predictor.reset(obs)
    for _ in range(25):
        obs, *_ = env.step(mpc.act(estimate))
        estimate = predictor.estimate(obs, np.zeros(4))
    assert estimate.shape == (13,)  # the plant's state layout
    truth = plant.sim.object_velocity()
    assert truth[1] == pytest.approx(plant.belt_speeds[25], abs=0.02)  # on the belt
    assert estimate[10:13] == pytest.approx(truth, abs=0.05)
    # without an estimate of it (the stale observation), the MPC assumes the nominal speed
    mpc.act(estimate[:10])
    env.close()


# ----------------------------------------------------------------------------- outcomes
@pytest.mark.parametrize(
    ("events", "reason"),
    [
        ({"missed_grasp": False, "dropped": False, "off_belt": False}, "timeout"),
        ({"missed_grasp": True, "dropped": False, "off_belt": True}, "missed_grasp"),
        ({"missed_grasp": True, "dropped": True, "off_belt": True}, "dropped"),
        ({"missed_grasp": False, "dropped": False, "off_belt": True}, "off_belt"),
    ],
)
def test_failure_reason_order(events: dict[str, bool], reason: str) -> None:
    assert failure_reason(False, **events) == reason
    assert failure_reason(True, **events) is None


def _tracker() -> OutcomeTracker:
    return OutcomeTracker(
        object_half_width_m=0.0225, lift_height_m=0.05, reach_y_m=0.55, control_period_s=0.04
    )


def _update(tracker: OutcomeTracker, t: int, **kw: object) -> None:
    step = {
        "object_pos": np.array([0.5, 0.0, 0.0825]),
        "rise": 0.0,
        "touched": False,
        "grasped": False,
        "closed": False,
        "finger_width": 0.08,
    }
    step.update(kw)
    tracker.update(t, **step)  # type: ignore[arg-type]


def test_outcome_events_on_constructed_episodes() -> None:
    missed = _tracker()
    _update(missed, 1, closed=True, finger_width=0.04)  # closing, not yet past the object
    assert not missed.missed_grasp
    _update(missed, 2, closed=True, finger_width=0.01)
    assert missed.missed_grasp and not missed.dropped and missed.time_to_grasp_s == -1

    dropped = _tracker()
    _update(dropped, 10, touched=True, grasped=True, closed=True, finger_width=0.045)
    _update(dropped, 11, touched=True, grasped=True, closed=True, rise=0.06, finger_width=0.045)
    assert not dropped.dropped and dropped.time_to_grasp_s == pytest.approx(0.4)
    _update(dropped, 12, closed=True, rise=0.02, finger_width=0.0)
    assert dropped.dropped

    gone = _tracker()
    _update(gone, 50, object_pos=np.array([0.5, 0.55 + 0.03, 0.0825]))
    assert gone.off_belt
    fell = _tracker()
    _update(fell, 50, object_pos=np.array([0.5 + 0.2, 0.0, 0.0825]))
    assert fell.off_belt
    carried = _tracker()  # in the fingers, above the belt's side: not off the belt
    _update(carried, 50, object_pos=np.array([0.7, 0.6, 0.2]), touched=True)
    assert not carried.off_belt


def test_episode_row_and_summary_report_the_reasons() -> None:
    def steps(success: bool, **events: object) -> pd.DataFrame:
        n = 4
        frame = pd.DataFrame(
            {
                "success": [False] * (n - 1) + [success],
                "reward": 0.0,
                "qos_reliability": 1.0,
                "qos_latency_steps": 0,
                "qos_cost": 1.0,
                "delivered": True,
                "age": 0,
                "estimation_error": 0.0,
                "perceived": [True, False, True, True],
                "missed_grasp": False,
                "dropped": False,
                "off_belt": False,
                "time_to_grasp_s": -1.0,
            }
        )
        for key, value in events.items():
            frame.loc[n - 1, key] = value
        return frame

    rows = [
        episode_row(steps(True, time_to_grasp_s=1.2)),
        episode_row(steps(False, missed_grasp=True)),
        episode_row(steps(False, missed_grasp=True, off_belt=True)),
        episode_row(steps(False, off_belt=True)),
        episode_row(steps(False)),
    ]
    assert [r["failure_reason"] for r in rows] == [
        None,
        "missed_grasp",
        "missed_grasp",
        "off_belt",
        "timeout",
    ]
    assert rows[0]["time_to_grasp_s"] == pytest.approx(1.2)
    assert math.isnan(rows[1]["time_to_grasp_s"])
    assert rows[0]["perceived_fraction"] == pytest.approx(0.75)
    summary = summarize(pd.DataFrame(rows))
    counts = {reason: summary[f"failures_{reason}"] for reason in FAILURE_REASONS}
    assert counts == {"dropped": 0, "missed_grasp": 2, "off_belt": 1, "timeout": 1}
    assert summary["mean_time_to_grasp_s"] == pytest.approx(1.2)


@pytest.mark.slow
def test_realistic_separates_blind_from_oracle() -> None:
    """MPC + predictor on ``realistic``: the prior alone fails, a perfect link succeeds."""
    from codesign_mb.evaluation.evaluate import run_config

    _, blind = run_config(EvaluateConfig(scenario="realistic", reliability=0.0, trials=40))
    _, oracle = run_config(EvaluateConfig(scenario="realistic", reliability=1.0, trials=40))
    assert blind["success_rate"] <= 0.15
    assert oracle["success_rate"] >= 0.95


@pytest.mark.parametrize(
    "command",
    [
        ["evaluate", "-n", "1"],
        ["table", "-n", "1"],
        ["sweep"],
        ["wifi", "capacity", "--trials", "1"],
        ["train", "a"],
    ],
)
def test_every_command_names_the_scenarios_on_an_unknown_one(command: list[str]) -> None:
    from typer.testing import CliRunner

    from codesign_mb.cli import app

    result = CliRunner().invoke(app, [*command, "--scenario", "fast"])
    assert result.exit_code == 2, result.output
    assert "unknown scenario 'fast'" in result.output
    assert "realistic" in result.output and "paper" in result.output
