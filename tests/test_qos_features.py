"""The learned QoS policy's inputs: ``predictor_std`` (the robot's predictor uncertainty,
seen from the edge), the elapsed time and the interface."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from codesign_mb.adaptation.learned import (
    ElapsedTimeFeature,
    LearnedQosPolicy,
    PredictorStdFeature,
    QosFeatures,
    QosInterface,
    make_features,
)
from codesign_mb.core.registry import ComponentSpec, PlantSpec, make_plant
from codesign_mb.network import BernoulliLink
from codesign_mb.network.qos import QosRequest
from codesign_mb.rollout.compose import covariance_rule_on, predictor_replica_on
from codesign_mb.stages.dual_ascent import DualAscent
from codesign_mb.stages.qos_env import QosEnvConfig
from codesign_mb.stages.stage import StageRun
from codesign_mb.stages.stage_c import StageCConfig, make_qos_env, train_stage_c
from codesign_mb.stages.training import SacSpec

LAYOUT = {"object_pos": slice(0, 3), "object_vel": slice(3, 6)}
PREDICTOR = {"prior_velocity": (0.0, 0.2, 0.0), "accel_std": 0.5}
PRIOR = np.array([0.5, -0.45, 0.08, 0.0, 0.2, 0.0])
TOY = PlantSpec("toy", {"horizon": 40})


def _feature(**options: object) -> PredictorStdFeature:
    replica = predictor_replica_on(LAYOUT, 0.04, predictor_options=PREDICTOR)
    return PredictorStdFeature(replica, horizon=100, **options)


def _state(t: int, z: float = 0.08) -> np.ndarray:
    return PRIOR + np.array([0.0, 0.2 * 0.04 * t, z - PRIOR[2], 0.0, 0.0, 0.0])


def test_dimension_and_options() -> None:
    feature = _feature()
    assert isinstance(feature, QosFeatures)
    assert feature.dim == 3
    feature.reset()
    assert feature(PRIOR, 0).shape == (3,)
    for options, dim in (({"lift_indicator": False}, 2), ({"elapsed_time": False}, 2)):
        f = _feature(**options)
        f.reset()
        assert f.dim == dim and f(PRIOR, 0).shape == (dim,)
    with pytest.raises(ValueError, match="elapsed_time needs a horizon"):
        PredictorStdFeature(predictor_replica_on(LAYOUT, 0.04))
    with pytest.raises(ValueError, match="scale_m"):
        _feature(scale_m=0.0)


def test_the_prior_is_uncertain_and_a_delivery_is_not() -> None:
    feature = _feature()
    feature.reset()
    first = feature(PRIOR, 0)  # t = 0: only the prior is held
    prior_std = 0.1 * math.sqrt(3)  # the predictor's prior: 0.1 m per axis
    assert first[0] > math.log10(prior_std / 0.01)  # propagated two steps ahead: larger
    assert first[2] == 0.0
    fresh = feature(_state(0), 0)  # packet 0 delivered at once
    assert fresh[0] < 0.0  # below 1 cm once measured (2 mm perception noise)
    assert fresh[2] == pytest.approx(0.01)


def test_grows_with_age_when_packets_are_lost() -> None:
    feature = _feature()
    feature.reset()
    feature(PRIOR, 0)
    feature(_state(0), 0)
    stds = [feature(_state(0), age)[0] for age in range(1, 30)]  # nothing new arrives
    assert np.all(np.diff(stds) > 0)
    assert stds[-1] > 0.5  # past 3 cm after ~30 lost packets
    assert feature(_state(30), 1)[0] < stds[0]  # a delivery brings it down again


def test_lift_indicator_latches_and_reset_clears_everything() -> None:
    feature = _feature()
    fresh = _feature()
    feature.reset()
    fresh.reset()
    feature(PRIOR, 0)
    feature(_state(0), 0)
    for age in range(1, 10):
        feature(_state(0), age)
    assert feature(_state(10, z=0.2), 0)[1] == 1.0  # held object 12 cm up: lifted
    assert feature(_state(10), 1)[1] == 1.0  # latched
    feature.reset()
    for t in range(4):  # the same stream after reset() as from a fresh feature
        held, age = (PRIOR, t) if t < 2 else (_state(1), t - 2)
        np.testing.assert_array_equal(feature(held, age), fresh(held, age))


def test_uncertainty_is_what_the_covariance_rule_thresholds() -> None:
    """Same stream: the feature's log-uncertainty crosses log10(threshold) where the rule fires."""
    threshold = 0.03
    rule = covariance_rule_on(
        LAYOUT, 0.04, threshold_m=threshold, low=0.0, predictor_options=PREDICTOR
    )
    feature = _feature()
    link = BernoulliLink(seed=1)
    link.reset(prior=PRIOR)
    rule.reset()
    feature.reset()
    held, age, fired = PRIOR, 0, 0
    for t in range(100):
        q = rule.request(held, age)
        f = feature(held, age)
        assert f[0] == pytest.approx(math.log10(rule.position_std_ahead(2) / 0.01))
        if t > 0:
            assert (q.reliability == 1.0) == (f[0] > math.log10(threshold / 0.01))
        fired += q.reliability == 1.0
        rx = link.step(_state(t), QosRequest(0.3, 1))
        held, age = rx.observation, rx.age
    assert 1 < fired < 100


def test_builds_by_name_for_a_plant_and_in_the_qos_env() -> None:
    plant = make_plant(TOY)
    feature = make_features("predictor_std", plant, {"elapsed_time": False})
    assert isinstance(feature, PredictorStdFeature) and feature.dim == 2
    config = StageCConfig(
        plant=TOY,
        controller=ComponentSpec("toy_pick"),
        estimator=ComponentSpec("predictor"),
        features="predictor_std",
    )
    env = make_qos_env(config)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (6 + 1 + 3,)
    for _ in range(5):
        obs, *_ = env.step(np.array([-1.0]))  # q = 0: nothing is delivered
    assert obs[-1] == pytest.approx(5 / 40)
    env.close()


def test_stage_c_with_predictor_std_round_trips(tmp_path) -> None:
    config = StageCConfig(
        plant=TOY,
        controller=ComponentSpec("toy_pick"),
        estimator=ComponentSpec("predictor"),
        features="predictor_std",
        feature_options={"scale_m": 0.02},
        sac=SacSpec(net_arch=(16, 16), buffer_size=1_000, batch_size=16, learning_starts=20),
        total_steps=60,
        chunk_steps=60,
        eval_episodes=1,
        dual=DualAscent(enabled=False),
    )
    train_stage_c(config, StageRun(tmp_path / "out", tmp_path / "work"))
    meta = json.loads((tmp_path / "out" / "qos_policy.json").read_text())
    assert meta["features"] == {"kind": "predictor_std", "options": {"scale_m": 0.02}}
    policy = LearnedQosPolicy.from_env(make_plant(TOY), tmp_path / "out")
    assert isinstance(policy.features, PredictorStdFeature) and policy.features.scale_m == 0.02
    policy.reset()
    request = policy.request(make_plant(TOY).remote_prior(), 0)
    assert 0.0 <= request.reliability <= 1.0


def test_qos_interface_and_features() -> None:
    iface = QosInterface(remote_dim=2, feature_dim=1, learn_latency=True, max_latency_steps=4)
    assert iface.request(np.array([1.0, -1.0])) == QosRequest(1.0, 0)
    assert iface.request(np.array([-1.0, 1.0])) == QosRequest(0.0, 4)
    feature = ElapsedTimeFeature(horizon=10)
    obs = iface.observation(np.zeros(2), 5, feature(np.zeros(2), 5))
    np.testing.assert_allclose(obs, [0, 0, 0.5, 0.0])
    with pytest.raises(ValueError, match="extra features"):
        iface.observation(np.zeros(2), 0)
    with pytest.raises(ValueError, match="loss must be one of"):
        QosEnvConfig(loss="nope")
