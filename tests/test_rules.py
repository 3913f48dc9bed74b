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


def _timeline(rule: CovarianceTriggeredQos, positions: np.ndarray, seed: int) -> list[float]:
    """The rule's requests over a belt trajectory, through a link that delivers what it asks."""
    link = BernoulliLink(seed=seed)
    link.reset(prior=positions[0])
    rule.reset()
    held, age = positions[0], 0
    requested = []
    for x in positions:
        qos = rule.request(held, age)
        requested.append(qos.reliability)
        rx = link.step(x, qos)
        held, age = rx.observation, rx.age
    return requested


def _belt(jump_at: int | None, steps: int = 60) -> np.ndarray:
    """Object positions at 0.2 m/s along +y (0.04 s steps), 0.6 m/s from step ``jump_at``."""
    speed = np.full(steps, 0.2)
    if jump_at is not None:
        speed[jump_at:] = 0.6
    y = np.concatenate([[0.0], np.cumsum(speed[:-1] * 0.04)])
    return np.column_stack([np.full(steps, 0.5), y - 0.4, np.full(steps, 0.1)])


def test_request_timeline_depends_on_belt_events() -> None:
    """A speed step changes when the gated rule asks; the covariance alone is one timetable."""
    options = {"threshold_m": 0.02, "low": 0.0, "latency_steps": 1}
    gated = [_timeline(_rule(**options, innovation_gate=0.99), _belt(s), 0) for s in (None, 25)]
    plain = [_timeline(_rule(**options), _belt(s), 0) for s in (None, 25)]
    assert plain[0] == plain[1]  # a linear filter's P depends on deliveries only
    assert gated[0] == plain[0]  # a belt that does what the model says surprises no one
    assert gated[1] != gated[0]
    first = next(t for t, (a, b) in enumerate(zip(*gated, strict=True)) if a != b)
    assert first > 25 and gated[1][first] == 1.0  # after the step, more requests, not fewer


def test_nis_is_chi_square_for_the_model_it_filters() -> None:
    """On data drawn from the predictor's own model, the packets' NIS average ~ p = 3."""
    rng = np.random.default_rng(5)
    predictor = DelayCompensatingPredictor(
        {"object_pos": slice(0, 3)},
        control_period_s=0.04,
        accel_std=0.5,
        position_noise_std=0.002,
        prior_position_std=0.1,
        prior_velocity_std=0.5,
    )
    A, Q, R = predictor.A, predictor.Q, predictor.R
    nis = []
    for _ in range(40):
        x = rng.multivariate_normal(np.zeros(6), predictor.prior_covariance)
        for t in range(30):
            z = x[:3] + rng.multivariate_normal(np.zeros(3), R)
            obs = np.append(z, 0.0)
            if t == 0:
                predictor.reset(obs)
            else:
                predictor.estimate(obs, np.zeros(0))
                nis.append(predictor.last_nis)
            x = A @ x + rng.multivariate_normal(np.zeros(6), Q)
    # 1160 draws of chi2(3): mean 3, standard error sqrt(6 / 1160) ~ 0.07
    assert abs(np.mean(nis) - 3.0) < 0.25


def test_last_nis_matches_the_innovation_formula() -> None:
    """NIS of a delayed packet: against the prior of the packet's own step, nu' S^-1 nu."""
    predictor = _predictor()
    predictor.reset(np.array([0, 0, 0, 0.5, -0.4, 0.1, 0.0]))
    predictor.estimate(np.array([0, 0, 0, 0.5, -0.4, 0.1, 1.0]), np.zeros(4))  # held, old
    predictor.estimate(np.array([0, 0, 0, 0.5, -0.4, 0.1, 2.0]), np.zeros(4))
    kf = predictor._kf
    prior_x, prior_P = kf._history[1].x_prior, kf._history[1].P_prior  # step 1's prior
    z = np.array([0.51, -0.39, 0.1])
    predictor.estimate(np.concatenate([np.zeros(3), z, [2.0]]), np.zeros(4))  # stamp 3-2 = 1
    nu = z - prior_x[:3]
    S = prior_P[:3, :3] + predictor.R
    assert predictor.last_nis == pytest.approx(float(nu @ np.linalg.solve(S, nu)), rel=1e-12)
