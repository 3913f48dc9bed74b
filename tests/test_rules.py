"""The model-based QoS rule: its replica knows the robot's covariance; bisection tuning."""

from __future__ import annotations

import math

import numpy as np
import pytest

from codesign_mb.adaptation.rules import CovarianceTriggeredQos, tune_threshold
from codesign_mb.estimation.predictor import DelayCompensatingPredictor
from codesign_mb.network import BernoulliLink, QosRequest
from codesign_mb.rollout.compose import covariance_rule_on

LAYOUT = {"gripper_pos": slice(0, 3), "object_pos": slice(3, 6)}


PREDICTOR = {"prior_velocity": (0.0, 0.2, 0.0), "accel_std": 0.5}


def _predictor() -> DelayCompensatingPredictor:
    return DelayCompensatingPredictor(LAYOUT, control_period_s=0.04, **PREDICTOR)


def _rule(**options: float) -> CovarianceTriggeredQos:
    return covariance_rule_on(
        {"object_pos": slice(0, 3)},
        0.04,
        predictor_options=PREDICTOR,
        **options,
    )


def test_replica_covariance_is_the_robots() -> None:
    """Fed the same (y, zeta) stream one step later, the rule's P equals the robot's P."""
    rule = _rule(threshold_m=0.01, low=0.0, latency_steps=1)
    robot = _predictor()
    link = BernoulliLink(seed=3)
    prior = np.array([0.5, -0.4, 0.1])
    link.reset(prior=prior)
    rule.reset()
    held, age = prior, 0
    robot_covs: list[np.ndarray] = []
    requests: list[QosRequest] = []
    for t in range(40):
        qos = rule.request(held, age)
        requests.append(qos)
        if t >= 2:
            # request for packet t was made from (y_{t-1}, zeta_{t-1}): the robot's P_{t-1}
            np.testing.assert_allclose(rule.predictor.covariance, robot_covs[t - 1], rtol=1e-12)
        x = prior + np.array([0.0, 0.008 * (t + 1), 0.0])
        rx = link.step(x, qos)
        obs = np.concatenate([np.zeros(3), rx.observation, [rx.age]])
        if t == 0:
            robot.reset(obs)
        else:
            robot.estimate(obs, np.zeros(4))
        robot_covs.append(robot.covariance)
        held, age = rx.observation, rx.age
    qs = np.array([r.reliability for r in requests])
    assert qs[0] == 1.0  # only the prior is held: its std (0.17 m) is above the threshold
    assert 0 < qs.mean() < 1  # the trigger fires now and then, not always


def test_lifted_object_gets_the_lift_reliability() -> None:
    rule = _rule(threshold_m=1e-6, low=0.05, lift_margin_m=0.03)
    rule.reset()
    assert rule.request(np.array([0.5, 0.0, 0.1]), 0).reliability == 1.0  # the prior
    assert rule.request(np.array([0.5, 0.0, 0.1]), 0).reliability == 1.0  # on the belt
    assert rule.request(np.array([0.5, 0.0, 0.2]), 0).reliability == 0.05  # lifted
    assert rule.request(np.array([0.5, 0.0, 0.1]), 1).reliability == 0.05  # latched


@pytest.mark.parametrize(
    ("field", "value"),
    [("threshold_m", -0.01), ("lift_margin_m", 0.0), ("latency_steps", 0)],
)
def test_bad_rule_settings_name_the_field(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        _rule(**{field: value})


def test_tune_threshold_finds_the_success_boundary() -> None:
    """Success falls past 0.02 m; bisection converges to it from below."""
    calls: list[float] = []

    def measure(threshold: float) -> tuple[float, float]:
        calls.append(threshold)
        return (1.0 if threshold <= 0.02 else 0.5), 0.1 / threshold

    best, probes = tune_threshold(measure, target_success=0.98, low=1e-3, high=1.0, iterations=12)
    assert best <= 0.02
    assert math.isclose(best, 0.02, rel_tol=0.01)
    assert len(probes) == len(calls) == 12
    assert all(p.success_rate >= 0.98 for p in probes if p.threshold <= best)
