"""The stages run THE closed loop: same seeds, same data as their former hand-written loops.

The shipped checkpoints were trained by the hand-written episode loops the stages had before
they ran :class:`~codesign_mb.rollout.ClosedLoop`. Copies of those loops are kept here (the
``_old_*`` functions and ``_OldQosEnv``), and each test asserts, on the toy plant, that the
new code collects exactly the same arrays.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from codesign_mb.control.sac import SacController
from codesign_mb.control.scripted import ToyPickController
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.stages.demonstrations import add_demonstrations
from codesign_mb.stages.episodes import DelayDistribution, EpisodeData, RandomQos, collect_episodes
from codesign_mb.stages.fitting import new_estimator
from codesign_mb.stages.qos_env import QosAdaptationEnv, QosEnvConfig
from codesign_mb.stages.stage_a_aids import Shaping, evaluate_ideal
from codesign_mb.stages.training import SacSpec, make_sac, stage_seeds

TOY = PlantSpec("toy", {"horizon": 40})
TINY_SAC = SacSpec(net_arch=(16,), buffer_size=2_000, batch_size=16, learning_starts=10)


def _seeds(seed: int, n: int) -> np.ndarray:
    return np.random.SeedSequence(seed).generate_state(max(n, 1))


# -- the former loops, verbatim ------------------------------------------------------------------
def _old_collect_episodes(
    plant: PlantSpec, controller: Any, qos_policy: Any, *, episodes: int, seed: int, behaviour=None
) -> EpisodeData:
    env = LinkObservationWrapper(make_plant(plant), BernoulliLink(), qos_policy)
    remote = env.remote_slice
    data = EpisodeData()
    for s in [int(s) for s in _seeds(seed, episodes)[:episodes]]:
        obs, info = env.reset(seed=s)
        controller.reset(seed=s)
        estimate = behaviour.reset(obs) if behaviour is not None else None
        act_dim = int(np.prod(env.action_space.shape))
        nets, prevs, truths, qs = [obs], [np.zeros(act_dim)], [info["remote_true"]], []
        qs.append(info["qos_reliability"])
        success, done = bool(info.get("success", False)), False
        while not done:
            if behaviour is None:
                state = np.asarray(obs[:-1], dtype=float).copy()
                state[remote] = info["remote_true"]
            else:
                state = estimate
            action = np.asarray(controller.act(state), dtype=float)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
            success = success or bool(info.get("success", False))
            if behaviour is not None and not done:
                estimate = behaviour.estimate(obs, action)
            nets.append(obs)
            prevs.append(action)
            truths.append(info["remote_true"])
            qs.append(info["qos_reliability"])
        data.networked.append(np.asarray(nets, dtype=np.float32))
        data.prev_actions.append(np.asarray(prevs, dtype=np.float32))
        data.truth.append(np.asarray(truths, dtype=np.float32))
        data.reliability.append(np.asarray(qs, dtype=np.float32))
        data.success.append(success)
    env.close()
    return data


def _old_evaluate_ideal(plant: PlantSpec, controller: Any, *, episodes: int, seed: int) -> dict:
    env = make_plant(plant)
    seeds = _seeds(seed, episodes)
    successes, returns = [], []
    for i in range(episodes):
        obs, info = env.reset(seed=int(seeds[i]))
        controller.reset(seed=int(seeds[i]))
        infos, total, done = [info], 0.0, False
        while not done:
            obs, reward, terminated, truncated, info = env.step(controller.act(obs))
            infos.append(info)
            total += float(reward)
            done = terminated or truncated
        successes.append(any(bool(i.get("success", False)) for i in infos))
        returns.append(total)
    env.close()
    if not episodes:
        return {}
    return {"success_rate": float(np.mean(successes)), "mean_return": float(np.mean(returns))}


def _old_add_demonstrations(
    model: Any, env: gym.Env, controller: Any, *, episodes: int, noise_std: float, seed: int,
    random_prob: float = 0.0,
) -> tuple[dict, tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    rng = np.random.default_rng(seed)
    seeds = _seeds(seed, episodes)
    low, high = env.action_space.low, env.action_space.high
    successes, n = [], 0
    clean_obs, clean_actions = [], []
    for i in range(episodes):
        obs, info = env.reset(seed=int(seeds[i]))
        controller.reset(seed=int(seeds[i]))
        infos, done = [info], False
        while not done:
            clean = np.clip(np.asarray(controller.act(obs), dtype=np.float64), low, high)
            clean_obs.append(np.asarray(obs, dtype=np.float32))
            clean_actions.append(clean.astype(np.float32))
            action = np.clip(clean + noise_std * rng.standard_normal(clean.shape), low, high)
            if random_prob and rng.random() < random_prob:
                action = rng.uniform(low, high)
            next_obs, reward, terminated, truncated, info = env.step(action)
            infos.append(info)
            model.replay_buffer.add(
                np.asarray(obs)[None],
                np.asarray(next_obs)[None],
                model.policy.scale_action(action)[None],
                np.array([reward]),
                np.array([terminated or truncated]),
                [{"TimeLimit.truncated": bool(truncated and not terminated)}],
            )
            obs = next_obs
            n += 1
            done = terminated or truncated
        successes.append(any(bool(i.get("success", False)) for i in infos))
    stats = {"demo_success_rate": float(np.mean(successes)) if episodes else 0.0, "demo_steps": n}
    return stats, (np.asarray(clean_obs), np.asarray(clean_actions))


class _OldQosEnv(QosAdaptationEnv):
    """The QoS env with its former hand-written robot step."""

    def step(self, action):
        if self._done:
            raise RuntimeError("call reset() before step()")
        qos = self.interface.request(action)
        self._qos.next = qos
        if not self._started:
            obs, info = self.wrapped.reset(seed=self._episode_seed)
            self.controller.reset(seed=self._episode_seed)
            self._estimate = self.estimator.reset(obs)
            terminated = truncated = False
            self._started = True
        else:
            u = np.asarray(self.controller.act(self._estimate))
            obs, _, terminated, truncated, info = self.wrapped.step(u)
            if not (terminated or truncated):
                self._estimate = self.estimator.estimate(obs, u)
        done = bool(terminated or truncated)
        s = self._stats
        s["success"] = bool(s["success"] or info.get("success", False))
        loss = self._loss(info, done)
        s["constraint"] += loss
        s["reliability"] += qos.reliability
        s["steps"] += 1
        c = self.config
        reward = -(float(info["qos_cost"]) + self.lam * (loss - c.j_max / self.horizon))
        rx = self.wrapped.last_reception
        next_obs = self._observe(rx.observation, rx.age)
        info = dict(info)
        info["lambda"] = self.lam
        info["task_loss"] = loss
        if done:
            self._done = True
            info["qos_episode"] = {
                "success": s["success"],
                "constraint": s["constraint"],
                "mean_reliability": s["reliability"] / s["steps"],
                "steps": s["steps"],
            }
        if c.terminal_horizon:
            return next_obs, reward, done, False, info
        return next_obs, reward, bool(terminated), bool(truncated), info

    def _loss(self, info, done):
        if self.config.loss != "estimation_error":
            return super()._loss(info, done)
        estimate = np.asarray(self._estimate)[self.wrapped.remote_slice]
        return float(np.linalg.norm(estimate - np.asarray(info["remote_true"])))


# -- parity ------------------------------------------------------------------------------------
def _assert_same_data(new: EpisodeData, old: EpisodeData) -> None:
    assert len(new) == len(old) and new.success == old.success
    for name in ("networked", "prev_actions", "truth", "reliability"):
        for a, b in zip(getattr(new, name), getattr(old, name), strict=True):
            np.testing.assert_array_equal(a, b, err_msg=name)


@pytest.mark.parametrize("behaviour", [None, "mlp", "lstm"])
def test_collect_episodes_equals_the_former_loop(behaviour: str | None) -> None:
    """Ideal trajectories (no behaviour estimator) and DAgger ones (acting through it)."""
    env = make_plant(TOY)
    qos = RandomQos(DelayDistribution(reliability_low=0.3, latency_high=3))
    estimator = None
    if behaviour is not None:
        hidden = (16,) if behaviour == "mlp" else 8
        estimator = new_estimator(behaviour, env, hidden=hidden, age_scale=10.0, seed=0)
    old = _old_collect_episodes(
        TOY, ToyPickController(), qos, episodes=3, seed=7, behaviour=estimator
    )
    new = collect_episodes(TOY, ToyPickController(), qos, episodes=3, seed=7, behaviour=estimator)
    _assert_same_data(new, old)
    if behaviour is None:  # the scripted pick succeeds on the truth: not a vacuous comparison
        assert all(new.success)


def test_evaluate_ideal_equals_the_former_loop() -> None:
    env = make_plant(TOY)
    untrained = SacController(make_sac(env, TINY_SAC, seed=1))
    for controller in (ToyPickController(), untrained):
        new = evaluate_ideal(TOY, controller, seeds=stage_seeds(5, 3))
        old = _old_evaluate_ideal(TOY, controller, episodes=3, seed=5)
        assert new == old
    assert evaluate_ideal(TOY, ToyPickController(), seeds=stage_seeds(5, 3))["success_rate"] == 1.0
    assert evaluate_ideal(TOY, untrained, seeds=[]) == {}


def test_add_demonstrations_equals_the_former_loop() -> None:
    """The same replay buffer, statistics and clean pairs, with noise and random steps."""

    def shaped() -> gym.Env:
        return Shaping(make_plant(TOY), 5.0, 0.9, grip_penalty=1.0)

    models, outputs = [], []
    for fill in (_old_add_demonstrations, add_demonstrations):
        env = shaped()
        model = make_sac(env, TINY_SAC, seed=0)
        target = model.replay_buffer if fill is add_demonstrations else model  # a buffer now
        outputs.append(
            fill(
                target, env, ToyPickController(), episodes=3, noise_std=0.1, seed=2, random_prob=0.2
            )
        )
        models.append(model)
    (old_stats, (old_obs, old_act)), (new_stats, (new_obs, new_act)) = outputs
    assert new_stats == old_stats and new_stats["demo_steps"] == 3 * 40
    np.testing.assert_array_equal(new_obs, old_obs)
    np.testing.assert_array_equal(new_act, old_act)
    old_buffer, new_buffer = (m.replay_buffer for m in models)
    assert new_buffer.pos == old_buffer.pos == 120
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        np.testing.assert_array_equal(getattr(new_buffer, name), getattr(old_buffer, name), name)


def _assert_same_info(new: dict, old: dict) -> None:
    assert new.keys() == old.keys()
    for key, value in old.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(new[key], value, err_msg=key)
        else:
            assert new[key] == value, key


@pytest.mark.parametrize("loss", ["failure", "distance", "estimation_error"])
def test_qos_env_steps_the_robot_as_before(loss: str) -> None:
    """Random QoS actions: observations, rewards, ends and infos equal the former step."""
    plant = make_plant(TOY)
    envs = [
        cls(
            lambda: make_plant(TOY),
            build("estimator", ComponentSpec("predictor"), plant),
            ToyPickController(),
            config=QosEnvConfig(loss=loss, lam=3.0),
        )
        for cls in (_OldQosEnv, QosAdaptationEnv)
    ]
    rng = np.random.default_rng(0)
    for seed in (3, 4):
        first = [env.reset(seed=seed)[0] for env in envs]
        np.testing.assert_array_equal(first[1], first[0])
        done = False
        while not done:
            action = rng.uniform(-1.0, 1.0, size=1).astype(np.float32)
            old, new = (env.step(action) for env in envs)
            np.testing.assert_array_equal(new[0], old[0])
            assert new[1:4] == old[1:4]
            _assert_same_info(new[4], old[4])
            done = new[2] or new[3]
        assert new[4]["qos_episode"]["steps"] == 41
