"""The intermittent Kalman filter and the linear plants against theory.

- ``q = 1``, no delay: ``P`` converges to the stationary Riccati solution (``control.dlqe``,
  ``scipy.linalg.solve_discrete_are``).
- Scalar ``|a| > 1``: ``E[P_t]`` stays bounded for ``q > 1 - 1/a^2`` and grows without bound
  below (Sinopoli et al. 2004), between the theorem's bounds when it is bounded.
- Delayed and out-of-sequence updates equal re-filtering the same data in time order.
"""

from __future__ import annotations

import math
import warnings

import control
import numpy as np
import pytest
import scipy.linalg
from gymnasium.utils.env_checker import check_env

from codesign_mb.core import registry
from codesign_mb.estimation.kalman import (
    IntermittentKalmanFilter,
    KalmanEstimator,
    critical_arrival_bounds,
    critical_arrival_lower_bound,
    expected_covariance_bounds,
    intermittent_riccati,
    steady_state_covariance,
)
from codesign_mb.network import BernoulliLink, LinkObservationWrapper, QosRequest
from codesign_mb.plants.linear import (
    LinearPlantEnv,
    LinearPlantSpec,
    double_integrator,
    inverted_pendulum,
    make_linear_plant,
    scalar_unstable,
)

A_SCALAR = 1.2
Q_CRIT = 1.0 - 1.0 / A_SCALAR**2  # Sinopoli et al. (2004) for C invertible


def random_model(seed: int, n: int = 3, p: int = 2, m: int = 1) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n)) / math.sqrt(n) + 0.3 * np.eye(n)
    Lq = rng.normal(size=(n, n)) * 0.3
    Lr = rng.normal(size=(p, p)) * 0.3
    return {
        "A": A,
        "C": rng.normal(size=(p, n)),
        "Q": Lq @ Lq.T + 0.05 * np.eye(n),
        "R": Lr @ Lr.T + 0.05 * np.eye(p),
        "B": rng.normal(size=(n, m)),
    }


# ----------------------------------------------------------------------------- shapes


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("A", np.ones((2, 3))),
        ("C", np.ones((1, 3))),
        ("Q", np.eye(3)),
        ("R", np.eye(2)),
        ("B", np.ones((3, 1))),
        ("Q", np.array([[1.0, 0.5], [0.0, 1.0]])),  # not symmetric
        ("R", np.array([[-1.0]])),  # not PSD
        ("A", np.array([[np.nan, 0.0], [0.0, 1.0]])),
    ],
)
def test_filter_rejects_bad_matrices_by_name(field: str, value: np.ndarray) -> None:
    good = {"A": np.eye(2), "C": np.ones((1, 2)), "Q": np.eye(2), "R": np.eye(1), "B": np.ones(2)}
    good[field] = value
    with pytest.raises(ValueError, match=rf"^{field} "):
        IntermittentKalmanFilter(**good)


def test_filter_rejects_bad_calls() -> None:
    kf = IntermittentKalmanFilter(np.eye(2), [[1.0, 0.0]], np.eye(2), [[1.0]])
    with pytest.raises(RuntimeError, match="reset"):
        kf.predict()
    with pytest.raises(ValueError, match="x0"):
        kf.reset([0.0], np.eye(2))
    with pytest.raises(ValueError, match="P0"):
        kf.reset([0.0, 0.0], np.eye(3))
    kf.reset([0.0, 0.0], np.eye(2))
    with pytest.raises(ValueError, match="timestamp"):
        kf.update([1.0], timestamp=1)  # the future
    with pytest.raises(ValueError, match="timestamp"):
        kf.update([1.0], timestamp=-1)
    with pytest.raises(ValueError, match="z "):
        kf.update([1.0, 2.0], timestamp=0)
    with pytest.raises(ValueError, match="B"):
        kf.predict(u=[1.0])
    with pytest.raises(ValueError, match="max_delay_steps"):
        IntermittentKalmanFilter(1.0, 1.0, 1.0, 1.0, max_delay_steps=-1)


@pytest.mark.parametrize(
    ("field", "kwargs"),
    [
        ("A", {"A": np.ones((2, 3))}),
        ("B", {"B": np.ones((3, 1))}),
        ("C", {"C": np.ones((1, 3))}),
        ("W", {"W": np.eye(3)}),
        ("V", {"V": np.eye(2)}),
        ("W", {"W": -np.eye(2)}),
        ("dt", {"dt": 0.0}),
    ],
)
def test_plant_spec_rejects_bad_fields_by_name(field: str, kwargs: dict) -> None:
    good = {"A": np.eye(2), "B": np.ones((2, 1)), "C": np.ones((1, 2)), "W": np.eye(2)}
    good.update(V=np.eye(1), dt=0.04)
    good.update(kwargs)
    with pytest.raises(ValueError, match=rf"^{field} "):
        LinearPlantSpec(name="bad", **good)


@pytest.mark.parametrize(
    ("field", "kwargs"),
    [
        ("state_cost", {"state_cost": np.eye(3)}),
        ("input_cost", {"input_cost": np.zeros((1, 1))}),
        ("x0_mean", {"x0_mean": [0.0, 0.0, 0.0]}),
        ("x0_cov", {"x0_cov": np.eye(1)}),
        ("horizon", {"horizon": 0}),
        ("action_bound", {"action_bound": -1.0}),
    ],
)
def test_env_rejects_bad_settings_by_name(field: str, kwargs: dict) -> None:
    with pytest.raises(ValueError, match=rf"^{field} "):
        LinearPlantEnv(double_integrator(), **kwargs)


# ----------------------------------------------------------------------------- plants


def test_plants_are_the_sampled_continuous_models() -> None:
    dt = 0.04
    di = double_integrator(accel_noise_std=2.0, dt=dt)
    np.testing.assert_allclose(di.A, [[1, dt], [0, 1]], atol=1e-15)
    np.testing.assert_allclose(di.B, [[dt**2 / 2], [dt]], rtol=1e-12)
    # White acceleration of intensity s^2: W = s^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]].
    np.testing.assert_allclose(di.W, 4.0 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]))
    pend = inverted_pendulum(cart_mass=1.0, pole_mass=0.1, pole_length=0.5, gravity=9.81)
    assert pend.system.isdtime(strict=True) and pend.system.dt == dt
    unstable = math.exp(math.sqrt(1.1 * 9.81 / 0.5) * dt)
    assert pend.spectral_radius == pytest.approx(unstable, rel=1e-12)
    assert critical_arrival_lower_bound(pend.A) == pytest.approx(1 - unstable**-2, rel=1e-12)
    assert set(registry.kinds("linear_plant")) == {"scalar", "double_integrator", "pendulum"}
    with pytest.raises(ValueError, match="plant"):
        make_linear_plant("segway")


@pytest.mark.parametrize("name", sorted(registry.kinds("linear_plant")))
def test_env_passes_check_env_and_reports_the_truth(name: str) -> None:
    env = LinearPlantEnv(make_linear_plant(name), horizon=20)
    with warnings.catch_warnings():
        # Unbounded Box spaces are intended (a linear plant has no natural bounds).
        warnings.filterwarnings("ignore", message=".*infinity.*")
        warnings.filterwarnings("ignore", message=".*normalized space.*")
        check_env(env, skip_render_check=True)
    plant = env.plant
    _, info = env.reset(seed=3)
    x = info["state"]
    u = np.full(plant.n_inputs, 0.3)
    z1, reward, terminated, truncated, info1 = env.step(u)
    expected_cost = x @ env.state_cost @ x + u @ env.input_cost @ u
    assert reward == pytest.approx(-expected_cost) and info1["stage_cost"] == -reward
    assert not terminated and not truncated
    # The measurement is C x + v, with v ~ N(0, V): small for these sensors.
    assert z1.shape == (plant.n_outputs,)
    np.testing.assert_array_equal(env.remote_prior(), plant.C @ env.x0_mean)
    assert env.remote_slice == slice(0, plant.n_outputs)


def test_env_is_seeded_only_through_reset() -> None:
    env = LinearPlantEnv(scalar_unstable(), horizon=5)
    a = [env.reset(seed=9)[0]] + [env.step([0.0])[0] for _ in range(4)]
    b = [env.reset(seed=9)[0]] + [env.step([0.0])[0] for _ in range(4)]
    np.testing.assert_array_equal(a, b)
    assert env.step([0.0])[3] is True  # truncated at the horizon (5 steps)


# ----------------------------------------------------------------------------- q = 1


@pytest.mark.parametrize("name", ["scalar", "pendulum"])
def test_full_arrivals_converge_to_the_riccati_solution(name: str) -> None:
    plant = make_linear_plant(name)
    kf = IntermittentKalmanFilter(plant.A, plant.C, plant.W, plant.V, plant.B)
    kf.reset(np.zeros(plant.n_states), np.eye(plant.n_states))
    for t in range(600):
        kf.update(np.zeros(plant.n_outputs), timestamp=t)
        posterior = kf.P
        kf.predict(np.zeros(plant.n_inputs))
    prior = kf.P
    _, P_dlqe, _ = control.dlqe(plant.A, np.eye(plant.n_states), plant.C, plant.W, plant.V)
    P_dare = scipy.linalg.solve_discrete_are(plant.A.T, plant.C.T, plant.W, plant.V)
    np.testing.assert_allclose(prior, P_dlqe, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(prior, P_dare, rtol=1e-8, atol=1e-12)
    prior_ss, posterior_ss = steady_state_covariance(plant.A, plant.C, plant.W, plant.V)
    np.testing.assert_allclose(posterior, posterior_ss, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(prior_ss, P_dare, rtol=1e-12, atol=1e-15)


def test_lost_observation_is_prediction_only() -> None:
    model = random_model(0)
    kf = IntermittentKalmanFilter(**model)
    x0, P0 = np.array([1.0, -2.0, 0.5]), np.eye(3)
    kf.reset(x0, P0)
    kf.predict([0.7])
    np.testing.assert_allclose(kf.x, model["A"] @ x0 + model["B"] @ [0.7], rtol=1e-15)
    np.testing.assert_allclose(kf.P, model["A"] @ P0 @ model["A"].T + model["Q"], rtol=1e-14)
    assert kf.t == 1


# ----------------------------------------------------------------------------- Sinopoli


def test_filter_covariance_equals_the_vectorised_recursion() -> None:
    model = random_model(1)
    rng = np.random.default_rng(1)
    arrivals = rng.random((25, 30)) < 0.5
    P0 = np.eye(3)
    priors, posteriors = intermittent_riccati(
        model["A"], model["C"], model["Q"], model["R"], P0, arrivals
    )
    for i, gamma in enumerate(arrivals):
        kf = IntermittentKalmanFilter(model["A"], model["C"], model["Q"], model["R"])
        kf.reset(np.zeros(3), P0)
        for t, arrived in enumerate(gamma):
            if arrived:
                kf.update(np.zeros(2), timestamp=t)
            np.testing.assert_allclose(kf.P, posteriors[i, t], rtol=1e-12, atol=1e-14)
            kf.predict()
            np.testing.assert_allclose(kf.P, priors[i, t + 1], rtol=1e-12, atol=1e-14)
    mean_priors, _ = intermittent_riccati(
        model["A"], model["C"], model["Q"], model["R"], P0, arrivals, average=True
    )
    np.testing.assert_allclose(mean_priors, priors.mean(axis=0), rtol=1e-12)


def monte_carlo_prior(q: float, *, n: int = 20_000, steps: int = 40, seed: int = 0) -> np.ndarray:
    """``E[P_{t|t-1}]`` for t = 0..steps of the scalar plant, Monte-Carlo over arrivals."""
    gamma = np.random.default_rng(seed).random((n, steps)) < q
    priors, _ = intermittent_riccati(A_SCALAR, 1.0, 1.0, 1.0, [[1.0]], gamma, average=True)
    return priors[:, 0, 0]


def test_expected_covariance_is_bounded_above_the_critical_probability() -> None:
    q = 0.6
    assert q > Q_CRIT
    mean_p = monte_carlo_prior(q)
    # Stationary already: the second half does not grow.
    assert mean_p[-1] == pytest.approx(mean_p[20], rel=0.1)
    # Sinopoli Thm 3-4: S <= lim E[P] <= V (MARE fixed point); 5 % Monte-Carlo slack.
    lower, upper = expected_covariance_bounds(A_SCALAR, 1.0, 1.0, 1.0, q)
    assert math.isfinite(upper[0, 0]) and lower[0, 0] < upper[0, 0]
    tail = mean_p[20:].mean()
    assert 0.95 * lower[0, 0] <= tail <= 1.05 * upper[0, 0]


def test_expected_covariance_diverges_below_the_critical_probability() -> None:
    q = 0.1
    assert (1 - q) * A_SCALAR**2 > 1  # i.e. q < 1 - 1/a^2
    mean_p = monte_carlo_prior(q)
    # Geometric growth at the rate (1 - q) a^2 = 1.296 per step: x180 over 20 steps.
    assert mean_p[40] / mean_p[20] > 50
    # And above Sinopoli's lower-bound sequence S_{t+1} = (1 - q) a^2 S_t + w, which -> inf.
    S = [1.0]
    for _ in range(40):
        S.append((1 - q) * A_SCALAR**2 * S[-1] + 1.0)
    assert np.all(mean_p >= 0.8 * np.array(S))
    lower, upper = expected_covariance_bounds(A_SCALAR, 1.0, 1.0, 1.0, q)
    assert np.isinf(lower).all() and np.isinf(upper).all()


def test_critical_probability_bounds() -> None:
    lower, upper = critical_arrival_bounds([[A_SCALAR]], [[1.0]], tol=1e-4)
    assert lower == pytest.approx(Q_CRIT, rel=1e-12)
    assert upper == pytest.approx(Q_CRIT, abs=2e-4)  # C invertible: the bounds coincide
    assert critical_arrival_bounds([[0.9]], [[1.0]]) == (0.0, 0.0)  # stable: any q
    # Not detectable: no reliability is enough.
    assert critical_arrival_bounds(np.diag([1.2, 1.1]), [[1.0, 0.0]])[1] == math.inf


# ----------------------------------------------------------------------------- delays


def arrival_schedule(seed: int, steps: int, max_delay: int) -> dict[int, list[int]]:
    """Arrival step -> timestamps arriving then (shuffled: out of sequence); ~20 % lost."""
    rng = np.random.default_rng(seed)
    schedule: dict[int, list[int]] = {}
    for s in range(steps):
        if rng.random() < 0.2:
            continue
        schedule.setdefault(s + int(rng.integers(0, max_delay + 1)), []).append(s)
    for stamps in schedule.values():
        rng.shuffle(stamps)
    return schedule


def refilter_in_time_order(
    model: dict, x0, P0, zs, us, used: list[int], until: int, As=None
) -> IntermittentKalmanFilter:
    """A fresh filter fed ``used`` measurements at their own steps, in time order."""
    kf = IntermittentKalmanFilter(**model)
    kf.reset(x0, P0)
    for t in range(until + 1):
        for s in used:  # ``used`` is in arrival order: the per-step order is kept
            if s == t:
                kf.update(zs[s], timestamp=s)
        if t < until:
            kf.predict(us[t], A=None if As is None else As[t])
    return kf


@pytest.mark.parametrize("time_varying", [False, True])
def test_delayed_and_out_of_sequence_updates_equal_refiltering(time_varying: bool) -> None:
    model = random_model(2)
    rng = np.random.default_rng(2)
    T = 60
    zs = rng.normal(size=(T, 2))
    us = rng.normal(size=(T, 1))
    As = [model["A"] * (1 + 0.1 * math.sin(t)) for t in range(T)] if time_varying else None
    x0, P0 = np.zeros(3), 2.0 * np.eye(3)
    schedule = arrival_schedule(seed=2, steps=T, max_delay=6)
    online = IntermittentKalmanFilter(**model, max_delay_steps=8)
    online.reset(x0, P0)
    used: list[int] = []
    out_of_sequence = 0
    for t in range(T):
        for s in schedule.get(t, []):
            out_of_sequence += bool(used) and s < max(used)
            assert online.update(zs[s], timestamp=s)
            used.append(s)
        reference = refilter_in_time_order(model, x0, P0, zs, us, used, t, As)
        np.testing.assert_allclose(online.x, reference.x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(online.P, reference.P, rtol=0, atol=1e-10)
        online.predict(us[t], A=None if As is None else As[t])
    assert out_of_sequence > 5  # the schedule did exercise out-of-sequence arrivals


def test_window_drops_measurements_that_are_too_old() -> None:
    model = random_model(3)
    kf = IntermittentKalmanFilter(**model, max_delay_steps=3)
    kf.reset(np.zeros(3), np.eye(3))
    for _ in range(10):
        kf.predict([0.0])
    assert kf.oldest_timestamp == 7
    x, P = kf.x, kf.P
    assert kf.update([1.0, 1.0], timestamp=6) is False
    np.testing.assert_array_equal(kf.x, x)
    np.testing.assert_array_equal(kf.P, P)
    assert kf.n_dropped == 1
    assert kf.update([1.0, 1.0], timestamp=7) is True
    assert np.trace(kf.P) < np.trace(P)


# ----------------------------------------------------------------------------- estimator


class ScheduleQos:
    """Deterministic QoS: q in {0, 1} and latency from fixed lists."""

    def __init__(self, delivered: list[bool], tau: list[int]) -> None:
        self.delivered, self.tau, self.k = delivered, tau, 0

    def reset(self, *, seed: int | None = None) -> None:
        self.k = 0

    def request(self, observation: np.ndarray, age: int) -> QosRequest:
        k, self.k = self.k, self.k + 1
        return QosRequest(float(self.delivered[k]), self.tau[k])


@pytest.mark.parametrize("use_arrivals", [True, False])
def test_estimator_feeds_the_filter_what_arrived(use_arrivals: bool) -> None:
    T = 40
    rng = np.random.default_rng(4)
    delivered = [bool(d) for d in rng.random(T + 1) < 0.8]
    tau = [int(k) for k in rng.integers(0, 4, T + 1)]
    plant = double_integrator()
    base = LinearPlantEnv(plant, horizon=T, x0_mean=[1.0, 0.0], x0_cov=0.1 * np.eye(2))
    env = LinkObservationWrapper(base, BernoulliLink(), ScheduleQos(delivered, tau))
    estimator = KalmanEstimator.for_env(env, use_arrivals=use_arrivals)
    obs, info = env.reset(seed=4)
    zs, us = [info["remote_true"]], []
    estimates = [estimator.reset(obs)]
    for _ in range(T):
        u = np.array([-0.5 * estimates[-1][0]])
        obs, _, _, truncated, info = env.step(u)
        us.append(u)
        zs.append(info["remote_true"])
        estimates.append(estimator.estimate(obs, u))
        if truncated:
            break
    model = {"A": plant.A, "C": plant.C, "Q": plant.W, "R": plant.V, "B": plant.B}
    for t, estimate in enumerate(estimates):
        arrived = [s for s in range(t + 1) if delivered[s] and s + tau[s] <= t]
        if use_arrivals:
            # Every arrived packet, in arrival order (ties by timestamp, as the link reports).
            used = sorted(arrived, key=lambda s: (s + tau[s], s))
        else:
            # Only packets that were the freshest when they arrived (eq_time).
            used, newest = [], -1
            for k in range(t + 1):
                fresh = [s for s in arrived if s + tau[s] == k and s > newest]
                if fresh:
                    newest = max(fresh)
                    used.append(newest)
        reference = refilter_in_time_order(model, base.x0_mean, base.x0_cov, zs, us, used, t)
        np.testing.assert_allclose(estimate, reference.x, rtol=0, atol=1e-10)
    assert any(
        s + tau[s] > s2 + tau[s2]
        for s in range(T)
        for s2 in range(s + 1, T)
        if delivered[s] and delivered[s2]
    )  # some packets did overtake others
