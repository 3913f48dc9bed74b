"""The conveyor pick-and-place env: API, seeding, validation, the link wrapper, the scripted
policy's success rate, rendering."""

from __future__ import annotations

import dataclasses
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import codesign_mb.plants  # noqa: F401  (registers the gym id)
from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.base import Controller
from codesign_mb.control.scripted import ScriptedPickController
from codesign_mb.core.config import from_mapping
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.network import BernoulliLink, LinkObservationWrapper, NetworkedPlant
from codesign_mb.plants.conveyor import (
    ConveyorConfig,
    ConveyorPickPlace,
    belt_speed_schedule,
    observation_layout,
)
from codesign_mb.rollout import rollout

GYM_ID = "codesign_mb/ConveyorPickPlace-v0"


@pytest.fixture(scope="module")
def env() -> ConveyorPickPlace:
    env = ConveyorPickPlace()
    yield env
    env.close()


def _run(env: gym.Env, seed: int, actions: np.ndarray) -> list:
    obs, info = env.reset(seed=seed)
    trace = [obs.copy()]
    for action in actions:
        obs, reward, terminated, truncated, info = env.step(action)
        trace.append((obs.copy(), reward, terminated, truncated, info["object_pos"].copy()))
    return trace


def _same(a: list, b: list) -> bool:
    if len(a) != len(b):
        return False
    if not np.array_equal(a[0], b[0]):
        return False
    for x, y in zip(a[1:], b[1:], strict=True):
        if not (np.array_equal(x[0], y[0]) and x[1:4] == y[1:4] and np.array_equal(x[4], y[4])):
            return False
    return True


# ----------------------------------------------------------------------------- API


def test_check_env_passes() -> None:
    env = ConveyorPickPlace(ConveyorConfig(horizon=20, perception_noise_std_m=0.002))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # check_env's warnings are failures too
        check_env(env, skip_render_check=True)
    env.close()


def test_gym_make_and_contract_attributes() -> None:
    env = gym.make(GYM_ID, config=ConveyorConfig(belt_speed_mps=0.6))
    plant = env.unwrapped
    assert isinstance(plant, ConveyorPickPlace)
    assert isinstance(plant, NetworkedPlant)
    assert plant.horizon == 100 and plant.control_period_s == pytest.approx(0.04)
    layout = plant.observation_layout
    for key in ("gripper_pos", "gripper_vel", "finger_width", "object_pos", "object_vel"):
        assert key in layout
    assert plant.remote_slice == slice(layout["object_pos"].start, layout["object_vel"].stop)
    assert env.action_space.shape == (4,)
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    obs, info = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape
    prior = plant.remote_prior()
    assert prior.shape == obs[plant.remote_slice].shape
    assert prior[4] == pytest.approx(0.6)  # nominal belt velocity along +y
    for key in ("success", "object_pos", "gripper_object_distance", "lifted"):
        assert key in info
    env.close()


def test_layout_without_velocity() -> None:
    config = ConveyorConfig(perceive_velocity=False)
    env = ConveyorPickPlace(config)
    assert "object_vel" not in env.observation_layout
    assert env.observation_space.shape == (10,)
    assert env.remote_slice == slice(7, 10)
    assert observation_layout(config) == env.observation_layout
    obs, _ = env.reset(seed=0)
    assert obs.shape == (10,)
    env.close()


def test_horizon_truncates(env: ConveyorPickPlace) -> None:
    short = ConveyorPickPlace(ConveyorConfig(horizon=3))
    short.reset(seed=0)
    flags = [short.step(np.zeros(4))[3] for _ in range(3)]
    assert flags == [False, False, True]
    short.close()


def test_observation_matches_truth(env: ConveyorPickPlace) -> None:
    obs, info = env.reset(seed=4)
    obs, _, _, _, info = env.step(np.array([0.3, 0.0, -0.2, -1.0]))
    lay = env.observation_layout
    np.testing.assert_allclose(obs[lay["object_pos"]], info["object_pos"])
    np.testing.assert_allclose(obs[lay["gripper_pos"]], info["gripper_pos"])
    assert obs[lay["finger_width"]][0] == pytest.approx(0.08, abs=1e-3)
    # The commanded velocity is tracked within one control step (up to the acceleration bound).
    assert obs[lay["gripper_vel"]][0] == pytest.approx(0.3, abs=0.05)


# ----------------------------------------------------------------------------- seeding


def test_same_seed_same_episode() -> None:
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(15, 4))
    config = ConveyorConfig(belt_profile="variable", perception_noise_std_m=0.003)
    a, b = ConveyorPickPlace(config), ConveyorPickPlace(config)
    first = _run(a, 7, actions)
    assert _same(first, _run(b, 7, actions))
    assert _same(first, _run(a, 7, actions))  # reset(seed) on a used env replays it
    assert not _same(first, _run(a, 8, actions))
    a.close()
    b.close()


def test_spawn_is_seeded_and_lateral() -> None:
    env = ConveyorPickPlace()
    xs = {round(float(env.reset(seed=s)[1]["object_pos"][0]), 6) for s in range(8)}
    assert len(xs) == 8
    assert all(abs(x - 0.5) <= 0.08 + 1e-9 for x in xs)
    env.close()


def test_variable_belt_schedule() -> None:
    config = ConveyorConfig(belt_profile="variable", belt_speed_mps=0.4, belt_stop_probability=0.3)
    schedules = [belt_speed_schedule(config, np.random.default_rng(s)) for s in range(30)]
    for speeds in schedules:
        assert speeds.shape == (101,)
        assert speeds[0] == pytest.approx(0.4)
        assert np.all(speeds >= 0) and np.all(speeds <= 0.4 * 1.3 + 1e-12)
        assert 1 <= np.count_nonzero(np.diff(speeds)) <= 10
    assert any(np.any(s == 0.0) for s in schedules)  # some episodes have stops
    np.testing.assert_array_equal(
        belt_speed_schedule(config, np.random.default_rng(3)), schedules[3]
    )
    constant = belt_speed_schedule(ConveyorConfig(), np.random.default_rng(0))
    assert np.all(constant == 0.2)


def test_belt_speed_follows_schedule_and_moves_object() -> None:
    config = ConveyorConfig(belt_profile="variable", belt_speed_mps=0.4, horizon=40)
    env = ConveyorPickPlace(config)
    _, info = env.reset(seed=11)
    speeds = env.belt_speeds
    assert np.count_nonzero(np.diff(speeds)) >= 1
    y0 = info["object_pos"][1]
    for t in range(1, 41):
        _, _, _, _, info = env.step(np.array([0.0, 0.0, 0.0, -1.0]))
        assert info["belt_speed"] == pytest.approx(speeds[t])
    expected = speeds[:40].sum() * config.control_period_s
    assert info["object_pos"][1] - y0 == pytest.approx(expected, abs=0.02)
    env.close()


def test_perception_noise() -> None:
    env = ConveyorPickPlace(ConveyorConfig(perception_noise_std_m=0.01, horizon=60))
    obs, info = env.reset(seed=0)
    errors = []
    for _ in range(60):
        obs, _, _, _, info = env.step(np.zeros(4))
        errors.append(obs[7:10] - info["object_pos"])
    std = float(np.std(errors))
    assert 0.007 < std < 0.013
    env.close()


# ----------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("changes", "field", "value"),
    [
        ({"belt_speed_mps": -0.2}, "belt_speed_mps", "-0.2"),
        ({"horizon": 0}, "horizon", "0"),
        ({"object": "banana"}, "object", "banana"),
        ({"belt_profile": "sinus"}, "belt_profile", "sinus"),
        ({"perception_noise_std_m": -1.0}, "perception_noise_std_m", "-1.0"),
        ({"belt_change_steps": (5, 2)}, "belt_change_steps", "(5, 2)"),
        ({"horizon": 2.5}, "horizon", "2.5"),
        ({"max_gripper_speed_mps": float("nan")}, "max_gripper_speed_mps", "nan"),
    ],
)
def test_bad_config_names_field_and_value(changes: dict, field: str, value: str) -> None:
    with pytest.raises(ValueError, match=field) as excinfo:
        ConveyorConfig(**changes)
    assert value in str(excinfo.value)


def test_config_from_mapping_is_strict() -> None:
    config = from_mapping(ConveyorConfig, {"belt_speed_mps": 0.6, "belt_change_steps": [5, 9]})
    assert config.belt_change_steps == (5, 9)
    with pytest.raises(ValueError, match="belt_sped"):
        from_mapping(ConveyorConfig, {"belt_sped": 0.6})


def test_belt_faster_than_gripper_is_rejected() -> None:
    with pytest.raises(ValueError, match="max_gripper_speed_mps"):
        ConveyorConfig(belt_speed_mps=0.8, max_gripper_speed_mps=0.5)


def test_nan_action_raises_and_leaves_state(env: ConveyorPickPlace) -> None:
    env.reset(seed=0)
    before = env.sim.data.qpos.copy(), env.sim.time
    for bad in ([np.nan, 0, 0, 0], [0, np.inf, 0, 1]):
        with pytest.raises(ValueError, match="finite"):
            env.step(np.array(bad))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))
    np.testing.assert_array_equal(env.sim.data.qpos, before[0])
    assert env.sim.time == before[1]


def test_out_of_range_action_is_clipped(env: ConveyorPickPlace) -> None:
    env.reset(seed=0)
    a = env.step(np.array([5.0, 0.0, 0.0, 1.0]))[0]
    env.reset(seed=0)
    b = env.step(np.array([1.0, 0.0, 0.0, 1.0]))[0]
    np.testing.assert_array_equal(a, b)


# ----------------------------------------------------------------------------- link wrapper


def test_link_wrapper_delays_the_object() -> None:
    config = ConveyorConfig(horizon=12)
    made = gym.make(GYM_ID, config=config)  # the registered env, with gymnasium's wrappers
    plant = made.unwrapped
    wrapped = LinkObservationWrapper(made, BernoulliLink(), StaticQos(1.0, 2))
    obs, info = wrapped.reset(seed=0)
    assert obs.shape == (plant.observation_space.shape[0] + 1,)
    assert wrapped.observation_space.contains(obs)
    truth = [info["remote_true"]]
    for t in range(1, 8):
        obs, _, _, _, info = wrapped.step(np.zeros(4))
        truth.append(info["remote_true"])
        if t >= 2:
            assert obs[-1] == 2  # age zeta_t = tau
            np.testing.assert_allclose(obs[plant.remote_slice], truth[t - 2])
        # proprioception is local and fresh
        np.testing.assert_allclose(obs[:3], info["gripper_pos"])
    wrapped.close()


def test_scripted_controller_through_the_wrapper_and_rollout() -> None:
    config = ConveyorConfig(terminate_on_success=True)
    plant = ConveyorPickPlace(config)
    controller = ScriptedPickController(config)
    assert isinstance(controller, Controller)
    wrapped = LinkObservationWrapper(plant, BernoulliLink(), StaticQos(1.0, 0))
    assert ScriptedPickController.from_env(wrapped).config == config
    table = rollout(wrapped, PassThroughEstimator(), controller, seed=3)
    assert bool(table["success"].iloc[-1])
    assert len(table) < config.horizon  # terminated at success
    assert table["estimation_error"].max() == 0.0
    assert {"lifted", "gripper_object_distance", "reward"} <= set(table.columns)
    wrapped.close()


# ----------------------------------------------------------------------------- success


def _success_rate(config: ConveyorConfig, seeds: range) -> tuple[int, int]:
    env = ConveyorPickPlace(dataclasses.replace(config, terminate_on_success=True))
    policy = ScriptedPickController(config)
    wins = 0
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        policy.reset(seed=seed)
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            done = terminated or truncated
        wins += bool(info["success"])
    env.close()
    return wins, len(seeds)


@pytest.mark.parametrize(("speed", "episodes"), [(0.2, 12), (0.6, 6)])
def test_scripted_policy_succeeds(speed: float, episodes: int) -> None:
    wins, n = _success_rate(ConveyorConfig(belt_speed_mps=speed), range(1000, 1000 + episodes))
    assert wins >= n - 1, f"{wins}/{n} at {speed} m/s"


def test_scripted_policy_variable_belt_and_cylinder() -> None:
    wins, n = _success_rate(
        ConveyorConfig(belt_speed_mps=0.4, belt_profile="variable", object="cylinder"),
        range(2000, 2006),
    )
    assert wins >= n - 1


def test_success_needs_the_lift(env: ConveyorPickPlace) -> None:
    # Holding still: never lifted, never a success; the reward is the reach term only.
    env.reset(seed=0)
    for _ in range(5):
        _, reward, _, _, info = env.step(np.array([0.0, 0.0, 0.0, 1.0]))
    assert not info["success"] and not info["lifted"] and not info["grasped"]
    assert 0.0 <= reward < 1.0


@pytest.mark.slow
@pytest.mark.parametrize("speed", [0.2, 0.6])
def test_scripted_policy_100_episodes(speed: float) -> None:
    wins, n = _success_rate(ConveyorConfig(belt_speed_mps=speed), range(100))
    print(f"scripted success at {speed} m/s: {wins}/{n}")
    assert wins >= 90


# ----------------------------------------------------------------------------- rendering


@pytest.mark.render
def test_render_rgb_array() -> None:
    from codesign_mb.robot.render import gl_backend

    if gl_backend() is None:
        pytest.skip("no headless GL backend (install libosmesa6, or libegl1 + libegl-mesa0)")
    env = ConveyorPickPlace(ConveyorConfig(render_width=160, render_height=120), "rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    assert frame.std() > 10  # not a blank image
    env.step(np.array([0.0, 0.5, -0.5, 1.0]))
    assert not np.array_equal(frame, env.render())
    env.close()
    assert ConveyorPickPlace().render() is None  # render_mode None


def test_random_bang_bang_actions_stay_in_the_workspace() -> None:
    """What early RL exploration does: full-speed commands held for a few steps.

    The gripper brakes at the workspace boundary (a few cm of overshoot when the arm is
    stretched and its shoulder saturates), keeps its orientation within a few degrees and
    settles back once the commands stop.
    """
    import pinocchio as pin

    from codesign_mb.robot.model import GRIPPER_DOWN

    def rotation_error() -> float:
        _, rotation = env.sim.robot.tcp_pose(env.sim.joint_positions())
        return float(np.linalg.norm(pin.log3(GRIPPER_DOWN.T @ rotation)))

    env = ConveyorPickPlace()
    rng = np.random.default_rng(0)
    worst_rotation, margin = 0.0, 0.06
    for seed in range(2):
        env.reset(seed=seed)
        for t in range(45):
            if t % 5 == 0:
                action = np.sign(rng.uniform(-1, 1, 4))
            p = env.step(action)[0][:3]
            assert np.all(p >= env.workspace_low - margin), p
            assert np.all(p <= env.workspace_high + margin), p
            assert np.hypot(p[0], p[1]) <= env.workspace_radius + margin
            worst_rotation = max(worst_rotation, rotation_error())
        for _ in range(15):
            env.step(np.zeros(4))
        assert rotation_error() < np.radians(0.5)
    assert worst_rotation < np.radians(15)
    env.close()


def _python_braking(
    velocity: list[float],
    x: tuple[float, float, float],
    low: list[float],
    high: list[float],
    workspace_radius: float,
    margin: float,
    T: float,
    a: float,
    limit: float,
) -> list[float]:
    """The braking law as plain Python (what ``plants.braking.keep_in_workspace`` compiles)."""
    import math

    x0, x1, x2 = x
    radius = math.hypot(x0, x1)
    if (
        min(x0 - low[0], x1 - low[1], x2 - low[2], high[0] - x0, high[1] - x1, high[2] - x2)
        > margin
        and workspace_radius - radius > margin
    ):
        return [min(max(vi, -limit), limit) for vi in velocity]

    def cap(distance: float) -> float:
        return a * (math.sqrt(T * T + 2.0 * max(distance, 0.0) / a) - T)

    v = [
        min(max(vi, -cap(xi - lo)), cap(hi - xi))
        for vi, xi, lo, hi in zip(velocity, x, low, high, strict=True)
    ]
    if radius > 0:
        outward = (v[0] * x0 + v[1] * x1) / radius
        allowed = cap(workspace_radius - radius)
        if outward > allowed:
            v[0] -= (outward - allowed) * x0 / radius
            v[1] -= (outward - allowed) * x1 / radius
    return [min(max(vi, -limit), limit) for vi in v]


@pytest.mark.parametrize("margin", [None, 0.01])
def test_compiled_braking_equals_the_python_law_bit_for_bit(
    env: ConveyorPickPlace, margin: float | None
) -> None:
    import math

    from codesign_mb.plants.braking import keep_in_workspace

    rng = np.random.default_rng(0)
    low, high = env.workspace_low, env.workspace_high
    margin = env._brake_distance if margin is None else margin
    T, a, limit = env.control_period_s, env._brake_accel, env.config.max_gripper_speed_mps
    for _ in range(3000):  # inside, near and beyond the faces and the cylinder
        x = rng.uniform(low - 0.1, high + 0.1)
        if rng.random() < 0.2:
            x[:2] *= env.workspace_radius / math.hypot(*x[:2]) * rng.uniform(0.97, 1.03)
        velocity = rng.uniform(-1.5, 1.5, 3) * (rng.random(3) < 0.9)
        expected = _python_braking(
            velocity.tolist(), tuple(x.tolist()), low.tolist(), high.tolist(),
            env.workspace_radius, margin, T, a, limit,
        )  # fmt: skip
        out = velocity.copy()
        keep_in_workspace(
            out, x, math.hypot(x[0], x[1]), low, high, env.workspace_radius, margin, T, a, limit
        )
        assert out.tolist() == expected
