"""The abstract link against the paper's equations ``eq_time``, ``eq_output`` and ``eq_d``.

Hand-made delivery patterns use ``q`` in {0, 1} (delivery is then certain) and per-step
latencies, and are checked against a brute-force transcription of ``eq_time``::

    zeta_t = t - max{t' <= t : t' + tau_t' <= t, delta_t' = 1},

with the documented convention that before any delivery the prior, stamped ``t = -1``, is
held (age ``t + 1``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import pytest

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.network import (
    PRIOR_TIMESTAMP,
    BernoulliLink,
    LinkObservationWrapper,
    ObservationBuffer,
    Packet,
    QosRequest,
    Reception,
    reliability_cost,
)
from codesign_mb.plants.linear import LinearPlantEnv, double_integrator, scalar_unstable


def eq_time_reference(delivered: list[bool], tau: list[int]) -> list[int]:
    """Brute-force ``eq_time`` with the prior stamped ``PRIOR_TIMESTAMP`` before any delivery."""
    ages = []
    for t in range(len(delivered)):
        stamps = [s for s in range(t + 1) if delivered[s] and s + tau[s] <= t]
        ages.append(t - (max(stamps) if stamps else PRIOR_TIMESTAMP))
    return ages


def run_pattern(
    delivered: list[bool], tau: list[int], *, prior: Sequence[float] | None = (-1.0,)
) -> list[Reception]:
    """Send ``x_t = [10 t]`` over a BernoulliLink with q in {0, 1} and the given latencies."""
    link = BernoulliLink(seed=0)
    link.reset(prior=prior)
    return [
        link.step([10.0 * t], QosRequest(1.0 if d else 0.0, k))
        for t, (d, k) in enumerate(zip(delivered, tau, strict=True))
    ]


# ----------------------------------------------------------------------------- eq_time


def test_hand_made_pattern_with_out_of_order_arrivals() -> None:
    # Packet 0 (tau 3) arrives at t = 3, after the fresher packet 1 (tau 0): ignored.
    # Packet 3 (tau 2) arrives at t = 5, after the fresher packet 4 (tau 0): ignored.
    delivered = [True, True, False, True, True, False, False, True]
    tau = [3, 0, 0, 2, 0, 0, 0, 1]
    receptions = run_pattern(delivered, tau)
    assert [rx.age for rx in receptions] == [1, 0, 1, 2, 0, 1, 2, 3]
    assert eq_time_reference(delivered, tau) == [1, 0, 1, 2, 0, 1, 2, 3]
    # eq_output: y_t = x_{t - zeta_t}, the prior before the first delivery.
    assert [rx.observation[0] for rx in receptions] == [-1.0, 10, 10, 10, 40, 40, 40, 40]
    # The stale packets are still reported as arrivals (for out-of-sequence estimation).
    assert [p.timestamp for p in receptions[3].arrivals] == [0]
    assert not receptions[3].fresh
    assert [p.timestamp for p in receptions[5].arrivals] == [3]
    assert receptions[4].fresh and receptions[4].timestamp == 4
    assert [rx.delivered for rx in receptions] == delivered


@pytest.mark.parametrize("seed", range(5))
def test_random_patterns_follow_eq_time(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = 120
    delivered = [bool(d) for d in rng.random(T) < 0.6]
    tau = [int(k) for k in rng.integers(0, 6, T)]
    receptions = run_pattern(delivered, tau)
    ages = [rx.age for rx in receptions]
    assert ages == eq_time_reference(delivered, tau)
    for t, rx in enumerate(receptions):
        expected = -1.0 if rx.timestamp == PRIOR_TIMESTAMP else 10.0 * (t - rx.age)
        assert rx.observation[0] == expected  # eq_output
        assert rx.t == t
        # Every packet that arrives at t was sent at s with s + tau_s == t.
        assert all(p.timestamp + tau[p.timestamp] == t for p in rx.arrivals)


def test_simultaneous_arrivals_keep_the_freshest() -> None:
    # Packets 0 (tau 2) and 1 (tau 1) both arrive at t = 2; the max in eq_time keeps 1.
    receptions = run_pattern([True, True, False], [2, 1, 0])
    assert [rx.age for rx in receptions] == [1, 2, 1]
    assert [p.timestamp for p in receptions[2].arrivals] == [0, 1]
    assert receptions[2].observation[0] == 10.0


def test_pre_delivery_age_counts_from_episode_start() -> None:
    receptions = run_pattern([False] * 4 + [True], [0] * 5, prior=[7.0])
    assert [rx.age for rx in receptions] == [1, 2, 3, 4, 0]
    assert [rx.observation[0] for rx in receptions] == [7.0, 7.0, 7.0, 7.0, 40.0]
    assert receptions[0].timestamp == PRIOR_TIMESTAMP
    # Without a prior the held observation is zeros of the state's shape.
    bare = run_pattern([False, False], [0, 0], prior=None)
    assert [rx.age for rx in bare] == [1, 2]
    assert bare[1].observation.tolist() == [0.0]


def test_latency_alone_delays_by_tau() -> None:
    tau = 3
    receptions = run_pattern([True] * 10, [tau] * 10)
    assert [rx.age for rx in receptions] == [1, 2, 3] + [tau] * 7


# ----------------------------------------------------------------------------- eq_d


def test_delivery_is_bernoulli_q_and_seeded() -> None:
    q, n = 0.3, 20_000
    link = BernoulliLink(seed=123)
    link.reset(prior=[0.0])
    delivered = np.array([link.step([0.0], QosRequest(q)).delivered for _ in range(n)])
    sigma = math.sqrt(q * (1 - q) / n)
    assert abs(delivered.mean() - q) < 4 * sigma
    # Same seed, same channel; reset(seed=...) restarts the stream.
    link.reset(seed=123, prior=[0.0])
    again = np.array([link.step([0.0], QosRequest(q)).delivered for _ in range(n)])
    assert np.array_equal(delivered, again)


@pytest.mark.parametrize("q", [0.0, 1.0])
def test_reliability_extremes_are_deterministic(q: float) -> None:
    link = BernoulliLink(seed=5)
    link.reset(prior=[0.0])
    assert all(link.step([1.0], QosRequest(q)).delivered == bool(q) for _ in range(200))


# ----------------------------------------------------------------------------- QoS values


@pytest.mark.parametrize("reliability", [-0.1, 1.5, math.nan, math.inf, -math.inf])
def test_qos_rejects_bad_reliability(reliability: float) -> None:
    with pytest.raises(ValueError, match="reliability"):
        QosRequest(reliability, 0)
    with pytest.raises(ValueError, match="reliability"):
        StaticQos(reliability=reliability)


@pytest.mark.parametrize("latency", [-1, -5, 1.5])
def test_qos_rejects_bad_latency(latency: float) -> None:
    with pytest.raises(ValueError, match="latency_steps"):
        QosRequest(0.5, latency)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="latency_steps"):
        StaticQos(reliability=0.5, latency_steps=latency)  # type: ignore[arg-type]


def test_qos_accepts_the_closed_interval_and_costs_q() -> None:
    assert QosRequest(0, 0).reliability == 0.0  # 0 = "do not send"
    assert QosRequest(1, 4).latency_steps == 4
    assert reliability_cost(QosRequest(0.37, 2)) == 0.37  # C(q) = q


# ----------------------------------------------------------------------------- buffer


def test_buffer_handles_any_shape_and_copies() -> None:
    buffer = ObservationBuffer(prior=np.zeros((2, 3)))
    value = np.arange(6.0).reshape(2, 3)
    buffer.push(Packet(0, value), arrival_step=1)
    value[0, 0] = 99.0  # the buffer copied it on the way in
    rx0 = buffer.receive(0, delivered=True, like=value)
    assert rx0.age == 1 and rx0.observation.shape == (2, 3) and buffer.in_flight == 1
    rx1 = buffer.receive(1, delivered=False, like=value)
    assert rx1.age == 1 and rx1.observation[0, 0] == 0.0
    rx1.observation[0, 0] = -5.0  # and copies on the way out
    assert buffer.latest is not None and buffer.latest.value[0, 0] == 0.0


def test_buffer_rejects_arrival_before_capture() -> None:
    with pytest.raises(ValueError, match="arrival_step"):
        ObservationBuffer().push(Packet(5, np.zeros(1)), arrival_step=4)


# ----------------------------------------------------------------------------- wrapper


class RecordingQos:
    """A QoS policy that records what it sees and plays a latency schedule."""

    def __init__(self, reliabilities: list[float], latencies: list[int]) -> None:
        self.reliabilities, self.latencies = reliabilities, latencies
        self.seen: list[tuple[np.ndarray, int]] = []

    def reset(self, *, seed: int | None = None) -> None:
        self.seen = []

    def request(self, observation: np.ndarray, age: int) -> QosRequest:
        k = len(self.seen)
        self.seen.append((np.array(observation, copy=True), age))
        return QosRequest(self.reliabilities[k], self.latencies[k])


def test_wrapper_observation_is_eq_output_plus_age_and_policy_sees_previous() -> None:
    T = 40
    rng = np.random.default_rng(3)
    qs = [float(d) for d in rng.random(T + 1) < 0.7]
    taus = [int(k) for k in rng.integers(0, 4, T + 1)]
    base = LinearPlantEnv(double_integrator(), horizon=T, x0_mean=[0.5, 0.0])
    policy = RecordingQos(qs, taus)
    env = LinkObservationWrapper(base, BernoulliLink(), policy)
    assert env.observation_space.shape == (2,)  # p = 1 measurement + the age
    obs, info = env.reset(seed=11)
    sent = [info["remote_true"]]
    observations = [obs]
    infos = [info]
    for _ in range(T):
        obs, _, _, truncated, info = env.step(np.zeros(1))
        sent.append(info["remote_true"])
        observations.append(obs)
        infos.append(info)
        if truncated:
            break
    ages = eq_time_reference([q == 1.0 for q in qs], taus)
    prior = base.remote_prior()
    for t, (obs, info) in enumerate(zip(observations, infos, strict=True)):
        assert obs[-1] == ages[t] == info["age"]
        held = prior if t - ages[t] == PRIOR_TIMESTAMP else sent[t - ages[t]]
        np.testing.assert_array_equal(obs[:-1], held)  # eq_output
        assert info["qos_reliability"] == qs[t] and info["qos_latency_steps"] == taus[t]
        assert info["qos_cost"] == qs[t] and info["delivered"] == (qs[t] == 1.0)
    # eq_q_pol: the request at t sees (y_{t-1}, zeta_{t-1}); at reset the prior with age 0.
    np.testing.assert_array_equal(policy.seen[0][0], prior)
    assert policy.seen[0][1] == 0
    for t in range(1, len(observations)):
        np.testing.assert_array_equal(policy.seen[t][0], observations[t - 1][:-1])
        assert policy.seen[t][1] == ages[t - 1]


def test_wrapper_is_reproducible_from_reset_seed() -> None:
    def episode(seed: int) -> np.ndarray:
        env = LinkObservationWrapper(
            LinearPlantEnv(scalar_unstable(), horizon=30), BernoulliLink(), StaticQos(0.5, 1)
        )
        out = [env.reset(seed=seed)[0]]
        out += [env.step(np.array([0.1]))[0] for _ in range(29)]
        return np.array(out)

    np.testing.assert_array_equal(episode(4), episode(4))
    assert not np.array_equal(episode(4), episode(5))


def test_wrapper_rejects_a_plant_without_remote_state() -> None:
    with pytest.raises(TypeError, match="remote_slice"):
        LinkObservationWrapper(gym.make("Pendulum-v1"), BernoulliLink(), StaticQos())
