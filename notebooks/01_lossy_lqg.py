# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Estimation and control over a lossy link: theory next to simulation
#
# The sensor measurement $z_t = C x_t + v_t$ of a linear plant
# $x_{t+1} = A x_t + B u_t + w_t$ ($w \sim N(0, W)$, $v \sim N(0, V)$) is sent over the
# paper's abstract link: it arrives with probability $q$ (`eq_d`), and the controller holds
# the freshest arrived measurement and its age (`eq_time`, `eq_output`).
#
# **Estimation** (Sinopoli et al. 2004, *Kalman filtering with intermittent observations*).
# With arrivals $\gamma_t \sim \mathrm{Bernoulli}(q)$ the Kalman filter stays optimal, and its
# error covariance follows the random Riccati recursion
# $P_{t+1} = A P_t A' + W - \gamma_t A P_t C' (C P_t C' + V)^{-1} C P_t A'$.
# There is a critical probability $q_c$: $E[P_t]$ is bounded for every initial condition iff
# $q > q_c$, and $1 - 1/\max_i |\lambda_i(A)|^2 \le q_c \le \bar q$ where $\bar q$ comes from
# an LMI; both bounds coincide when $C$ is invertible, so for a scalar plant
# $q_c = 1 - 1/a^2$. Above $q_c$, $\bar S \le \lim E[P_t] \le \bar V$ with
# $\bar S = (1-q) A \bar S A' + W$ and $\bar V$ the fixed point of the *modified* Riccati
# equation $\bar V = A \bar V A' + W - q A \bar V C'(C \bar V C' + V)^{-1} C \bar V A'$.
#
# **Control.** Certainty-equivalent LQG $u_t = -K \hat x_{t|t}$ costs, per step,
# $J = \mathrm{tr}(S W) + \mathrm{tr}(K'(R + B'SB)K\,\Sigma)$ with $\Sigma = E[P_{t|t}]$: the
# first term is the price of the process noise, the second the price of not knowing the state.
# With $q = 1$, $\Sigma$ is the stationary posterior covariance of the Kalman filter.
#
# Set `CODESIGN_SMOKE=1` for small settings (the test suite does).

# %%
import os

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.estimation.kalman import (
    IntermittentKalmanFilter,
    critical_arrival_bounds,
    expected_covariance_bounds,
    intermittent_riccati,
)
from codesign_mb.network import BernoulliLink, LinkObservationWrapper
from codesign_mb.plants.linear import LinearPlantEnv, inverted_pendulum, scalar_unstable
from codesign_mb.rollout import rollout
from codesign_mb.rollout.compose import lqg, lqg_average_cost

SMOKE = os.environ.get("CODESIGN_SMOKE") == "1"
N_SEQUENCES = 2_000 if SMOKE else 20_000  # Monte-Carlo arrival sequences for E[P]
STEPS = 40 if SMOKE else 200  # length of each sequence
EPISODES = 4 if SMOKE else 40  # closed-loop episodes per reliability
HORIZON = 150 if SMOKE else 500  # steps per episode
BURN_IN = 50  # steps discarded before averaging (transient of x_0 and P_0)
rng = np.random.default_rng(2004)

# %% [markdown]
# ## 1. The scalar plant: a critical arrival probability
#
# $x_{t+1} = 1.2\,x_t + u_t + w_t$, $z_t = x_t + v_t$, unit noises, at 40 ms per step.

# %%
plant = scalar_unstable(a=1.2)
a = float(plant.A[0, 0])
q_c = 1 - 1 / a**2
lower, upper = critical_arrival_bounds(plant.A, plant.C, tol=1e-4)
print(f"q_c = 1 - 1/a^2 = {q_c:.4f}; LMI bounds [{lower:.4f}, {upper:.4f}] (C invertible)")

# %% [markdown]
# The Monte-Carlo runs the vectorised recursion `intermittent_riccati`, which performs the
# filter's own arithmetic; first a check on a few sequences that the filter agrees.

# %%
check = rng.random((5, STEPS)) < 0.5
priors, _ = intermittent_riccati(plant.A, plant.C, plant.W, plant.V, np.eye(1), check)
for gamma, expected in zip(check, priors, strict=True):
    kf = IntermittentKalmanFilter(plant.A, plant.C, plant.W, plant.V)
    kf.reset([0.0], np.eye(1))
    for t, arrived in enumerate(gamma):
        if arrived:
            kf.update([0.0], timestamp=t)
        kf.predict()
        assert np.isclose(kf.P[0, 0], expected[t + 1, 0, 0], rtol=1e-12)
print("filter P == vectorised recursion on", len(check), "sequences")

# %%
qs_traj = [0.1, 0.2, q_c, 0.4, 0.6, 0.9]
fig, ax = plt.subplots(figsize=(6, 3.5))
for q in qs_traj:
    gamma = rng.random((N_SEQUENCES, STEPS)) < q
    mean_prior, _ = intermittent_riccati(
        plant.A, plant.C, plant.W, plant.V, np.eye(1), gamma, average=True
    )
    ax.semilogy(mean_prior[:, 0, 0], label=f"q = {q:.2f}")
ax.set_xlabel("step t")
ax.set_ylabel("E[P_t] (Monte-Carlo)")
ax.set_title("Below q_c the expected error covariance diverges")
ax.legend(fontsize=8)
plt.show()
plt.close(fig)

# %% [markdown]
# Stationary $E[P]$ against $q$, with Sinopoli's bounds. Below $q_c$ both bounds are
# infinite; the Monte-Carlo mean there only grows with the run length (and with the number of
# sequences, which decides how long a run of losses is sampled). Just above $q_c$ the
# distribution of $P$ is heavy-tailed (its variance is infinite for $(1-q)a^4 > 1$), so a
# finite Monte-Carlo there tends to fall below the lower bound.

# %%
q_grid = np.linspace(0.05, 1.0, 8 if SMOKE else 20)
rows = []
for q in q_grid:
    gamma = rng.random((N_SEQUENCES, STEPS)) < q
    mean_prior, _ = intermittent_riccati(
        plant.A, plant.C, plant.W, plant.V, np.eye(1), gamma, average=True
    )
    s_bar, v_bar = expected_covariance_bounds(plant.A, plant.C, plant.W, plant.V, q)
    rows.append(
        {
            "q": q,
            "E[P] (MC, last half)": float(mean_prior[STEPS // 2 :, 0, 0].mean()),
            "lower S": float(s_bar[0, 0]),
            "upper V (MARE)": float(v_bar[0, 0]),
        }
    )
bounds = pd.DataFrame(rows)
fig, ax = plt.subplots(figsize=(6, 3.5))
ax.semilogy(bounds["q"], bounds["E[P] (MC, last half)"], "o-", label="E[P], Monte-Carlo")
ax.semilogy(bounds["q"], bounds["lower S"], "--", label="lower bound S")
ax.semilogy(bounds["q"], bounds["upper V (MARE)"], ":", label="upper bound V (MARE)")
ax.axvline(q_c, color="k", lw=0.8, label=f"q_c = {q_c:.3f}")
ax.set_xlabel("reliability q")
ax.set_ylabel("stationary E[P]")
ax.legend(fontsize=8)
plt.show()
plt.close(fig)
bounds.round(3)

# %% [markdown]
# ## 2. The inverted pendulum: bounds from the unstable eigenvalue
#
# The linearised cart-pole at 40 ms has one unstable eigenvalue
# $e^{\sqrt{(M+m)g/(Ml)}\,dt} \approx 1.20$ and a double eigenvalue at 1 (the cart). Only the
# cart position and the pole angle are measured, so $C$ is not invertible and the critical
# probability is only bracketed: the lower bound from the largest unstable eigenvalue, the
# upper one from the LMI. Here the bracket is narrow. Just below it ($q = 0.3$) $E[P_t]$ does
# diverge, but at the rate $(1-q)\lambda_{max}^2 \approx 1.015$ per step and through loss
# runs too rare for this Monte-Carlo to sample; at $q = 0.2$ the growth is plain.

# %%
pendulum = inverted_pendulum()
eigenvalues = np.linalg.eigvals(pendulum.A)
p_lower, p_upper = critical_arrival_bounds(pendulum.A, pendulum.C, tol=1e-4)
print("eigenvalues of A:", np.round(eigenvalues.real, 4))
print(f"{p_lower:.4f} <= q_c <= {p_upper:.4f}")

pend_rows = []
for q in [0.2, 0.3, 0.4, 0.6, 0.8, 1.0]:
    gamma = rng.random((N_SEQUENCES // 4, STEPS)) < q
    mean_prior, _ = intermittent_riccati(
        pendulum.A, pendulum.C, pendulum.W, pendulum.V, 1e-2 * np.eye(4), gamma, average=True
    )
    trace = np.trace(mean_prior, axis1=1, axis2=2)
    pend_rows.append({"q": q, "tr E[P] mid": trace[STEPS // 2], "tr E[P] end": trace[-1]})
pd.DataFrame(pend_rows).round(5)

# %% [markdown]
# ## 3. LQG cost against reliability
#
# Closed loops through the toolkit's own pieces (`LinearPlantEnv`, `BernoulliLink`,
# `LinkObservationWrapper`, `lqg` = Kalman estimator + LQR, `rollout`), seeded, against
# $J(q) = \mathrm{tr}(SW) + \mathrm{tr}(K'(R + B'SB)K\,E[P_{t|t}])$ with $E[P_{t|t}]$ from the
# Monte-Carlo recursion (exact Riccati value at $q = 1$). Episodes share their seeds across
# $q$ (common random numbers).

# %%
Q_cost, R_cost = np.eye(1), np.eye(1)
riccati = lqg_average_cost(plant, Q_cost, R_cost)
base = LinearPlantEnv(plant, horizon=HORIZON, state_cost=Q_cost, input_cost=R_cost)
lqg_rows = []
for q in [1.0, 0.9, 0.8, 0.7, 0.6, 0.5] if SMOKE else np.linspace(1.0, 0.4, 13):
    env = LinkObservationWrapper(base, BernoulliLink(), StaticQos(float(q)))
    estimator, controller = lqg(env)
    costs = np.array(
        [
            rollout(env, estimator, controller, seed=seed)["stage_cost"].iloc[BURN_IN:].mean()
            for seed in range(EPISODES)
        ]
    )
    gamma = rng.random((N_SEQUENCES, HORIZON)) < q
    _, mean_post = intermittent_riccati(
        plant.A, plant.C, plant.W, plant.V, np.eye(1), gamma, average=True
    )
    theory = lqg_average_cost(plant, Q_cost, R_cost, posterior_cov=mean_post[BURN_IN:].mean(0))
    lqg_rows.append(
        {
            "q": float(q),
            "simulated": costs.mean(),
            "ci95": 1.96 * costs.std(ddof=1) / np.sqrt(costs.size),
            "theory": theory.total,
        }
    )
lqg_table = pd.DataFrame(lqg_rows)
print(
    f"Riccati cost at q = 1: tr(SW) = {riccati.control:.3f} + estimation "
    f"{riccati.estimation:.3f} = {riccati.total:.3f}"
)
fig, ax = plt.subplots(figsize=(6, 3.5))
ax.errorbar(
    lqg_table["q"],
    lqg_table["simulated"],
    yerr=lqg_table["ci95"],
    fmt="o",
    label="simulated (95 % CI)",
)
ax.plot(lqg_table["q"], lqg_table["theory"], "-", label="tr(SW) + tr(M E[P])")
ax.axhline(riccati.control, color="gray", ls=":", label="tr(SW): perfect state")
ax.axvline(q_c, color="k", lw=0.8, label="q_c")
ax.set_xlabel("reliability q")
ax.set_ylabel("average cost per step")
ax.legend(fontsize=8)
plt.show()
plt.close(fig)
lqg_table.round(3)

# %% [markdown]
# The cost rises slowly from its Riccati value while $q$ is well above $q_c$ and steeply as
# $q$ approaches it: the estimation term carries $E[P_{t|t}]$, which diverges at $q_c$. This
# is the trade-off the co-design exploits: reliability is expensive for the network, and a
# plant needs less of it when its estimator can bridge the losses.
