"""Stage B on the ``realistic`` scenario: the packet without velocity, per-phase errors.

A tiny stage B (scripted controller, a few short episodes) on the realistic plant: the
estimators output the plant's state layout (the estimated velocity appended where the packet
has none) and ``training.json`` reports their errors per phase of the object, which are
recomputed here independently from the held-out episodes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from codesign_mb.core.registry import ComponentSpec, PlantSpec, make_plant
from codesign_mb.estimation.learned import EstimatorFeatures, MlpEstimator, load_estimator
from codesign_mb.plants.phases import NOT_SPAWNED, PHASES
from codesign_mb.plants.scenarios import scenario_options
from codesign_mb.stages.episodes import EpisodeData
from codesign_mb.stages.fitting import EstimatorTraining, fit_estimator
from codesign_mb.stages.stage import StageRun
from codesign_mb.stages.stage_b import StageBConfig, train_stage_b

REALISTIC = PlantSpec("conveyor", {**scenario_options("realistic"), "horizon": 40})


@pytest.fixture(scope="module")
def realistic_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("stage_b_realistic")
    config = StageBConfig(
        plant=REALISTIC,
        controller=ComponentSpec("scripted"),
        train_episodes=3,
        val_episodes=2,
        dagger_rounds=0,
        mlp_hidden=(16,),
        lstm_hidden=8,
        mlp=EstimatorTraining(epochs=2),
        lstm=EstimatorTraining(epochs=2),
    )
    train_stage_b(config, StageRun(root / "out", root / "work"))
    meta = json.loads((root / "out" / "training.json").read_text())
    return {"root": root, "meta": meta, "val": EpisodeData.load(root / "work" / "val.npz")}


def test_realistic_estimators_output_the_state_layout(realistic_run: dict[str, Any]) -> None:
    """The packet has the position only: the output is the state layout, velocity appended."""
    meta, root = realistic_run["meta"], realistic_run["root"]
    env = make_plant(REALISTIC)
    state, observed = env.state_layout, env.observation_layout
    assert "object_vel" not in observed and meta["layout"]["estimates_velocity"] is True
    assert meta["layout"]["state"]["object_vel"] == [state["object_vel"].start, 13]
    networked = realistic_run["val"].networked[0].astype(float)
    for kind in ("mlp", "lstm"):
        est = load_estimator(root / "out" / f"{kind}.pt")
        out = est.reset(networked[0])
        assert out.shape == (max(s.stop for s in state.values()),)
        # the non-remote entries pass through; the estimate = y + the network's residual
        np.testing.assert_array_equal(out[:7], networked[0][:7])
        x = torch.as_tensor(est.features(networked[0]))[None]
        with torch.no_grad():
            residual = (est.net(x)[0] if kind == "mlp" else est.net(x[None])[0][0, -1]).numpy()
        np.testing.assert_allclose(out[7:10], networked[0][7:10] + residual[:3], atol=1e-5)
        np.testing.assert_allclose(out[state["object_vel"]], residual[3:], atol=1e-6)
    env.close()


def test_realistic_per_phase_errors_match_an_independent_count(
    realistic_run: dict[str, Any],
) -> None:
    """``training.json``'s per-phase RMSE = the RMSE over the steps of that recorded phase."""
    val, root = realistic_run["val"], realistic_run["root"]
    mlp = realistic_run["meta"]["held_out_mse"]["mlp"]
    est = load_estimator(root / "out" / "mlp.pt")
    err_pos, err_vel, phases = [], [], []
    for nets, prevs, truth, phase in zip(
        val.networked, val.prev_actions, val.truth, val.phase, strict=True
    ):
        nets = nets.astype(float)
        outs = [est.reset(nets[0])] + [
            est.estimate(nets[t], prevs[t].astype(float)) for t in range(1, len(nets))
        ]
        out = np.asarray(outs)
        err_pos.append(np.sum((out[:, 7:10] - truth[:, :3]) ** 2, axis=1))
        err_vel.append(np.sum((out[:, 10:13] - truth[:, 3:6]) ** 2, axis=1))
        phases.append(phase)
        # before the object spawned its true velocity is zero (as the plant's remote_true)
        assert np.all(truth[phase == NOT_SPAWNED, 3:] == 0.0)
    pos, vel, phase = map(np.concatenate, (err_pos, err_vel, phases))
    assert sum(mlp[f"steps_{p}"] for p in PHASES) == int(np.sum(phase >= 0))
    seen = 0
    for k, name in enumerate(PHASES):
        mask = phase == k
        assert mlp[f"steps_{name}"] == int(mask.sum())
        if mask.any():
            seen += 1
            assert mlp[f"rmse_position_{name}_m"] == pytest.approx(np.sqrt(pos[mask].mean()))
            assert mlp[f"rmse_velocity_{name}_mps"] == pytest.approx(np.sqrt(vel[mask].mean()))
    assert seen >= 2  # the scripted pick goes through the phases
    assert mlp["rmse_position_m"] == pytest.approx(np.sqrt(pos.mean()))
    compare = realistic_run["meta"]["held_out_mse"]
    assert "rmse_velocity_mps" in compare["predictor"]  # the predictor appends one too
    assert "rmse_velocity_mps" not in compare["none"]  # the stale packet has none


def test_velocity_head_learns_an_unobserved_velocity() -> None:
    """Ground truth: the velocity (not in the packet) is a function of an observed entry;
    the appended head learns it far below its spread."""
    rng = np.random.default_rng(0)
    features = EstimatorFeatures(
        obs_dim=4, action_dim=1, remote_start=1, remote_stop=4, output_velocity=True
    )
    est = MlpEstimator.create(features, hidden=(32, 32), seed=0)
    data = EpisodeData()
    for _ in range(20):
        speed = rng.uniform(0.1, 0.6)
        nets = np.column_stack([np.full(10, speed), rng.normal(size=(10, 3)), np.zeros(10)])
        velocity = np.column_stack([np.zeros(10), np.full(10, speed), np.zeros(10)])
        data.networked.append(nets.astype(np.float32))
        data.prev_actions.append(np.zeros((10, 1), np.float32))
        data.truth.append(np.column_stack([nets[:, 1:4], velocity]).astype(np.float32))
        data.reliability.append(np.ones(10, np.float32))
        data.success.append(True)
        data.phase.append(np.zeros(10, np.int8))
    fit_estimator(est, data, None, EstimatorTraining(epochs=150, batch_size=32), seed=0)
    for speed in (0.15, 0.35, 0.55):
        out = est.reset(np.array([speed, 0.1, -0.2, 0.3, 0.0]))
        assert out.shape == (7,)
        np.testing.assert_allclose(out[1:4], [0.1, -0.2, 0.3], atol=0.02)
        assert out[5] == pytest.approx(speed, abs=0.03)


def test_old_checkpoints_load_without_velocity(tmp_path: Path) -> None:
    """A checkpoint written before ``output_velocity`` existed reads as without it."""
    f = EstimatorFeatures(obs_dim=4, action_dim=1, remote_start=1, remote_stop=4)
    path = MlpEstimator.create(f, hidden=(4,)).save(tmp_path / "mlp.pt")
    blob = torch.load(path, weights_only=True)
    del blob["features"]["output_velocity"]
    torch.save(blob, path)
    est = load_estimator(path)
    assert est.features.output_velocity is False
    assert est.reset(np.zeros(5)).shape == (4,)


def test_fig_cn_learned_rows_from_realistic_checkpoints(realistic_run: dict[str, Any]) -> None:
    """With estimators that read the realistic packet, Fig. 4 gets the learned curves: the
    controller alone and with each estimator, beside the model-based ones."""
    from codesign_mb.studies.fig_cn import FigCnConfig, learned_skip_reason, run_fig_cn

    out = realistic_run["root"] / "out"
    cfg = FigCnConfig(
        trials=1,
        workers=1,
        delays=(2,),
        belt_speeds_mps=(0.6,),
        reliabilities=(),
        estimators=("none",),
        max_steps=6,
        learned_controller=ComponentSpec("scripted"),  # a stand-in: no stage A on realistic yet
        learned_estimators=(
            ComponentSpec("mlp", str(out / "mlp.pt")),
            ComponentSpec("lstm", str(out / "lstm.pt")),
        ),
    )
    assert learned_skip_reason(cfg) is None
    table = run_fig_cn(cfg)
    curves = list(zip(table["pipeline"], table["estimator"], strict=True))
    assert curves == [
        ("model_based", "none"),
        ("learned", "none"),
        ("learned", "mlp"),
        ("learned", "lstm"),
    ]
    assert table["trials"].eq(1).all() and table["latency_steps"].eq(2).all()


def test_fig_cn_skips_learned_rows_with_a_reason(tmp_path: Path) -> None:
    """The shipped checkpoints read the paper's packet (with velocity): on the realistic
    plant the learned rows are skipped and the reason names them; a missing one likewise."""
    from codesign_mb.studies.fig_cn import FigCnConfig, fig_cn_points, learned_skip_reason

    shipped = FigCnConfig(delays=(0,), reliabilities=())
    reason = learned_skip_reason(shipped)
    assert reason is not None and "not for the realistic plant" in reason
    assert "stage_b/mlp.pt" in reason
    assert {labels["pipeline"] for labels, _ in fig_cn_points(shipped)} == {"model_based"}
    gone = FigCnConfig(learned_estimators=(ComponentSpec("mlp", str(tmp_path / "no.pt")),))
    assert "checkpoints missing" in str(learned_skip_reason(gone))
    assert learned_skip_reason(FigCnConfig(learned=False)) == "not asked for (learned = false)"
    with pytest.raises(ValueError, match="distinct kinds of mlp, lstm"):
        FigCnConfig(learned_estimators=(ComponentSpec("mlp", "a.pt"), ComponentSpec("mlp", "b")))


def test_belt_speed_of_a_point_overrides_the_scenario_range() -> None:
    """Fig. 4's 0.2 and 0.6 m/s panels on the realistic scenario: the speed given is the
    episodes' base speed (the scenario's per-episode range would otherwise replace it)."""
    from codesign_mb.evaluation.evaluate import EvaluateConfig

    cfg = EvaluateConfig(scenario="realistic", belt_speed_mps=0.6).env_config()
    assert cfg.belt_speed_mps == 0.6 and cfg.belt_speed_range_mps == ()
    kept = EvaluateConfig(scenario="realistic").env_config()
    assert kept.belt_speed_range_mps == (0.1, 0.6)


def test_fig_cn_realistic_config_names_the_realistic_checkpoints() -> None:
    """The shipped config of the learned Fig. 4 reads; its rows wait for their checkpoints."""
    from codesign_mb.cli.common import load_config
    from codesign_mb.studies.fig_cn import FigCnConfig, learned_skip_reason

    path = Path(__file__).parents[1] / "configs" / "fig_cn_learned_realistic.toml"
    cfg = load_config(FigCnConfig, path, {}, section="fig_cn")
    assert [e.kind for e in cfg.learned_estimators] == ["mlp", "lstm"]
    assert cfg.learned_controller.checkpoint == "checkpoints/stage_a_realistic/model.zip"
    reason = learned_skip_reason(cfg)
    assert reason is None or "stage_a_realistic" in reason or "stage_b_realistic" in reason


def test_ideal_control_gives_the_true_velocity_the_packet_lacks() -> None:
    """Ideal control on the realistic plant: the controller gets the state layout, with the
    object's true position and velocity (zero before it spawned)."""
    from codesign_mb.network.link import BernoulliLink
    from codesign_mb.network.wrapper import LinkObservationWrapper
    from codesign_mb.rollout.loop import ClosedLoop
    from codesign_mb.stages.episodes import DelayDistribution, RandomQos

    seen: list[tuple[np.ndarray, dict[str, Any]]] = []

    class Spy:
        def reset(self, *, seed: int | None = None) -> None:
            return None

        def act(self, state: np.ndarray) -> np.ndarray:
            seen.append((state.copy(), dict(loop.info)))
            return np.zeros(4)

    env = LinkObservationWrapper(
        make_plant(PlantSpec("conveyor", {**REALISTIC.options, "horizon": 15})),
        BernoulliLink(),
        RandomQos(DelayDistribution()),
    )
    loop = ClosedLoop(env, None, Spy(), record=False)
    loop.reset(seed=3)
    while not loop.done:
        loop.step()
    phases = set()
    for state, info in seen:
        assert state.shape == (13,)
        np.testing.assert_array_equal(state[7:10], info["remote_true"])
        spawned = info["phase"] != NOT_SPAWNED
        phases.add(spawned)
        np.testing.assert_array_equal(state[10:13], info["object_vel"] if spawned else 0.0)
    assert True in phases
    env.close()


def test_no_estimator_with_nominal_velocity_fills_the_state_layout() -> None:
    """Fig. 4's learned "controller alone": the stale packet, and where it has no velocity
    the nominal belt velocity in the state layout's slot (what the MPC assumes too)."""
    from codesign_mb.core.registry import build

    realistic = make_plant(REALISTIC)
    networked = np.arange(11.0)
    alone = build("estimator", ComponentSpec("none", options={"nominal_velocity": True}), realistic)
    out = alone.reset(networked)
    np.testing.assert_array_equal(out[:10], networked[:10])
    np.testing.assert_array_equal(out[realistic.state_layout["object_vel"]], [0.0, 0.35, 0.0])
    plain = build("estimator", ComponentSpec("none"), realistic)
    np.testing.assert_array_equal(plain.reset(networked), networked[:10])
    paper = make_plant(PlantSpec("conveyor", scenario_options("paper")))
    full = build("estimator", ComponentSpec("none", options={"nominal_velocity": True}), paper)
    np.testing.assert_array_equal(full.reset(np.arange(14.0)), np.arange(13.0))  # perceived
    realistic.close()
    paper.close()
