"""The MPC on the MuJoCo conveyor: it picks, and (slow) the issue's success targets hold."""

from __future__ import annotations

import numpy as np
import pytest

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.mpc import MpcController, Phase
from codesign_mb.core import registry
from codesign_mb.core.registry import ComponentSpec
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.evaluation.evaluate import evaluate, summarize
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace
from codesign_mb.rollout import rollout


@pytest.mark.parametrize("speed", [0.2, 0.6])
def test_mpc_picks_off_the_belt_with_perfect_communication(speed: float) -> None:
    plant = ConveyorPickPlace(ConveyorConfig(belt_speed_mps=speed))
    env = LinkObservationWrapper(plant, BernoulliLink(), StaticQos(1.0, 0))
    controller = MpcController.from_env(plant)
    phases: list[Phase] = []
    solve = controller.act

    def act(obs: np.ndarray) -> np.ndarray:
        action = solve(obs)
        phases.append(controller.phase)
        assert action.shape == (4,) and np.all(np.abs(action) <= 1.0)
        return action

    controller.act = act  # type: ignore[method-assign]
    steps = rollout(env, PassThroughEstimator(), controller, seed=11)
    assert steps["success"].iloc[-1]
    assert controller.failures == 0
    assert [p for i, p in enumerate(phases) if i == 0 or p != phases[i - 1]] == list(Phase)
    # the workspace of the MPC lies inside the plant's
    assert np.all(np.asarray(controller.config.workspace_low) > plant.workspace_low)
    assert np.all(np.asarray(controller.config.workspace_high) < plant.workspace_high)


def test_from_env_reads_the_plant() -> None:
    plant = ConveyorPickPlace(ConveyorConfig(belt_speed_mps=0.6, max_gripper_speed_mps=1.5))
    controller = MpcController.from_env(plant)
    assert controller.max_speed_mps == 1.5
    assert controller.control_period_s == pytest.approx(0.04)
    np.testing.assert_allclose(controller.belt_velocity, [0.0, 0.6, 0.0])


def _success(speed: float, latency: int, estimator: str) -> dict:
    table = evaluate(
        registry.factory("controller", ComponentSpec("mpc")),
        registry.factory("estimator", ComponentSpec(estimator)),
        StaticQos(1.0, latency),
        ConveyorConfig(belt_speed_mps=speed),
        100,
        0,
        workers=2,
    )
    return summarize(table)


@pytest.mark.slow
@pytest.mark.parametrize(("speed", "target"), [(0.2, 0.99), (0.6, 0.97)])
def test_success_targets_with_perfect_communication(speed: float, target: float) -> None:
    summary = _success(speed, 0, "none")
    assert summary["success_rate"] >= target, summary
    assert summary["mpc_failures"] == 0


@pytest.mark.slow
def test_predictor_target_at_fast_belt_and_four_steps_of_delay() -> None:
    summary = _success(0.6, 4, "predictor")
    assert summary["success_rate"] >= 0.95, summary


@pytest.mark.slow
def test_bench_mpc_on_recorded_problems() -> None:
    from codesign_mb.bench.mpc import bench_mpc

    result = bench_mpc(
        repeats=1,
        seed=0,
        solvers=("qpoases", "daqp"),
        episodes_per_speed=1,
        model_error_episodes=1,
    )
    assert result["solver"] == "daqp_native" and result["problems"] == 200
    assert result["model_error"]["steps"] == 99 and result["joint_limited_steps"][0] == 1
    assert [s["solver"] for s in result["solvers"]] == ["daqp_native", "qpoases", "daqp"]
    assert all(s["failures"] == 0 for s in result["solvers"])
    assert 0 < result["median_ms"] <= result["p99_ms"] <= result["max_ms"]
