"""Estimation error per phase of a conveyor episode and the estimator's consistency (NEES):
the phase labels, the chi-square band, the per-step record, the pooled summary, the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.mpc import MpcController
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.estimation.consistency import has_covariance, nees, nees_band
from codesign_mb.estimation.predictor import DelayCompensatingPredictor
from codesign_mb.evaluation.evaluate import episode_row, summarize
from codesign_mb.evaluation.phase_metrics import SUMMARY_COLUMNS, summarize_phases
from codesign_mb.network import BernoulliLink, LinkObservationWrapper
from codesign_mb.plants.conveyor import ConveyorPickPlace
from codesign_mb.plants.phases import (
    GRASP_WINDOW_HEIGHT_M,
    GRASP_WINDOW_RADIUS_M,
    NOT_SPAWNED,
    PHASES,
    episode_phase,
)
from codesign_mb.plants.scenarios import scenario_config
from codesign_mb.rollout.loop import ClosedLoop

BELT, GRASP, CARRIED = (PHASES.index(p) for p in ("belt", "grasp", "carried"))


# ----------------------------------------------------------------------------- phases
def test_phase_of_constructed_states() -> None:
    obj = np.array([0.5, 0.1, 0.0825])

    def phase(dx: float, dy: float, dz: float, **kw: bool) -> int:
        flags = {"grasped": False, "lifted": False, "spawned": True, **kw}
        return episode_phase(obj, obj + np.array([dx, dy, dz]), **flags)

    assert phase(0.0, -0.2, 0.15) == BELT  # far upstream, high
    assert phase(0.0, 0.0, 0.06) == BELT  # hovering above it: the descent has not begun
    assert phase(0.03, 0.0, 0.0) == GRASP  # beside it at its height, within the fingers' span
    assert phase(0.02, -0.02, 0.04) == GRASP  # descending onto it
    assert phase(0.03, 0.03, 0.0) == BELT  # 4.2 cm away horizontally: out of the window
    r, h = GRASP_WINDOW_RADIUS_M, GRASP_WINDOW_HEIGHT_M
    assert phase(r - 1e-6, 0.0, h - 1e-6) == GRASP  # just inside the window's edges
    assert phase(r + 1e-6, 0.0, 0.0) == BELT and phase(0.0, 0.0, h + 1e-6) == BELT
    assert phase(0.0, 0.0, 0.0, grasped=True) == CARRIED
    assert phase(0.0, -0.3, 0.1, lifted=True) == CARRIED  # in the air, whatever holds it
    assert phase(0.0, 0.0, 0.0, spawned=False) == NOT_SPAWNED


# ----------------------------------------------------------------------------- NEES theory
def test_nees_is_the_quadratic_form() -> None:
    rng = np.random.default_rng(0)
    factors = rng.normal(size=(5, 4, 4))
    P = factors @ factors.transpose(0, 2, 1) + 0.1 * np.eye(4)
    e = rng.normal(size=(5, 4))
    expected = [float(ek @ np.linalg.inv(Pk) @ ek) for ek, Pk in zip(e, P, strict=True)]
    assert nees(e, P) == pytest.approx(expected, rel=1e-9)
    with pytest.raises(ValueError, match="shape"):
        nees(e, P[:, :3, :3])


def test_nees_band_known_values_and_coverage() -> None:
    """One sample: the chi-square(3) quantiles of the tables; N samples of a consistent filter
    (errors drawn from its covariance) average inside the band 95 % of the time, those of a
    filter that reports a quarter of its covariance (4x overconfident) almost never."""
    low, high = nees_band(1, 3)
    assert (low, high) == pytest.approx((0.2158, 9.348), abs=1e-3)
    assert all(math.isnan(v) for v in nees_band(0, 3))
    rng = np.random.default_rng(1)
    dof, samples, trials = 3, 20, 4000
    factor = rng.normal(size=(dof, dof))
    P = factor @ factor.T + 0.2 * np.eye(dof)
    errors = rng.multivariate_normal(np.zeros(dof), P, size=trials * samples)
    low, high = nees_band(samples, dof)
    assert low * samples == pytest.approx(chi2.ppf(0.025, dof * samples))
    for reported, coverage in ((P, (0.935, 0.965)), (P / 4, (0.0, 0.01))):
        values = nees(errors, np.broadcast_to(reported, (len(errors), dof, dof)))
        means = values.reshape(trials, samples).mean(axis=1)
        inside = float(np.mean((means >= low) & (means <= high)))
        assert coverage[0] <= inside <= coverage[1]


class _Proxy:
    """Forwards every attribute (as the table's timing wrappers do)."""

    def __init__(self, inner: object) -> None:
        self._inner = inner

    def __getattr__(self, name: str) -> object:
        return getattr(self._inner, name)


def test_has_covariance_sees_a_reset_filter_through_a_proxy() -> None:
    predictor = DelayCompensatingPredictor({"object_pos": slice(0, 3)}, control_period_s=0.04)
    predictor.reset(np.zeros(4))
    assert has_covariance(predictor) and has_covariance(_Proxy(predictor))
    assert not has_covariance(PassThroughEstimator())
    assert not has_covariance(_Proxy(PassThroughEstimator()))


# ----------------------------------------------------------------------------- closed loop
def _loop(scenario: str, latency_steps: int, estimator: str) -> ClosedLoop:
    plant = ConveyorPickPlace(scenario_config(scenario))
    env = LinkObservationWrapper(plant, BernoulliLink(), StaticQos(1.0, latency_steps))
    est = (
        DelayCompensatingPredictor.from_env(plant)
        if estimator == "predictor"
        else PassThroughEstimator()
    )
    return ClosedLoop(env, est, MpcController.from_env(plant))


def test_predictor_on_a_constant_belt_with_a_perfect_link() -> None:
    """Noiseless perception of a constant-velocity object, every packet fresh: the prediction
    is the truth while the object rides the belt. The episode goes belt -> grasp -> carried,
    and the recorded NEES is the filter's own quadratic form at each step."""
    loop = _loop("paper", 0, "predictor")
    loop.reset(seed=3)
    expected = []
    while not loop.done:
        est, truth = loop.estimator, loop.info
        error = est.state - np.concatenate([truth["remote_true"][:3], truth["object_vel"]])
        expected.append(error[:3] @ np.linalg.inv(est.covariance[:3, :3]) @ error[:3])
        loop.step()
    steps = loop.table()
    phases = steps["phase"].to_numpy()
    assert set(phases) == {BELT, GRASP, CARRIED} and np.all(np.diff(phases) >= 0)
    assert steps["nees_position"].to_numpy() == pytest.approx(expected, rel=1e-6, abs=1e-12)
    row = episode_row(steps)
    assert row["success"] and row["est_error_mm_belt"] < 0.05
    assert row["phase_steps"] == len(steps)  # spawned at t = 0: every step has a phase
    assert row["nees_belt"] < 3.0  # no error at all: far below the 3 of a consistent filter


def test_stale_observation_lags_by_belt_speed_times_delay() -> None:
    """Estimator ``none`` with delay ``d``: the held position is the object's ``d`` steps ago,
    ``v d dt`` behind it on the belt; the episode's belt-phase RMS is the one of the errors
    computed from the true positions alone (the prior before the first packet)."""
    d = 3
    loop = _loop("paper", d, "none")
    loop.reset(seed=5)
    plant = loop.env.unwrapped
    v, dt = plant.config.belt_speed_mps, plant.control_period_s
    truth = []
    while not loop.done:
        truth.append(np.array(loop.info["remote_true"][:3]))
        loop.step()
    steps = loop.table()
    held = [plant.remote_prior()[:3]] * d + truth[:-d]
    independent = np.linalg.norm(np.array(truth) - np.array(held), axis=1)
    belt = steps["phase"].to_numpy() == BELT
    late = belt & (steps["t"].to_numpy() >= d)
    assert late.sum() > 10
    assert steps["position_error_m"][late].to_numpy() == pytest.approx(v * d * dt, abs=2e-4)
    row = episode_row(steps)
    rms_mm = 1e3 * math.sqrt(np.mean(independent[belt] ** 2))
    assert row["est_error_mm_belt"] == pytest.approx(rms_mm, rel=1e-6)
    assert "nees_belt" not in row and "nees_position" not in steps  # no covariance


# ----------------------------------------------------------------------------- summary
def _steps(
    phase: list[int], error_m: list[float], nees_position: list[float] | None
) -> pd.DataFrame:
    n = len(phase)
    frame = pd.DataFrame(
        {
            "success": False,
            "reward": 0.0,
            "qos_reliability": 1.0,
            "qos_latency_steps": 0,
            "qos_cost": 1.0,
            "delivered": True,
            "age": 0,
            "estimation_error": error_m,
            "phase": phase,
            "position_error_m": error_m,
        },
        index=range(n),
    )
    if nees_position is not None:
        frame["nees_position"] = nees_position
    return frame


def test_summary_pools_the_steps_of_every_episode() -> None:
    episodes = [
        _steps([-1, 0, 0, 1, 2], [0.5, 0.001, 0.003, 0.002, 0.004], [9.0, 1.0, 2.0, 3.0, 4.0]),
        _steps([0, 0, 0, 0, 0], [0.002, 0.002, 0.004, 0.001, 0.0], [0.5, 1.5, 2.5, 3.5, 8.5]),
    ]
    table = pd.DataFrame([episode_row(s) for s in episodes])
    summary = summarize(table)
    steps = pd.concat(episodes)
    for suffix, mask in (("", steps["phase"] >= 0), ("_belt", steps["phase"] == BELT)):
        errors, values = steps["position_error_m"][mask], steps["nees_position"][mask]
        assert summary[f"est_error_mm{suffix}"] == pytest.approx(1e3 * np.sqrt(np.mean(errors**2)))
        assert summary[f"nees{suffix}"] == pytest.approx(values.mean())
        inside = np.mean(values <= chi2.ppf(0.95, 3))  # 7.81: the 8.5 step is outside
        assert summary[f"nees_inside{suffix}"] == pytest.approx(inside)
        assert summary[f"phase_steps{suffix}"] == mask.sum()
        band = nees_band(int(mask.sum()), 3)
        assert (summary[f"nees{suffix}_low"], summary[f"nees{suffix}_high"]) == band
    assert summary["phase_steps_carried"] == 1 and summary["est_error_mm_carried"] == 4.0
    assert set(summarize_phases(table)) <= set(SUMMARY_COLUMNS)  # what the tables carry
    without = summarize(pd.DataFrame([episode_row(_steps([0], [0.001], None))]))
    assert without["est_error_mm_belt"] == pytest.approx(1.0)
    assert not any(k.startswith("nees") for k in without)
    assert math.isnan(without["est_error_mm_grasp"]) and without["phase_steps_grasp"] == 0
    assert summarize_phases(pd.DataFrame({"success": [True]})) == {}


def test_cli_evaluate_reports_the_phases(tmp_path) -> None:
    from typer.testing import CliRunner

    from codesign_mb.cli import app

    args = ["evaluate", "--scenario", "realistic", "-n", "1", "-j", "1", "--max-steps", "30"]
    result = CliRunner().invoke(app, [*args, "-o", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert 0 < summary["phase_steps"] <= 30 and summary["est_error_mm_belt"] > 0
    assert summary["nees_belt_low"] < 3.0 < summary["nees_belt_high"]
    assert {"nees_state", "nees_state_belt_high"} <= set(summary)
