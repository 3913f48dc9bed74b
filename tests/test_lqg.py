"""Certainty-equivalent LQG over the link against the Riccati cost, and the demo command.

The average cost per step of ``u = -K x_hat`` is ``tr(S W) + tr(K' (R + B' S B) K Sigma)``
with ``Sigma = E[P_{t|t}]`` (``codesign_mb.control.lqr``). It is checked three ways: against
the stationary covariance of the closed loop (an independent derivation), against seeded
Monte-Carlo closed loops through ``rollout`` (confidence interval), and with a one-step delay,
where ``Sigma`` is the filter's stationary *prior* covariance.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import scipy.linalg
import typer
from typer.testing import CliRunner

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.cli.demo import register
from codesign_mb.control.lqr import LqrController
from codesign_mb.core import registry
from codesign_mb.estimation.kalman import intermittent_riccati, steady_state_covariance
from codesign_mb.network import BernoulliLink, LinkObservationWrapper
from codesign_mb.plants.linear import (
    LinearPlantEnv,
    make_linear_plant,
    scalar_unstable,
)
from codesign_mb.rollout import rollout
from codesign_mb.rollout.compose import lqg, lqg_average_cost
from codesign_mb.studies.demo import LqgDemoConfig, run_lqg_demo

Z99 = 2.5758293035489004  # two-sided 99 % normal quantile


def test_lqr_gain_matches_the_scalar_riccati_equation() -> None:
    a, b, q, r = 1.2, 0.5, 2.0, 0.3
    ctrl = LqrController([[a]], [[b]], [[q]], [[r]])
    # s = q + a^2 s - (a b s)^2 / (r + b^2 s)  <=>  b^2 s^2 + (r - a^2 r - q b^2) s - q r = 0
    c2, c1, c0 = b**2, r - a**2 * r - q * b**2, -q * r
    s = (-c1 + math.sqrt(c1**2 - 4 * c2 * c0)) / (2 * c2)
    assert ctrl.riccati[0, 0] == pytest.approx(s, rel=1e-12)
    assert ctrl.gain[0, 0] == pytest.approx(a * b * s / (r + b**2 * s), rel=1e-12)
    assert abs(ctrl.closed_loop_poles[0]) < 1
    assert ctrl.act([2.0])[0] == pytest.approx(-2.0 * ctrl.gain[0, 0], rel=1e-15)


@pytest.mark.parametrize(
    ("field", "args"),
    [
        ("A", (np.ones((2, 3)), np.ones((2, 1)), np.eye(2), np.eye(1))),
        ("B", (np.eye(2), np.ones((3, 1)), np.eye(2), np.eye(1))),
        ("state_cost", (np.eye(2), np.ones((2, 1)), np.eye(3), np.eye(1))),
        ("input_cost", (np.eye(2), np.ones((2, 1)), np.eye(2), np.eye(2))),
        ("input_cost", (np.eye(2), np.ones((2, 1)), np.eye(2), np.zeros((1, 1)))),
    ],
)
def test_lqr_rejects_bad_matrices_by_name(field: str, args: tuple) -> None:
    with pytest.raises(ValueError, match=rf"^{field} "):
        LqrController(*args)


@pytest.mark.parametrize("name", sorted(registry.kinds("linear_plant")))
def test_riccati_cost_equals_the_closed_loop_stationary_cost(name: str) -> None:
    plant = make_linear_plant(name)
    n = plant.n_states
    Q, R = np.eye(n), np.eye(plant.n_inputs)
    ctrl = LqrController.for_plant(plant, Q, R)
    prior, _ = steady_state_covariance(plant.A, plant.C, plant.W, plant.V)
    L = prior @ plant.C.T @ np.linalg.inv(plant.C @ prior @ plant.C.T + plant.V)
    K, A, B, C = ctrl.gain, plant.A, plant.B, plant.C
    I_LC = np.eye(n) - L @ C
    # xi = (x, e), e = x - x_hat_{t|t}: x+ = (A - BK) x + BK e + w; e+ = (I - LC)(A e + w) - L v.
    F = np.block([[A - B @ K, B @ K], [np.zeros((n, n)), I_LC @ A]])
    G = np.block([[np.eye(n), np.zeros((n, plant.n_outputs))], [I_LC, -L]])
    N = scipy.linalg.block_diag(plant.W, plant.V)
    Xi = scipy.linalg.solve_discrete_lyapunov(F, G @ N @ G.T)
    Xxx, Xxe, Xee = Xi[:n, :n], Xi[:n, n:], Xi[n:, n:]
    # u = -K (x - e)
    expected = np.trace(Q @ Xxx) + np.trace(K.T @ R @ K @ (Xxx - Xxe - Xxe.T + Xee))
    assert lqg_average_cost(plant, Q, R).total == pytest.approx(expected, rel=1e-8)


def simulated_costs(
    reliability: float, latency: int, *, episodes: int = 30, horizon: int = 250, burn_in: int = 50
) -> np.ndarray:
    """Per-episode mean stage cost after ``burn_in`` steps: scalar plant, LQG, seeded."""
    base = LinearPlantEnv(scalar_unstable(), horizon=horizon)
    env = LinkObservationWrapper(base, BernoulliLink(), StaticQos(reliability, latency))
    estimator, controller = lqg(env)
    costs = []
    for seed in range(episodes):
        df = rollout(env, estimator, controller, seed=seed)
        costs.append(df["stage_cost"].iloc[burn_in:].mean())
    return np.asarray(costs)


def assert_within_ci(costs: np.ndarray, expected: float, *, max_width: float = 0.1) -> None:
    """``expected`` lies in the 99 % interval of the mean, and that interval is informative."""
    half = Z99 * costs.std(ddof=1) / math.sqrt(costs.size)
    assert half < max_width * expected, "the Monte-Carlo interval is too wide to test anything"
    assert abs(costs.mean() - expected) <= half, (costs.mean(), half, expected)


def test_lqg_closed_loop_reaches_the_riccati_cost() -> None:
    plant = scalar_unstable()
    theory = lqg_average_cost(plant, np.eye(1), np.eye(1))
    assert_within_ci(simulated_costs(1.0, 0), theory.total)


def test_one_step_delay_costs_the_prior_covariance() -> None:
    # With tau = 1 the estimate at t uses z_0..z_{t-1}: Sigma is the stationary prior.
    plant = scalar_unstable()
    prior, _ = steady_state_covariance(plant.A, plant.C, plant.W, plant.V)
    delayed = lqg_average_cost(plant, np.eye(1), np.eye(1), posterior_cov=prior)
    assert delayed.total > lqg_average_cost(plant, np.eye(1), np.eye(1)).total
    assert_within_ci(simulated_costs(1.0, 1), delayed.total)


def test_lossy_lqg_cost_follows_the_expected_covariance() -> None:
    # q = 0.7 > q_c = 0.31: Sigma = E[P_{t|t}] (Monte-Carlo of the random Riccati recursion).
    q, plant = 0.7, scalar_unstable()
    gamma = np.random.default_rng(0).random((20_000, 200)) < q
    _, posteriors = intermittent_riccati(
        plant.A, plant.C, plant.W, plant.V, np.eye(1), gamma, average=True
    )
    sigma = posteriors[50:].mean(axis=0)
    theory = lqg_average_cost(plant, np.eye(1), np.eye(1), posterior_cov=sigma)
    # Loss makes the cost heavy-tailed: a wider (but still informative) interval.
    assert_within_ci(simulated_costs(q, 0), theory.total, max_width=0.15)


def test_same_seed_same_rollout_bit_for_bit() -> None:
    def run(seed: int) -> pd.DataFrame:
        base = LinearPlantEnv(make_linear_plant("pendulum"), horizon=80, x0_cov=0.01 * np.eye(4))
        env = LinkObservationWrapper(base, BernoulliLink(), StaticQos(0.6, 1))
        return rollout(env, *lqg(env), seed=seed)

    first = run(7)
    pd.testing.assert_frame_equal(first, run(7), check_exact=True)
    assert not first.equals(run(8))
    assert {"stage_cost", "age", "delivered", "estimation_error", "reward"} <= set(first.columns)


# ----------------------------------------------------------------------------- demo


def demo_app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """Test app."""

    register(app)
    return app


def test_demo_prints_the_table_as_json() -> None:
    result = CliRunner().invoke(
        demo_app(),
        [
            *("demo", "--plant", "scalar", "-n", "2", "--horizon", "40"),
            *("-q", "1", "-q", "0.5", "--seed", "3", "--json"),
        ],
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert [row["reliability"] for row in data["rows"]] == [1.0, 0.5]
    full, lossy = data["rows"]
    assert full["delivered_fraction"] == 1.0 and full["mean_age"] == 0.0
    assert 0 < lossy["delivered_fraction"] < 1 and lossy["mean_age"] > 0
    assert data["critical_reliability_lower_bound"] == pytest.approx(1 - 1 / 1.44)
    expected = run_lqg_demo(
        LqgDemoConfig(plant="scalar", reliabilities=(1, 0.5), episodes=2, horizon=40, seed=3)
    )
    assert data["rows"] == expected["rows"]  # the CLI is the library call, seeded


def test_codesign_demo_is_registered() -> None:
    from codesign_mb.cli import app

    result = CliRunner().invoke(app, ["demo", "--plant", "scalar", "-n", "1", "--horizon", "5"])
    assert result.exit_code == 0, result.output
    assert "reliability" in result.stdout and "Riccati cost" in result.stdout


@pytest.mark.parametrize(
    ("args", "field"),
    [
        (["-q", "1.5"], "reliabilities"),
        (["-q", "-0.1"], "reliabilities"),
        (["--episodes", "0"], "episodes"),
        (["--latency", "-1"], "latency_steps"),
        (["--plant", "segway"], "plant"),
        (["--scenario", "nope"], "scenario"),
    ],
)
def test_demo_rejects_bad_input_in_one_line(args: list[str], field: str) -> None:
    result = CliRunner().invoke(demo_app(), ["demo", *args])
    assert result.exit_code == 2
    assert result.stderr.startswith(f"error: {field} ")
    assert "Traceback" not in result.output
