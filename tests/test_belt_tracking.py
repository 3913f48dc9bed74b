"""The belt-tracking plant of the linear scenario, its extrapolating estimator and its LQR.

Ground truth: the Gymnasium checker, the model of the module docstring step by step (the
noise-free trajectory in closed form, the noise statistics), the LQR gain from the discrete
algebraic Riccati equation, and the estimators against ``A^zeta y`` and the Kalman filter run
by hand on the same packets.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pytest
import scipy.linalg
from gymnasium.utils.env_checker import check_env

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.tracking import TrackingLqr
from codesign_mb.estimation.base import Estimator, PassThroughEstimator
from codesign_mb.estimation.extrapolation import ModelExtrapolation, RemotePartEstimator
from codesign_mb.estimation.kalman import IntermittentKalmanFilter, KalmanEstimator
from codesign_mb.network import BernoulliLink, LinkObservationWrapper, NetworkedPlant
from codesign_mb.plants.belt_tracking import BeltTracking
from codesign_mb.plants.linear import LinearPlantEnv, double_integrator
from codesign_mb.rollout import ClosedLoop, Transition, rollout

NOISELESS = {
    "start_spread_m": 0.0,
    "velocity_noise_mps": 0.0,
    "measurement_noise_m": 0.0,
    "measurement_noise_mps": 0.0,
}


# ----------------------------------------------------------------------------- plant


def test_check_env_passes_and_reset_seeds_everything() -> None:
    env = BeltTracking(horizon=20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker's warnings are failures too, except:
        # the object and gripper have no natural bounds, and gymnasium asks for a normalised
        # action space where the action is an acceleration in m/s^2.
        warnings.filterwarnings("ignore", message=".*infinity.*")
        warnings.filterwarnings("ignore", message=".*normalized space.*")
        check_env(env, skip_render_check=True)
    assert isinstance(env, NetworkedPlant)

    def trajectory(seed: int) -> np.ndarray:
        plant = BeltTracking(horizon=20)
        obs, _ = plant.reset(seed=seed)
        rows = [obs]
        for _ in range(20):
            rows.append(plant.step(np.array([3.0]))[0])
        return np.array(rows)

    np.testing.assert_array_equal(trajectory(3), trajectory(3))
    assert not np.array_equal(trajectory(3), trajectory(4))


def test_noiseless_trajectory_is_the_model_in_closed_form() -> None:
    dt, speed, u_max = 0.04, 0.5, 2.0
    env = BeltTracking(
        belt_speed_mps=speed, horizon=5, max_accel_mps2=u_max, velocity_weight=0.3, **NOISELESS
    )
    obs, info = env.reset(seed=0)
    np.testing.assert_array_equal(obs, [0.0, 0.0, 0.1, speed])
    np.testing.assert_array_equal(info["object"], env.remote_prior())
    np.testing.assert_array_equal(obs[env.remote_slice], env.remote_prior())
    actions = [5.0, -1.0, 0.5, -7.0, 1.5]  # the first and fourth are clipped to +-u_max
    pos = vel = 0.0
    for t, requested in enumerate(actions, start=1):
        u = float(np.clip(requested, -u_max, u_max))
        p_before = 0.1 + speed * dt * (t - 1)
        e = np.array([pos - p_before, vel - speed])
        obs, reward, terminated, truncated, info = env.step(np.array([requested]))
        pos, vel = pos + dt * vel + 0.5 * dt**2 * u, vel + dt * u
        p = 0.1 + speed * dt * t
        np.testing.assert_allclose(obs, [pos, vel, p, speed], rtol=0, atol=1e-14)
        np.testing.assert_allclose(info["object"], [p, speed], rtol=0, atol=1e-14)
        cost = e @ np.diag([1.0, 0.3]) @ e + 1e-3 * u * u
        assert reward == pytest.approx(-cost, rel=1e-12) and info["stage_cost"] == -reward
        assert info["tracking_error_m"] == pytest.approx(e[0], abs=1e-15)
        assert info["within_radius"] == (abs(e[0]) <= 0.01)
        assert not terminated and truncated == (t == 5)
    assert env.t == 5


def test_noise_has_the_stated_statistics() -> None:
    env = BeltTracking(
        horizon=4000,
        start_spread_m=0.03,
        velocity_noise_mps=0.05,
        measurement_noise_m=0.004,
        measurement_noise_mps=0.02,
    )
    starts = [BeltTracking(start_spread_m=0.03).reset(seed=s)[1]["object"][0] for s in range(400)]
    assert np.mean(starts) == pytest.approx(0.1, abs=4 * 0.03 / 20)
    assert np.std(starts) == pytest.approx(0.03, rel=0.15)
    obs, info = env.reset(seed=1)
    objects, measured = [info["object"]], [obs[2:]]
    for _ in range(4000):
        obs, _, _, _, info = env.step(np.zeros(1))
        objects.append(info["object"])
        measured.append(obs[2:])
    o, x = np.array(objects), np.array(measured)
    noise = x - o
    for column, std in enumerate((0.004, 0.02)):  # 4001 samples: 4 standard errors
        assert abs(noise[:, column].mean()) < 4 * std / 63
        assert noise[:, column].std() == pytest.approx(std, rel=0.05)
    np.testing.assert_allclose(np.diff(o[:, 0]), 0.04 * o[:-1, 1], rtol=0, atol=1e-12)
    assert np.std(np.diff(o[:, 1])) == pytest.approx(0.05, rel=0.05)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"horizon": 0}, "horizon must be an integer >= 1, got 0"),
        ({"control_period_s": 0.0}, "control_period_s must be > 0"),
        ({"velocity_noise_mps": -0.1}, "velocity_noise_mps must be >= 0, got -0.1"),
        ({"control_weight": 0.0}, "control_weight must be > 0"),
        ({"belt_speed_mps": float("nan")}, "belt_speed_mps"),
        ({"render_mode": "human"}, "render_mode must be None"),
    ],
)
def test_invalid_settings_are_refused_by_name(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        BeltTracking(**kwargs)


def test_step_before_reset_and_bad_action_are_refused() -> None:
    env = BeltTracking()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(1))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="1 entry"):
        env.step(np.zeros(2))
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(seed=0, options={"x0": 1.0})


# ----------------------------------------------------------------------------- controller


def test_tracking_lqr_gain_solves_the_riccati_equation() -> None:
    env = BeltTracking(control_period_s=0.05, velocity_weight=0.2, control_weight=1e-2)
    ctrl = TrackingLqr.for_env(LinkObservationWrapper(env, BernoulliLink(), StaticQos()))
    dt = 0.05
    A = np.array([[1.0, dt], [0.0, 1.0]])
    B = np.array([[0.5 * dt * dt], [dt]])
    Q, R = np.diag([1.0, 0.2]), np.array([[1e-2]])
    S = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ S @ B, B.T @ S @ A)
    np.testing.assert_allclose(ctrl.gain, K, rtol=1e-9)
    assert np.max(np.abs(np.linalg.eigvals(A - B @ ctrl.gain))) < 1
    obs = np.array([0.02, -0.1, 0.07, 0.3])
    np.testing.assert_allclose(ctrl.act(obs), -K @ (obs[:2] - obs[2:]), rtol=1e-12)
    with pytest.raises(TypeError, match="BeltTracking"):
        TrackingLqr.for_env(LinearPlantEnv(double_integrator()))
    with pytest.raises(ValueError, match="remote must select 2 entries"):
        TrackingLqr(env.error_model, Q, R, local=slice(0, 2), remote=slice(2, 5))


def test_ideal_control_tracks_the_object() -> None:
    """Ideal control (no estimator) brings the gripper onto the object and keeps it there."""
    env = LinkObservationWrapper(BeltTracking(belt_speed_mps=0.6), BernoulliLink(), StaticQos())
    table = rollout(env, None, TrackingLqr.for_env(env), seed=5)
    assert len(table) == 100
    assert table["tracking_error_m"].abs().iloc[-20:].max() < 0.01
    assert table["within_radius"].iloc[-20:].all()
    np.testing.assert_allclose(table["reward"], -table["stage_cost"], rtol=0, atol=0)


# ----------------------------------------------------------------------------- estimators


def _transitions(estimator: Estimator, *, reliability: float, latency: int) -> list[Transition]:
    env = LinkObservationWrapper(
        BeltTracking(belt_speed_mps=0.6), BernoulliLink(), StaticQos(reliability, latency)
    )
    seen: list[Transition] = []
    loop = ClosedLoop(env, estimator, TrackingLqr.for_env(env), observer=seen.append)
    loop.reset(seed=11)
    while not loop.done:
        loop.step()
    return seen


def test_model_extrapolation_is_the_held_observation_aged_by_the_model() -> None:
    A = BeltTracking().remote_model.A
    estimator = RemotePartEstimator(ModelExtrapolation(A), BeltTracking.remote_slice)
    seen = _transitions(estimator, reliability=0.5, latency=2)
    ages = {round(float(s.observation[-1])) for s in seen}
    assert len(ages) > 3  # losses and latency age the observation
    for step in seen:
        age = round(float(step.observation[-1]))
        np.testing.assert_array_equal(step.state[:2], step.observation[:2])  # local: fresh
        expected = np.linalg.matrix_power(A, age) @ step.observation[2:4]
        np.testing.assert_allclose(step.state[2:], expected, rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="square"):
        ModelExtrapolation(np.ones((2, 3)))
    with pytest.raises(ValueError, match="age must be >= 0"):
        ModelExtrapolation(A).power(-1)


def test_pass_through_uses_the_stale_observation() -> None:
    for step in _transitions(PassThroughEstimator(), reliability=0.5, latency=1):
        np.testing.assert_array_equal(step.state, step.observation[:-1])


def test_kalman_in_the_layout_equals_the_filter_run_by_hand() -> None:
    """The embedded KalmanEstimator is the intermittent filter on every packet that arrived."""
    plant = BeltTracking(belt_speed_mps=0.6)
    env = LinkObservationWrapper(plant, BernoulliLink(), StaticQos(0.6, 3))
    model = plant.remote_model
    prior_cov = np.diag([0.02**2, 1e-6])
    kalman = KalmanEstimator(
        model, x0_mean=plant.remote_prior(), x0_cov=prior_cov, link_wrapper=env
    )
    estimator = RemotePartEstimator(kalman, plant.remote_slice)
    by_hand = IntermittentKalmanFilter(model.A, np.eye(2), model.W, model.V)
    by_hand.reset(plant.remote_prior(), prior_cov)
    seen: list[Transition] = []
    loop = ClosedLoop(env, estimator, TrackingLqr.for_env(env), observer=seen.append)
    loop.reset(seed=2)
    expected, n_packets = [], 0
    while True:
        rx = env.last_reception
        assert rx is not None
        for packet in rx.arrivals:
            by_hand.update(packet.value, packet.timestamp)
            n_packets += 1
        expected.append(by_hand.x)
        if loop.done:
            break
        loop.step()
        by_hand.predict()
    assert len(seen) == 100 and 30 < n_packets < 100  # q = 0.6: lost and late ones
    states = np.array([step.state for step in seen])  # x_hat_0 .. x_hat_99, as acted on
    np.testing.assert_allclose(states[:, 2:], np.array(expected[:-1]), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(states[:, :2], [step.observation[:2] for step in seen])


def test_remote_part_estimator_refuses_an_open_slice() -> None:
    with pytest.raises(ValueError, match="contiguous slice"):
        RemotePartEstimator(PassThroughEstimator(), slice(2, None))
