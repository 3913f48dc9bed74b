"""Stage A by SAC from demonstrations: demo-mixed batches, LayerNorm critics, the BC term, and a
tiny training run on the toy plant whose shipped actor is SAC-trained, not the clone."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer

from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.stages.sac_from_demos import (
    ActorWarmup,
    BehaviourCloningTerm,
    DemoMixedReplayBuffer,
    make_sac_from_demos,
)
from codesign_mb.stages.stage import StageRun
from codesign_mb.stages.stage_a import StageAConfig, train_stage_a
from codesign_mb.stages.stage_a_aids import EstimatedStateEnv, curriculum_schedule, plant_at_speed
from codesign_mb.stages.training import SacSpec

TOY = PlantSpec("toy", {"horizon": 40})
TINY_SAC = SacSpec(net_arch=(32, 32), buffer_size=5_000, batch_size=32, learning_starts=0)


def _filled(buffer: ReplayBuffer, n: int, reward: float) -> None:
    for _ in range(n):
        buffer.add(
            np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 1)), np.array([reward]),
            np.array([False]), [{}],
        )  # fmt: skip


@pytest.mark.parametrize("fraction", [0.5, 0.25, 1.0, 0.0])
def test_demo_fraction_of_a_batch_is_as_configured(fraction: float) -> None:
    import gymnasium as gym

    box = gym.spaces.Box(-1.0, 1.0, (2,))
    act = gym.spaces.Box(-1.0, 1.0, (1,))
    buffer = DemoMixedReplayBuffer(100, box, act, device="cpu", demo_fraction=fraction)
    demo = ReplayBuffer(100, box, act, device="cpu")
    _filled(demo, 30, reward=1.0)  # demonstrations are marked by reward 1, online by 0
    buffer.set_demonstrations(demo)
    assert buffer.sample(64).rewards.sum().item() == 64  # no online data yet: all demos
    _filled(buffer, 50, reward=0.0)
    batch = buffer.sample(64)
    assert batch.observations.shape == (64, 2)
    assert batch.rewards.sum().item() == round(64 * fraction)


def test_layer_norm_critics_and_plain_actor() -> None:
    env = make_plant(TOY)
    model = make_sac_from_demos(env, TINY_SAC, seed=0)
    critic_norms = [m for m in model.critic.modules() if isinstance(m, torch.nn.LayerNorm)]
    assert len(critic_norms) == 2 * len(TINY_SAC.net_arch)  # two Q-nets, one per hidden layer
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in model.actor.modules())
    target = [m for m in model.critic_target.modules() if isinstance(m, torch.nn.LayerNorm)]
    assert len(target) == len(critic_norms)
    plain = make_sac_from_demos(env, TINY_SAC, seed=0, layer_norm_critics=False)
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in plain.critic.modules())
    wide = make_sac_from_demos(env, TINY_SAC, seed=0, n_critics=5)
    obs = torch.zeros((3, env.observation_space.shape[0]))
    values = wide.critic(obs, torch.zeros((3, 4)))
    assert len(values) == 5 and len(wide.critic_target(obs, torch.zeros((3, 4)))) == 5


def test_bc_term_adds_the_q_normalised_cloning_gradient_and_decays() -> None:
    env = make_plant(TOY)
    model = make_sac_from_demos(env, TINY_SAC, seed=0)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(50, env.observation_space.shape[0])).astype(np.float32)
    actions = rng.uniform(-1, 1, size=(50, 4)).astype(np.float32)
    term = BehaviourCloningTerm(model, obs, actions, weight=0.5, decay_steps=100, batch_size=8)
    model.num_timesteps = 25
    assert term.beta() == pytest.approx(0.375)  # linear: 0.5 * (1 - 25 / 100)
    # Independent computation of the same gradient on the same indices.
    idx = torch.randint(50, (8,), generator=torch.Generator().manual_seed(0))
    params = list(model.actor.parameters())
    for p in params:
        p.grad = None
    mean = model.actor(torch.as_tensor(obs[idx]), deterministic=True)
    target = torch.as_tensor(np.clip(actions[idx], -0.97, 0.97))
    with torch.no_grad():
        scale = torch.cat(model.critic(torch.as_tensor(obs[idx]), mean), dim=1).abs().mean()
    expected = torch.autograd.grad(
        0.375 * scale * ((mean - target) ** 2).sum(dim=1).mean(), params, allow_unused=True
    )
    term._hook(model.actor.optimizer, (), {})
    assert any(g is not None for g in expected)
    for p, g in zip(params, expected, strict=True):
        if g is None:  # the log-std head: the mean action does not depend on it
            assert p.grad is None or not p.grad.any()
        else:
            torch.testing.assert_close(p.grad, g)
    model.num_timesteps = 100
    assert term.beta() == 0.0
    term.remove()


def test_actor_warmup_holds_the_actor_then_ramps_its_learning_rate() -> None:
    env = make_plant(TOY)
    model = make_sac_from_demos(env, TINY_SAC, seed=0)
    warmup = ActorWarmup(model, freeze_steps=100, ramp_steps=200)
    obs = torch.zeros((4, env.observation_space.shape[0]))
    optimizer = model.actor.optimizer

    def step() -> list[torch.Tensor]:
        before = [p.detach().clone() for p in model.actor.parameters()]
        optimizer.zero_grad()
        model.actor(obs, deterministic=True).sum().backward()
        optimizer.step()
        return before

    model.num_timesteps = 60  # frozen: a real gradient, no change
    before = step()
    for old, new in zip(before, model.actor.parameters(), strict=True):
        assert torch.equal(old, new)
    assert optimizer.param_groups[0]["lr"] == 0.0
    model.num_timesteps = 150  # a quarter of the way up the ramp
    before = step()
    assert optimizer.param_groups[0]["lr"] == pytest.approx(0.25 * TINY_SAC.learning_rate)
    moved = zip(before, model.actor.parameters(), strict=True)
    assert any(not torch.equal(old, new) for old, new in moved)
    model.num_timesteps = 10_000
    step()
    assert optimizer.param_groups[0]["lr"] == pytest.approx(TINY_SAC.learning_rate)
    warmup.remove()


def test_curriculum_caps_the_per_episode_speed_range() -> None:
    realistic = PlantSpec("conveyor", {"belt_speed_mps": 0.35, "belt_speed_range_mps": (0.1, 0.6)})
    assert curriculum_schedule(realistic, (0.3,), 1000) == [(0, 0.3), (500, 0.6)]
    capped = plant_at_speed(realistic, 0.3)
    assert capped.options["belt_speed_range_mps"] == (0.1, 0.3)
    assert capped.options["belt_speed_mps"] == 0.35  # the robot's prior is kept
    constant = PlantSpec("conveyor", {"belt_speed_mps": 0.2})
    assert plant_at_speed(constant, 0.1).options["belt_speed_mps"] == 0.1


def test_estimated_state_env_gives_the_estimators_output() -> None:
    """Under the oracle link the actor's input is what the stack's estimator outputs."""
    plant = PlantSpec("conveyor", {"perceive_velocity": False})
    env = EstimatedStateEnv(plant, ComponentSpec("predictor"))
    obs, _ = env.reset(seed=3)
    base = make_plant(plant)
    assert obs.shape == (base.observation_space.shape[0] + 3,)  # the velocity estimate appended
    env2 = EstimatedStateEnv(plant, ComponentSpec("none"))
    obs2, _ = env2.reset(seed=3)
    np.testing.assert_allclose(obs2, build("estimator", ComponentSpec("none"), base).reset(
        np.append(base.reset(seed=3)[0], 0.0)), atol=1e-6)  # fmt: skip


def _actor_params(path: Path) -> list[torch.Tensor]:
    return [p.detach().clone() for p in SAC.load(path, device="cpu").actor.parameters()]


def _tiny_config(**overrides: Any) -> StageAConfig:
    """Stage A on the toy plant in two 60-step chunks, one evaluation episode each."""
    options: dict[str, Any] = {
        "plant": TOY,
        "estimator": ComponentSpec("none"),
        "sac": TINY_SAC,
        "total_steps": 120,
        "chunk_steps": 60,
        "eval_episodes": 1,
        "demo": ComponentSpec("toy_pick"),
        "demo_episodes": 2,
        "bc_epochs": 2,
        "critic_warmup_steps": 5,
        "curriculum": (),
        "final_eval_episodes": 1,
    }
    return StageAConfig(**{**options, **overrides})


def test_tiny_stage_a_ships_a_sac_trained_actor_not_the_clone(tmp_path: Path) -> None:
    config = _tiny_config(bc_decay_steps=100)
    train_stage_a(config, StageRun(tmp_path / "out", tmp_path / "work", command="t"))
    meta = json.loads((tmp_path / "out" / "training.json").read_text())
    assert meta["env_steps"] == 120 and meta["command"] == "t"
    assert meta["demonstrations"]["demo_steps"] == 2 * 40
    assert {"success_rate", "bc_success_rate"} <= set(meta["final_evaluation"])
    curve = json.loads((tmp_path / "out" / "curve.json").read_text())
    assert [(p["steps"], p["actor"]) for p in curve] == [(0, "bc"), (60, "sac"), (120, "sac")]
    assert meta["best"]["steps"] in (60, 120)  # never the clone
    clone, shipped = (
        _actor_params(tmp_path / "out" / "bc.zip"),
        _actor_params(tmp_path / "out" / "model.zip"),
    )
    assert any(not torch.equal(a, b) for a, b in zip(clone, shipped, strict=True))
    # The demo-mixed buffer is saved with its demonstrations (for --resume).
    model = SAC.load(tmp_path / "work" / "model.zip", device="cpu")
    model.load_replay_buffer(tmp_path / "work" / "replay_buffer.pkl")
    assert model.replay_buffer.demo is not None and model.replay_buffer.demo.size() == 80


def test_frozen_actor_chunks_are_evaluated_but_never_shipped(tmp_path: Path) -> None:
    """With the actor held still for the first chunk, that chunk is the clone's: not shipped."""
    config = _tiny_config(actor_freeze_steps=60, actor_ramp_steps=30)
    train_stage_a(config, StageRun(tmp_path / "out", tmp_path / "work"))
    curve = json.loads((tmp_path / "out" / "curve.json").read_text())
    assert [(p["steps"], p["actor"]) for p in curve] == [
        (0, "bc"),
        (60, "bc (frozen)"),
        (120, "sac"),
    ]
    meta = json.loads((tmp_path / "out" / "training.json").read_text())
    assert meta["best"]["steps"] == 120  # the only SAC-updated actor, whatever it scored
    clone, shipped = (
        _actor_params(tmp_path / "out" / "bc.zip"),
        _actor_params(tmp_path / "out" / "model.zip"),
    )
    assert any(not torch.equal(a, b) for a, b in zip(clone, shipped, strict=True))
    with pytest.raises(ValueError, match="actor_freeze_steps"):
        StageAConfig(total_steps=100, actor_freeze_steps=100)
