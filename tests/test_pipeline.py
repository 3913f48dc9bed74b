"""The model-free pipeline (stages A-D, Table I) on the kinematic toy plant: smoke and parity.

Every stage trains for a few hundred steps on :class:`~codesign_mb.plants.toy.ToyConveyor`
(microseconds per step), chained as the real pipeline is: A's SAC drives B's rollouts, B's
MLP is C's estimator, D continues both. The conveyor runs are the shipped checkpoints.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from codesign_mb.adaptation.learned import ElapsedTimeFeature, LearnedQosPolicy
from codesign_mb.control.sac import SacController
from codesign_mb.control.scripted import ToyPickController
from codesign_mb.core.config import from_mapping
from codesign_mb.core.registry import (
    ComponentSpec,
    PlantSpec,
    build,
    make_plant,
)
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.estimation.learned import MlpEstimator, load_estimator
from codesign_mb.network.qos import QosRequest
from codesign_mb.plants.toy import ToyConveyor
from codesign_mb.stages.dual_ascent import DualAscent, DualAscentCallback, feasible_score
from codesign_mb.stages.episodes import (
    DelayDistribution,
    RandomQos,
    collect_episodes,
    estimator_mse,
)
from codesign_mb.stages.fitting import EstimatorTraining, fit_estimator, new_estimator
from codesign_mb.stages.paths import recorded_components, resolve_recorded
from codesign_mb.stages.qos_env import QosAdaptationEnv, QosEnvConfig
from codesign_mb.stages.stage import StageRun
from codesign_mb.stages.stage_a import StageAConfig, train_stage_a
from codesign_mb.stages.stage_b import StageBConfig, train_stage_b
from codesign_mb.stages.stage_c import StageCConfig, train_stage_c
from codesign_mb.stages.stage_d import StageDConfig, _stage_c_interface, train_stage_d
from codesign_mb.stages.training import SacSpec, make_sac

TOY = PlantSpec("toy", {"horizon": 40})
TINY_SAC = SacSpec(net_arch=(32, 32), buffer_size=5_000, batch_size=32, learning_starts=50)


class _Idle:
    """A controller that never moves: every episode fails (for the dual-ascent test)."""

    def reset(self, *, seed: int | None = None) -> None:
        return None

    def act(self, observation: np.ndarray) -> np.ndarray:
        return np.array([0.0, 0.0, 0.0, -1.0])


def _qos_env(estimator=None, controller=None, **env_kwargs) -> QosAdaptationEnv:
    return QosAdaptationEnv(
        lambda: make_plant(TOY),
        estimator or PassThroughEstimator(),
        controller or ToyPickController(),
        config=QosEnvConfig(**env_kwargs),
    )


# -- the chained pipeline on the toy ------------------------------------------------------------
@pytest.fixture(scope="module")
def pipeline(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("pipeline")
    out = {s: root / f"out_{s}" for s in ("a", "b", "c", "d")}
    work = {s: root / f"work_{s}" for s in ("a", "b", "c", "d")}
    train_stage_a(
        StageAConfig(
            plant=TOY,
            sac=TINY_SAC,
            total_steps=200,
            chunk_steps=100,
            eval_episodes=1,
            demo=ComponentSpec("toy_pick"),
            demo_episodes=2,
            bc_epochs=2,
            critic_warmup_steps=20,
            estimator=ComponentSpec("none"),
            curriculum=(),
            final_eval_episodes=1,
        ),
        StageRun(out["a"], work["a"], command="test a"),
    )
    sac = ComponentSpec("sac", str(out["a"] / "model.zip"))
    train_stage_b(
        StageBConfig(
            plant=TOY,
            controller=sac,
            train_episodes=4,
            val_episodes=2,
            dagger_rounds=1,
            dagger_episodes=2,
            mlp_hidden=(16,),
            lstm_hidden=8,
            mlp=EstimatorTraining(epochs=2),
            lstm=EstimatorTraining(epochs=2),
        ),
        StageRun(out["b"], work["b"]),
    )
    stage_c = StageCConfig(
        plant=TOY,
        controller=sac,
        estimator=ComponentSpec("mlp", str(out["b"] / "mlp.pt")),
        sac=TINY_SAC,
        total_steps=200,
        chunk_steps=100,
        eval_episodes=1,
        dual=DualAscent(every_episodes=1),
    )
    train_stage_c(stage_c, StageRun(out["c"], work["c"]))
    train_stage_d(
        StageDConfig(
            plant=TOY,
            controller=sac,
            estimator=ComponentSpec("mlp", str(out["b"] / "mlp.pt")),
            qos_policy=str(out["c"]),
            episodes=2,
            val_episodes=1,
            mix_episodes=1,
            estimator_training=EstimatorTraining(epochs=2),
            qos=StageCConfig(total_steps=100, chunk_steps=100, eval_episodes=1, sac=TINY_SAC),
        ),
        StageRun(out["d"], work["d"]),
    )
    return {**{f"out_{k}": v for k, v in out.items()}, **{f"work_{k}": v for k, v in work.items()}}


def test_stage_a_writes_checkpoint_and_curve(pipeline: dict[str, Path]) -> None:
    meta = json.loads((pipeline["out_a"] / "training.json").read_text())
    assert meta["env_steps"] == 200
    assert meta["command"] == "test a"
    assert meta["demonstrations"]["demo_steps"] == 2 * 40
    curve = json.loads((pipeline["out_a"] / "curve.json").read_text())
    assert [p["steps"] for p in curve] == [0, 100, 200]  # 0: after cloning, before SAC
    assert {"success_rate", "mean_return", "wall_time_s"} <= set(curve[-1])
    assert meta["best"]["steps"] in (0, 100, 200)
    assert meta["final_evaluation"]["success_rate"] >= 0.0


def test_stage_a_resume_continues_the_step_count(pipeline: dict[str, Path], tmp_path) -> None:
    import shutil

    work = tmp_path / "work"
    shutil.copytree(pipeline["work_a"], work)
    config = StageAConfig(
        plant=TOY,
        sac=TINY_SAC,
        total_steps=300,
        chunk_steps=100,
        eval_episodes=0,
        demo=None,
        demo_episodes=0,
        bc_epochs=0,
        critic_warmup_steps=0,
        bc_weight=0.0,
        estimator=ComponentSpec("none"),
        curriculum=(),
        final_eval_episodes=1,
    )
    result = train_stage_a(config, StageRun(tmp_path / "out", work, resume=True))
    assert result["env_steps"] == 300
    state = json.loads((work / "state.json").read_text())
    assert [p["steps"] for p in state["curve"]] == [0, 100, 200, 300]


def test_stage_b_estimators_and_comparison(pipeline: dict[str, Path]) -> None:
    meta = json.loads((pipeline["out_b"] / "training.json").read_text())
    assert set(meta["held_out_mse"]) == {"mlp", "lstm", "none", "predictor"}
    for kind in ("mlp", "lstm"):
        assert meta["held_out_mse"][kind]["mse"] >= 0
        est = load_estimator(pipeline["out_b"] / f"{kind}.pt")
        assert est.kind == kind
    curve = json.loads((pipeline["out_b"] / "curve.json").read_text())
    assert {p["round"] for p in curve["mlp"]} == {0, 1}


def test_learned_estimators_save_load_identical(pipeline: dict[str, Path], tmp_path) -> None:
    env = make_plant(TOY)
    data = collect_episodes(
        TOY, ToyPickController(), RandomQos(DelayDistribution()), episodes=1, seed=0
    )
    for kind in ("mlp", "lstm"):
        a = load_estimator(pipeline["out_b"] / f"{kind}.pt")
        a.save(tmp_path / f"{kind}.pt")
        b = load_estimator(tmp_path / f"{kind}.pt")
        nets, prevs = data.networked[0].astype(float), data.prev_actions[0].astype(float)
        np.testing.assert_array_equal(a.reset(nets[0]), b.reset(nets[0]))
        for t in range(1, len(nets)):
            np.testing.assert_array_equal(
                a.estimate(nets[t], prevs[t]), b.estimate(nets[t], prevs[t])
            )
    env.close()


def test_mlp_estimator_beats_the_stale_observation() -> None:
    """Ground truth: a fitted MLP predicts the moving object better than y_t itself."""
    delays = DelayDistribution(reliability_low=0.2, latency_high=3)
    data = collect_episodes(TOY, ToyPickController(), RandomQos(delays), episodes=20, seed=1)
    val = collect_episodes(TOY, ToyPickController(), RandomQos(delays), episodes=5, seed=2)
    env = make_plant(TOY)
    est = new_estimator("mlp", env, hidden=(64, 64), age_scale=10.0, seed=0)
    curve = fit_estimator(est, data, val, EstimatorTraining(epochs=30), seed=0)
    assert curve[-1]["train_loss"] < curve[0]["train_loss"]
    kw = {"remote": env.remote_slice, "position": env.observation_layout["object_pos"]}
    learned = estimator_mse(est, val, **kw)
    stale = estimator_mse(PassThroughEstimator(), val, **kw)
    assert learned["mse_position"] < 0.5 * stale["mse_position"]


def test_estimator_output_layout() -> None:
    env = make_plant(TOY)
    est = new_estimator("mlp", env, hidden=(8,), age_scale=10.0, seed=0)
    obs, _ = env.reset(seed=0)
    networked = np.append(obs, 3.0)
    out = est.reset(networked)
    assert out.shape == obs.shape
    local = np.r_[0:7]
    np.testing.assert_array_equal(out[local], obs[local])  # only the remote part is estimated
    assert isinstance(est, MlpEstimator)


# -- stage C ------------------------------------------------------------------------------------
@pytest.mark.filterwarnings("ignore:.*Box observation space")
def test_qos_env_passes_the_gymnasium_checker() -> None:
    check_env(_qos_env(), skip_render_check=True)


def test_qos_env_reward_is_eq_q_t_pol2() -> None:
    env = _qos_env(loss="distance", j_max=0.5, lam=2.0, latency_steps=1)
    obs, _ = env.reset(seed=0)
    np.testing.assert_allclose(obs[:6], make_plant(TOY).remote_prior())  # (y_{-1}, zeta) = prior
    assert obs[6] == 0.0
    for a, q in ((1.0, 1.0), (-1.0, 0.0), (0.0, 0.5)):
        obs, reward, *_, info = env.step(np.array([a], dtype=np.float32))
        assert info["qos_reliability"] == pytest.approx(q)
        assert info["qos_latency_steps"] == 1
        expected = -(q + 2.0 * (info["gripper_object_distance"] - 0.5 / 40))
        assert reward == pytest.approx(expected)


def test_qos_env_episode_statistics_and_failure_loss() -> None:
    env = QosAdaptationEnv(
        lambda: make_plant(TOY), PassThroughEstimator(), _Idle(), config=QosEnvConfig(lam=3.0)
    )
    env.reset(seed=1)
    done, n = False, 0
    while not done:
        _, reward, terminated, truncated, info = env.step(np.array([-1.0], dtype=np.float32))
        done = terminated or truncated
        n += 1
    assert n == 41  # packets 0..T
    assert terminated and not truncated  # J is scored at T: no bootstrapping past it
    assert info["qos_episode"] == {
        "success": False,
        "constraint": 1.0,
        "mean_reliability": 0.0,
        "steps": 41,
    }
    assert reward == pytest.approx(-3.0 * (1.0 - 0.02 / 40))


@pytest.mark.parametrize(("j_max", "direction"), [(0.0, 1), (5.0, -1)])
def test_primal_dual_lambda_moves_with_the_constraint(j_max: float, direction: int) -> None:
    """Always failing: lambda rises when J_max = 0 is violated, falls when J_max is slack."""
    env = QosAdaptationEnv(
        lambda: make_plant(TOY), PassThroughEstimator(), _Idle(), config=QosEnvConfig(j_max=j_max)
    )
    model = make_sac(env, SacSpec(net_arch=(8,), learning_starts=10_000, buffer_size=1_000), seed=0)
    callback = DualAscentCallback(j_max=j_max, lam=10.0, learning_rate=2.0, every_episodes=1)
    model.learn(41 * 3, callback=callback)
    lams = [10.0] + [p["lambda"] for p in callback.history]
    if direction > 0:  # each episode fails (J = 1 > 0): lambda += 2 * (1 - 0)
        assert lams == pytest.approx([10.0, 12.0, 14.0, 16.0])
    else:  # J = 1 < 5: lambda += 2 * (1 - 5), clipped at lam_min = 0
        assert lams == pytest.approx([10.0, 2.0, 0.0, 0.0])
    assert env.lam == pytest.approx(lams[-1])  # the env sees the updated multiplier


def test_dual_ascent_is_clipped() -> None:
    env = QosAdaptationEnv(
        lambda: make_plant(TOY), PassThroughEstimator(), _Idle(), config=QosEnvConfig(j_max=0.0)
    )
    model = make_sac(env, SacSpec(net_arch=(8,), learning_starts=10_000, buffer_size=1_000), seed=0)
    callback = DualAscentCallback(
        j_max=0.0, lam=10.0, learning_rate=100.0, every_episodes=1, lam_max=15.0
    )
    model.learn(41, callback=callback)
    assert callback.lam == 15.0
    with pytest.raises(ValueError, match="lam_min <= lam_max"):
        DualAscentCallback(j_max=0.0, lam=1.0, lam_min=2.0, lam_max=1.0)


def test_stage_c_outputs_a_loadable_qos_policy(pipeline: dict[str, Path]) -> None:
    meta = json.loads((pipeline["out_c"] / "training.json").read_text())
    assert meta["env_steps"] == 200
    assert meta["dual_history"], "dual ascent ran"
    env = make_plant(TOY)
    policy = build("qos", ComponentSpec("learned", str(pipeline["out_c"])), env)
    assert isinstance(policy, LearnedQosPolicy)
    policy.reset(seed=0)
    q = policy.request(env.unwrapped.remote_prior(), 0)
    assert isinstance(q, QosRequest) and q.latency_steps == 1


def test_learned_qos_policy_save_load_identical(pipeline: dict[str, Path], tmp_path) -> None:
    a = LearnedQosPolicy.load(pipeline["out_c"])
    a.save(tmp_path / "q")
    b = LearnedQosPolicy.load(tmp_path / "q")
    rng = np.random.default_rng(0)
    for age in range(6):
        y = rng.normal(size=6)
        assert a.request(y, age) == b.request(y, age)


def test_stage_c_resume_continues(pipeline: dict[str, Path], tmp_path) -> None:
    import shutil

    work = tmp_path / "work"
    shutil.copytree(pipeline["work_c"], work)
    config = StageCConfig(
        plant=TOY,
        controller=ComponentSpec("toy_pick"),
        estimator=ComponentSpec("mlp", str(pipeline["out_b"] / "mlp.pt")),
        sac=TINY_SAC,
        total_steps=300,
        chunk_steps=100,
        eval_episodes=0,
    )
    result = train_stage_c(config, StageRun(tmp_path / "out", work, resume=True))
    assert result["env_steps"] == 300
    state = json.loads((work / "state.json").read_text())
    assert [p["steps"] for p in state["curve"]] == [100, 200, 300]
    assert "lambda" in state["extra"]


def test_stage_c_with_features_round_trips(tmp_path) -> None:
    config = StageCConfig(
        plant=TOY,
        controller=ComponentSpec("toy_pick"),
        estimator=ComponentSpec("none"),
        features="elapsed_time",
        sac=TINY_SAC,
        total_steps=100,
        chunk_steps=100,
        eval_episodes=1,
        dual=DualAscent(enabled=False),
    )
    train_stage_c(config, StageRun(tmp_path / "out", tmp_path / "work"))
    policy = LearnedQosPolicy.from_env(make_plant(TOY), tmp_path / "out")
    assert isinstance(policy.features, ElapsedTimeFeature)
    meta = json.loads((tmp_path / "out" / "training.json").read_text())
    assert meta["lambda"] == config.env.lam  # fixed lambda


def test_feasible_score_prefers_the_cheapest_feasible_policy() -> None:
    points = [
        {"eval_success_rate": 0.9, "eval_mean_reliability": 0.05},  # infeasible, cheap
        {"eval_success_rate": 1.0, "eval_mean_reliability": 0.40},
        {"eval_success_rate": 0.95, "eval_mean_reliability": 0.20},  # feasible, cheapest
        {"eval_success_rate": 0.85, "eval_mean_reliability": 0.90},
    ]
    scores = [feasible_score(p, 0.95) for p in points]
    assert int(np.argmax(scores)) == 2
    assert scores[0] > scores[3]  # among infeasible ones: the more successful
    assert feasible_score({"steps": 5}, 0.95) is None  # no evaluation


# -- stage D ------------------------------------------------------------------------------------
def test_stage_d_keeps_the_stage_c_policys_action_interface(
    pipeline: dict[str, Path], tmp_path: Path
) -> None:
    """The warm-started policy's reliability floor (an action-scale setting) carries into
    stage D's re-training; a conflicting explicit value is refused."""
    policy = tmp_path / "c"
    shutil.copytree(pipeline["out_c"], policy)
    meta = json.loads((policy / "qos_policy.json").read_text())
    meta["interface"]["min_reliability"] = 0.05
    (policy / "qos_policy.json").write_text(json.dumps(meta))
    estimator = ComponentSpec("mlp", "unused.pt")
    meta = LearnedQosPolicy.read_meta(policy)  # as stage D reads it
    interface = _stage_c_interface(StageDConfig(estimator=estimator), meta, policy)
    assert interface["min_reliability"] == 0.05
    assert interface["latency_steps"] == meta["interface"]["latency_steps"]
    clash = StageCConfig(env=QosEnvConfig(min_reliability=0.2))
    with pytest.raises(ValueError, match=r"qos.env.min_reliability=0.2 .* trained with 0.05"):
        _stage_c_interface(StageDConfig(estimator=estimator, qos=clash), meta, policy)


def test_stage_d_continues_estimator_and_qos(pipeline: dict[str, Path]) -> None:
    meta = json.loads((pipeline["out_d"] / "training.json").read_text())
    assert meta["qos"]["env_steps"] == 100
    assert {"before", "after"} <= set(meta["estimator"]["held_out_mse_under_learned_qos"])
    assert load_estimator(pipeline["out_d"] / "mlp.pt").kind == "mlp"
    qos_meta = json.loads((pipeline["out_d"] / "qos" / "training.json").read_text())
    assert not Path(qos_meta["warm_start"]).is_absolute()
    warm_start = resolve_recorded(qos_meta["warm_start"], pipeline["out_d"] / "qos")
    assert warm_start == pipeline["out_c"].resolve()
    # the multiplier continues from stage C's (which dual ascent moved every episode); stage
    # D's 100 steps finish no 20-episode window, so it ends there too
    meta_c = json.loads((pipeline["out_c"] / "training.json").read_text())
    lam_c = meta_c["shipped"]["lambda"]  # that of the shipped (best evaluated) iterate
    assert meta_c["shipped"]["steps"] == meta_c["best"]["steps"]
    assert lam_c != StageCConfig().env.lam
    assert qos_meta["lambda"] == pytest.approx(lam_c)
    LearnedQosPolicy.load(pipeline["out_d"] / "qos")


def test_checkpoints_record_relative_paths_and_load_after_a_move(
    pipeline: dict[str, Path], tmp_path: Path
) -> None:
    """Moved together, the checkpoint folders still find one another (no absolute paths)."""
    import shutil

    root = pipeline["out_a"].parent
    for name in ("out_a", "out_b", "out_c", "out_d"):
        for path in pipeline[name].rglob("*.json"):
            assert str(root) not in path.read_text(), path
        shutil.copytree(pipeline[name], tmp_path / "first" / name)
    shutil.move(tmp_path / "first", tmp_path / "then" / "elsewhere")
    moved = (tmp_path / "then" / "elsewhere").resolve()
    qos_dir = moved / "out_d" / "qos"
    components = recorded_components(qos_dir)
    assert Path(components["estimator"].checkpoint) == moved / "out_d" / "mlp.pt"
    assert Path(components["controller"].checkpoint) == moved / "out_a" / "model.zip"
    env = make_plant(TOY)
    assert isinstance(build("controller", components["controller"], env), SacController)
    assert load_estimator(components["estimator"].checkpoint).kind == "mlp"
    LearnedQosPolicy.from_env(env, qos_dir)
    meta = json.loads((qos_dir / "training.json").read_text())
    assert resolve_recorded(meta["warm_start"], qos_dir) == moved / "out_c"
    with pytest.raises(ValueError, match="not found"):
        resolve_recorded("../nope.pt", qos_dir)


def test_shipped_checkpoints_record_portable_paths() -> None:
    """Every checkpoint path in the shipped JSON is relative and resolves where it should."""
    from codesign_mb.core.registry import models_dir
    from codesign_mb.stages.paths import PATH_KEYS

    def paths(node):
        if isinstance(node, dict):
            for key, value in node.items():
                if key in PATH_KEYS and isinstance(value, str):
                    yield value
                else:
                    yield from paths(value)
        elif isinstance(node, list):
            for value in node:
                yield from paths(value)

    for path in (models_dir() / "checkpoints").rglob("*.json"):
        for recorded in paths(json.loads(path.read_text())):
            assert not Path(recorded).is_absolute(), (path, recorded)
            assert resolve_recorded(recorded, path.parent).exists()
    stage_d = models_dir() / "checkpoints" / "stage_d"
    estimator = recorded_components(stage_d / "qos")["estimator"]
    assert Path(estimator.checkpoint) == (stage_d / "mlp.pt").resolve()


# -- toy plant and configuration ------------------------------------------------------------------
@pytest.mark.filterwarnings("ignore:.*Box observation space")
def test_toy_plant_checker_and_scripted_pick() -> None:
    check_env(ToyConveyor(), skip_render_check=True)
    env = ToyConveyor()
    controller = ToyPickController.from_env(env)
    obs, _ = env.reset(seed=0)
    controller.reset()
    success = False
    for _ in range(env.horizon):
        obs, _, _, _, info = env.step(controller.act(obs))
        success = success or info["success"]
    assert success
    assert isinstance(env.observation_space, gym.spaces.Box)


def test_configs_reject_bad_values() -> None:
    with pytest.raises(ValueError, match=r"plant\.name"):
        PlantSpec("nope")
    with pytest.raises(ValueError, match="unknown key"):
        from_mapping(StageAConfig, {"total_step": 3})
    with pytest.raises(ValueError, match="demo controller"):
        StageAConfig(demo=None, demo_episodes=3)
    with pytest.raises(ValueError, match="reliability_low"):
        DelayDistribution(reliability_low=0.9, reliability_high=0.1)
    with pytest.raises(ValueError, match="unknown estimator kind"):
        build("estimator", ComponentSpec("nope"), make_plant(TOY))
    with pytest.raises(ValueError, match="needs a checkpoint"):
        build("controller", ComponentSpec("sac"), make_plant(TOY))


def test_stage_d_rejects_features_the_stage_c_policy_lacks(
    pipeline: dict[str, Path], tmp_path
) -> None:
    config = StageDConfig(
        plant=TOY,
        controller=ComponentSpec("sac", str(pipeline["out_a"] / "model.zip")),
        estimator=ComponentSpec("mlp", str(pipeline["out_b"] / "mlp.pt")),
        qos_policy=str(pipeline["out_c"]),
        qos=StageCConfig(features="predictor_std"),
    )
    with pytest.raises(ValueError, match="trained with None"):
        train_stage_d(config, StageRun(tmp_path / "out", tmp_path / "work"))


def test_shipped_stage_c_config_parses() -> None:
    """configs/stage_c_model_based.toml reproduces the shipped stage_c_mpc run's settings."""
    from codesign_mb.core.config import from_mapping, load_config_file

    root = Path(__file__).resolve().parents[1]
    config = from_mapping(
        StageCConfig, load_config_file(root / "configs" / "stage_c_model_based.toml")
    )
    assert (config.controller.kind, config.estimator.kind) == ("mpc", "predictor")
    assert not config.keep_best and not config.env.terminal_horizon


def test_every_stage_records_what_the_issue_asks_of_a_checkpoint(
    pipeline: dict[str, Path],
) -> None:
    import subprocess

    root = Path(__file__).resolve().parents[1]
    head = subprocess.run(
        ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    for stage in ("a", "b", "c", "d"):
        meta = json.loads((pipeline[f"out_{stage}"] / "training.json").read_text())
        assert {"command", "seed", "env_steps", "wall_time_s"} <= set(meta), stage
        if head:  # a source checkout: the commit (dirty or not) that trained it
            assert str(meta["git_commit"]).startswith(head), stage


def test_the_qos_env_builds_its_controller_on_the_plant_it_steps() -> None:
    """The MPC reads the arm's joint sensors of the plant it was built for: built on another
    instance, it steered by a robot that never moved (0 % at q = 1 on realistic)."""
    import numpy as np

    from codesign_mb.core.registry import ComponentSpec, PlantSpec
    from codesign_mb.plants.scenarios import scenario_options
    from codesign_mb.stages.stage_c import StageCConfig, make_qos_env

    config = StageCConfig(
        plant=PlantSpec("conveyor", scenario_options("realistic")),
        controller=ComponentSpec("mpc"),
        estimator=ComponentSpec("belt_imm"),
    )
    env = make_qos_env(config)
    assert env.controller._joint_state.__self__ is env.wrapped.unwrapped.sim
    successes = 0
    for seed in range(2):
        env.reset(seed=seed)
        done = False
        while not done:  # q = 1 on every step: the stack's static row (98 % on realistic)
            _, _, terminated, truncated, info = env.step(np.ones(env.action_space.shape))
            done = terminated or truncated
        successes += bool(info["qos_episode"]["success"])
    assert successes >= 1


@pytest.mark.parametrize(("given", "expected"), [(0.01, 0.01), ("0.02", 0.02)])
def test_a_fixed_entropy_coefficient_is_given_as_a_number_or_a_string(
    given: float | str, expected: float
) -> None:
    """``--set sac.ent_coef=0.01`` (a number) and ``"0.02"`` both fix SAC's coefficient."""
    spec = from_mapping(SacSpec, {"ent_coef": given, "net_arch": [8], "learning_starts": 10})
    env = QosAdaptationEnv(lambda: make_plant(TOY), PassThroughEstimator(), _Idle())
    model = make_sac(env, spec, seed=0)
    assert model.ent_coef_optimizer is None  # not learned
    assert float(model.ent_coef_tensor) == pytest.approx(expected)
    for bad in (0.0, -1.0, "fast"):
        with pytest.raises(ValueError, match="ent_coef"):
            SacSpec(ent_coef=bad)


def test_stage_b_and_d_collection_builds_the_controller_on_the_plant_it_steps() -> None:
    """``collect_episodes`` builds a controller spec on its own plant: the arm-aware MPC built
    on another instance (as stages B and D did) reads joints that never move and fails."""
    from codesign_mb.adaptation.base import StaticQos
    from codesign_mb.core.registry import ComponentSpec, PlantSpec, build
    from codesign_mb.plants.scenarios import scenario_options

    plant = PlantSpec("conveyor", scenario_options("realistic"))
    probe = make_plant(plant)
    behaviour = build("estimator", ComponentSpec("belt_imm"), probe)
    link = StaticQos(1.0, 1)
    data = collect_episodes(
        plant, ComponentSpec("mpc"), link, episodes=2, seed=0, behaviour=behaviour
    )
    assert any(data.success)  # the stack's static row: 98 % on realistic
    stale = build("controller", ComponentSpec("mpc"), probe)  # built on the probe, not stepped
    data = collect_episodes(plant, stale, link, episodes=2, seed=0, behaviour=behaviour)
    assert not any(data.success)
    probe.close()
