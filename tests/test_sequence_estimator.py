"""The Gaussian sequence estimator (stage B, issue 30) and the QoS features on its belief.

Checked against independent computations: the step-by-step estimates equal one batch pass
of the network over the episode's features (training and deployment see the same numbers);
the delivered-history features equal a hand count; a fit on the toy plant beats the stale
observation and its 95 % ellipsoids hold the truth about 95 % of the time (the coverage
:func:`estimator_mse` reports, recounted here); the belief a QoS feature reads through the
closed loop is the estimator's own; parallel collection gives the serial data.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.adaptation.belief_features import BeliefFeature
from codesign_mb.control.scripted import ToyPickController
from codesign_mb.core.registry import PlantSpec, make_plant
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.estimation.learned import load_estimator
from codesign_mb.estimation.sequence import GaussianSequenceEstimator, SequenceFeatures
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.rollout.loop import ClosedLoop
from codesign_mb.stages.episodes import (
    DelayDistribution,
    RandomQos,
    collect_episodes,
    estimator_mse,
)
from codesign_mb.stages.fitting import EstimatorTraining, fit_estimator, new_estimator

TOY = PlantSpec("toy", {"horizon": 40})
DELAYS = DelayDistribution(reliability_low=0.2, latency_high=3, perfect_probability=0.2)


@pytest.fixture(scope="module")
def toy_data():
    train = collect_episodes(TOY, ToyPickController(), RandomQos(DELAYS), episodes=40, seed=1)
    val = collect_episodes(TOY, ToyPickController(), RandomQos(DELAYS), episodes=12, seed=2)
    return train, val


@pytest.fixture(scope="module")
def fitted(toy_data):
    train, val = toy_data
    env = make_plant(TOY)
    est = new_estimator("sequence", env, hidden=32, age_scale=10.0, seed=0)
    settings = EstimatorTraining(epochs=60, sequence_batch_size=4, cosine_decay=True)
    curve = fit_estimator(est, train, val, settings, seed=0)
    env.close()
    return est, curve


def test_the_delivered_history_features_match_a_hand_count() -> None:
    f = SequenceFeatures(
        obs_dim=6, action_dim=1, remote_start=3, remote_stop=6, use_action=True, gripper_start=0
    )
    g = [0.1, 0.0, 0.0]
    episode = np.array(
        [
            [*g, 0.0, 0.0, 0.0, 0.0],  # t=0: the prior, age 0 (captured at 0)
            [*g, 0.0, 0.0, 0.0, 1.0],  # t=1: the same packet, age 1
            [*g, 0.0, 0.3, 0.0, 0.0],  # t=2: a packet captured at 2: 0.3 in 2 steps
            [*g, 0.0, 0.3, 0.0, 1.0],  # t=3: held
        ]
    )
    extra = f.sequence(episode)[:, f.in_dim - f.extra_dim :]
    fresh, rate, gap, relative = extra[:, 0], extra[:, 1:4], extra[:, 4], extra[:, 5:8]
    np.testing.assert_array_equal(fresh, [1, 0, 1, 0])
    np.testing.assert_allclose(rate[:, 1], [0, 0, 0.15, 0.15])
    np.testing.assert_allclose(gap, [0, 0, 0.2, 0.2])  # 2 steps over age_scale 10
    np.testing.assert_allclose(relative[2], [-0.1, 0.3, 0.0])


def test_step_by_step_estimates_equal_one_batch_pass(toy_data, fitted) -> None:
    est, _ = fitted
    nets = toy_data[1].networked[0].astype(np.float64)
    prevs = toy_data[1].prev_actions[0].astype(np.float64)
    steps = [est.reset(nets[0])]
    variances = [np.diag(est.covariance)]
    for t in range(1, len(nets)):
        steps.append(est.estimate(nets[t], prevs[t]))
        variances.append(np.diag(est.covariance))
    x = torch.as_tensor(est.features.sequence(nets, prevs))[None]
    with torch.no_grad():
        mean, log_var, _ = est.net(x)
    scale = est.net.out_std.numpy()
    f = est.features
    expected = nets[:, f.remote_slice] + mean[0].numpy() * scale
    np.testing.assert_allclose(np.asarray(steps)[:, f.target_slice], expected, atol=1e-5)
    np.testing.assert_allclose(variances, np.exp(log_var[0].numpy()) * scale**2, rtol=1e-4)


def test_a_fitted_sequence_estimator_beats_the_stale_observation_and_is_calibrated(
    toy_data, fitted
) -> None:
    est, curve = fitted
    val = toy_data[1]
    assert curve[-1]["train_loss"] < curve[0]["train_loss"]
    env = make_plant(TOY)
    kw = {"remote": env.remote_slice, "position": env.observation_layout["object_pos"]}
    learned = estimator_mse(est, val, **kw)
    stale = estimator_mse(PassThroughEstimator(), val, **kw)
    assert learned["mse_position"] < 0.5 * stale["mse_position"]
    assert "coverage_position" not in stale  # no Gaussian, no coverage
    # coverage recounted: the true position inside the 95 % ellipsoid of the 3-D position
    inside = []
    for nets, prevs, truth in zip(val.networked, val.prev_actions, val.truth, strict=True):
        nets = nets.astype(np.float64)
        for t in range(len(nets)):
            if t == 0:
                est.reset(nets[0])
            else:
                est.estimate(nets[t], prevs[t].astype(np.float64))
            err = est.state[:3] - truth[t, :3]
            inside.append(err @ np.linalg.solve(est.covariance[:3, :3], err) <= chi2.ppf(0.95, 3))
    assert learned["coverage_position"] == pytest.approx(np.mean(inside))
    assert 0.8 <= learned["coverage_position"] <= 1.0


def test_save_and_load_give_the_same_estimates(toy_data, fitted, tmp_path) -> None:
    est, _ = fitted
    est.save(tmp_path / "seq.pt")
    again = load_estimator(tmp_path / "seq.pt")
    assert isinstance(again, GaussianSequenceEstimator)
    nets = toy_data[1].networked[1].astype(np.float64)
    np.testing.assert_array_equal(est.reset(nets[0]), again.reset(nets[0]))
    for t in range(1, len(nets)):
        action = np.zeros(4)
        np.testing.assert_array_equal(
            est.estimate(nets[t], action), again.estimate(nets[t], action)
        )
        np.testing.assert_array_equal(est.covariance, again.covariance)


class _BeliefQos(StaticQos):
    """A static policy whose request also records the belief features it would read."""

    def __init__(self, feature: BeliefFeature) -> None:
        super().__init__(reliability=1.0, latency_steps=0)
        self.feature = feature
        self.seen: list[np.ndarray] = []

    def bind_belief(self, belief) -> None:
        self.feature.bind_belief(belief)

    def reset(self, *, seed=None) -> None:
        self.feature.reset()

    def request(self, observation, age):
        self.seen.append(self.feature(observation, age))
        return super().request(observation, age)


def test_the_closed_loop_binds_the_robots_estimator_to_belief_features(fitted) -> None:
    est, _ = fitted
    plant = make_plant(TOY)
    feature = BeliefFeature.from_env(plant)
    qos = _BeliefQos(feature)
    env = LinkObservationWrapper(plant, BernoulliLink(), qos)
    loop = ClosedLoop(env, est, ToyPickController(), record=False)
    loop.reset(seed=3)
    beliefs = []
    for _ in range(5):
        beliefs.append((est.state.copy(), np.diag(est.covariance).copy(), est.output.copy()))
        loop.step()
    # the request of step t + 1 reads the estimate made at step t
    assert feature.dim == 17  # the toy has a gripper: its relative position and the fingers
    for (mean, var, out), seen in zip(beliefs, qos.seen[1:], strict=False):
        np.testing.assert_allclose(seen[1:7], np.log10(np.sqrt(var[:6]) / feature._scales))
        np.testing.assert_allclose(seen[7:10], mean[3:6] / feature.speed_scale_mps)
        np.testing.assert_allclose(seen[13:16], (mean[:3] - out[0:3]) / feature.position_scale_m)
        np.testing.assert_allclose(seen[16], out[6] / feature.finger_scale_m)
    np.testing.assert_allclose(qos.seen[0][1:7], feature._prior)  # the reset's: the prior
    with pytest.raises(ValueError, match="state and covariance"):
        ClosedLoop(env, PassThroughEstimator(), ToyPickController())
    env.close()


def test_parallel_collection_gives_the_serial_data() -> None:
    qos = RandomQos(DELAYS)
    serial = collect_episodes(TOY, ToyPickController(), qos, episodes=6, seed=4)
    parallel = collect_episodes(TOY, ToyPickController(), qos, episodes=6, seed=4, workers=2)
    assert len(parallel) == len(serial) == 6
    for a, b in zip(serial.networked, parallel.networked, strict=True):
        np.testing.assert_array_equal(a, b)
    assert serial.success == parallel.success


def test_perfect_episodes_have_the_oracle_link() -> None:
    qos = RandomQos(DelayDistribution(perfect_probability=1.0))
    data = collect_episodes(TOY, ToyPickController(), qos, episodes=2, seed=5)
    for nets, reliability in zip(data.networked, data.reliability, strict=True):
        assert np.all(reliability == 1.0)
        assert np.all(nets[:, -1] == 0.0)  # every packet arrives fresh
