"""The delay-compensating predictor against hand-computed constant-velocity predictions."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.estimation.base import Estimator, PassThroughEstimator
from codesign_mb.estimation.predictor import DelayCompensatingPredictor, constant_velocity_model
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper

DT = 0.04
# plant observation: gripper (3), object position (3), object velocity (3); then the age
LAYOUT = {"gripper_pos": slice(0, 3), "object_pos": slice(3, 6), "object_vel": slice(6, 9)}


def _wrapped(gripper, pos, vel, age) -> np.ndarray:
    return np.concatenate([gripper, pos, vel, [age]]).astype(float)


def _exact(**kw) -> DelayCompensatingPredictor:
    """Near noise-free measurements and no process noise: the filter reproduces the model."""
    base = dict(
        control_period_s=DT,
        position_noise_std=1e-7,
        velocity_noise_std=1e-7,
        accel_std=0.0,
        prior_position_std=1.0,
        prior_velocity_std=10.0,
    )
    base.update(kw)
    return DelayCompensatingPredictor(LAYOUT, **base)


def test_predicts_through_losses_and_delays_by_hand() -> None:
    est = _exact(accel_std=1.0)  # the belt may change speed: a fresh packet is believed
    assert isinstance(est, Estimator)
    g = np.array([0.1, 0.2, 0.3])
    p0, w0 = np.array([0.1, 0.2, 0.05]), np.array([0.6, 0.0, 0.0])
    out = est.reset(_wrapped(g, p0, w0, 0))  # x_0 received at t = 0
    np.testing.assert_allclose(out[3:6], p0, atol=1e-9)
    np.testing.assert_allclose(out[:3], g)  # local part untouched
    # Five losses: y stays x_0, the age grows; the prediction is p0 + t dt w0.
    for t in range(1, 6):
        out = est.estimate(_wrapped(g, p0, w0, t), np.zeros(4))
        np.testing.assert_allclose(out[3:6], p0 + t * DT * w0, atol=1e-9)
        np.testing.assert_allclose(out[6:9], w0, atol=1e-9)
    # t = 6: a packet stamped 4 arrives (age 2): the belt slowed to 0.3 m/s at x_4 = (0.2, ...).
    p4, w4 = np.array([0.2, 0.2, 0.05]), np.array([0.3, 0.0, 0.0])
    out = est.estimate(_wrapped(g, p4, w4, 2), np.zeros(4))
    np.testing.assert_allclose(out[3:6], p4 + 2 * DT * w4, atol=1e-9)
    np.testing.assert_allclose(out[6:9], w4, atol=1e-9)
    assert est.t == 6 and est.updates == 2


def test_velocity_inferred_from_positions_only() -> None:
    layout = {"object_pos": slice(0, 3)}
    est = DelayCompensatingPredictor(
        layout,
        control_period_s=DT,
        position_noise_std=1e-7,
        accel_std=0.0,
        prior_velocity_std=10.0,
    )
    x0 = np.array([0.0, 0.1, 0.05])
    x1 = np.array([0.02, 0.1, 0.05])  # 0.5 m/s along x
    est.reset(np.append(x0, 0))
    est.estimate(np.append(x1, 0), np.zeros(4))
    for age in (1, 2, 3):  # held y = x_1
        out = est.estimate(np.append(x1, age), np.zeros(4))
    # hand: x_4 = x_1 + 3 (x_1 - x_0)
    np.testing.assert_allclose(out, x1 + 3 * (x1 - x0), atol=1e-6)


def test_prior_before_any_delivery_and_stale_packets() -> None:
    est = _exact(prior_velocity=(0.2, 0.0, 0.0))
    g = np.zeros(3)
    prior = np.array([-0.3, 0.0, 0.05])
    # age 1 at t = 0: the prior (stamped -1) is held, nothing measured yet
    out = est.reset(_wrapped(g, prior, np.zeros(3), 1))
    np.testing.assert_allclose(out[3:6], prior)
    np.testing.assert_allclose(out[6:9], [0.2, 0.0, 0.0])
    out = est.estimate(_wrapped(g, prior, np.zeros(3), 2), np.zeros(4))
    np.testing.assert_allclose(out[3:6], prior + DT * np.array([0.2, 0, 0]), atol=1e-12)
    assert est.updates == 0
    std_before = est.position_std
    est.estimate(_wrapped(g, prior, np.zeros(3), 2), np.zeros(4))  # x_0 = prior arrives at t = 2
    assert est.updates == 1 and est.position_std < std_before
    est.estimate(_wrapped(g, prior, np.zeros(3), 3), np.zeros(4))  # the same packet: ignored
    assert est.updates == 1


def test_covariance_grows_without_packets_and_shrinks_on_arrival() -> None:
    est = DelayCompensatingPredictor(LAYOUT, control_period_s=DT)
    g, p, w = np.zeros(3), np.array([0.0, 0.0, 0.05]), np.array([0.2, 0.0, 0.0])
    est.reset(_wrapped(g, p, w, 0))
    stds = [est.position_std]
    for t in range(1, 10):
        est.estimate(_wrapped(g, p, w, t), np.zeros(4))
        stds.append(est.position_std)
    assert np.all(np.diff(stds) > 0)
    assert est.covariance.shape == (6, 6) and est.state.shape == (6,)
    est.estimate(_wrapped(g, p + 10 * DT * w, w, 0), np.zeros(4))
    assert est.position_std < stds[1]


def test_constant_velocity_model_matrices() -> None:
    A, Q = constant_velocity_model(0.5, 2.0, dims=1)
    np.testing.assert_allclose(A, [[1, 0.5], [0, 1]])
    np.testing.assert_allclose(Q, 4.0 * np.array([[0.5**4 / 4, 0.5**3 / 2], [0.5**3 / 2, 0.25]]))


class BeltEnv(gym.Env):
    """An object on a belt at a constant speed; the object part is remote."""

    remote_slice = slice(3, 9)
    observation_layout = LAYOUT
    control_period_s = DT

    def __init__(self, speed: float = 0.6) -> None:
        self.speed = speed
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(9,), dtype=np.float64)
        self.action_space = gym.spaces.Box(-1, 1, shape=(4,), dtype=np.float64)

    def remote_prior(self):
        return np.array([-0.5, 0.0, 0.05, self.speed, 0.0, 0.0])

    def _obs(self):
        return np.concatenate([np.zeros(3), self._p, [self.speed, 0.0, 0.0]])

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._p = np.array([-0.5 + 0.1 * self.np_random.random(), 0.0, 0.05])
        return self._obs(), {}

    def step(self, action):
        self._p = self._p + DT * np.array([self.speed, 0.0, 0.0])
        return self._obs(), 0.0, False, False, {}


@pytest.mark.parametrize("latency", [0, 4])
def test_through_the_link_the_prediction_is_current(latency: int) -> None:
    env = LinkObservationWrapper(BeltEnv(), BernoulliLink(), StaticQos(0.5, latency))
    est = _exact()
    plain = PassThroughEstimator()
    obs, info = env.reset(seed=1)
    est.reset(obs)
    plain.reset(obs)
    err, err_plain = [], []
    for _ in range(40):
        obs, _, _, _, info = env.step(np.zeros(4))
        true = info["remote_true"][:3]
        err.append(np.linalg.norm(est.estimate(obs, np.zeros(4))[3:6] - true))
        err_plain.append(np.linalg.norm(plain.estimate(obs, np.zeros(4))[3:6] - true))
    # after the first delivery the constant-velocity prediction is exact
    assert max(err[-20:]) < 1e-6
    assert max(err_plain[-20:]) >= 0.6 * DT * max(latency, 1) - 1e-9


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="object_pos"):
        DelayCompensatingPredictor({"gripper_pos": slice(0, 3)}, control_period_s=DT)
    with pytest.raises(ValueError, match="control_period_s must be > 0"):
        DelayCompensatingPredictor(LAYOUT, control_period_s=0.0)
    with pytest.raises(RuntimeError, match="reset"):
        DelayCompensatingPredictor(LAYOUT, control_period_s=DT).estimate(np.zeros(10), None)


@pytest.mark.parametrize(
    "value",
    [
        np.arange(6.0),
        np.arange(12.0)[::2],  # a strided view
        np.arange(6.0).astype(">f8"),  # big-endian: the general path
        np.arange(6),  # integers
        [0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
        np.array([0.0, 1.0, np.nan, 3.0, 4.0, 5.0]),
        np.array([0.0, 1.0, 2.0, -np.inf, 4.0, 5.0]),
        np.arange(5.0),
    ],
)
def test_vector_fast_path_equals_the_general_check(value: object) -> None:
    from codesign_mb.estimation.model_checks import _vector

    def general(v: object) -> np.ndarray:
        out = np.array(v, dtype=float)
        if out.shape != (6,):
            raise ValueError("shape")
        if not np.isfinite(out).all():
            raise ValueError("finite")
        return out

    try:
        expected = general(value)
    except ValueError:
        with pytest.raises(ValueError):
            _vector("z", value, 6)
        return
    out = _vector("z", value, 6)
    assert out.dtype == np.float64 and out.flags.c_contiguous and out.flags.owndata
    assert out.tobytes() == expected.tobytes()


def test_age_rounds_like_rint() -> None:
    from codesign_mb.estimation.base import split_networked_observation

    for age in (0.0, 1.0, 2.5, 3.5, 4.4999, 4.5000001, 1e6 + 0.5, 7.0 - 1e-12):
        _, got = split_networked_observation(np.array([1.0, age]))
        assert type(got) is int and got == int(np.rint(age))
