"""Stage A's start from demonstrations: replay buffer, behaviour cloning, critic warm-up.

Demonstrations run through THE closed loop (:class:`~codesign_mb.rollout.ClosedLoop`) with
ideal control (``estimator=None``) behind a perfect link (``q = 1``, ``tau = 0``), so the
demonstrator acts on the plant's own observation: a :class:`NoisyController` perturbs its
actions, a :class:`ReplayBufferWriter` observer puts every transition into SAC's replay buffer.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.base import Controller
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.rollout.loop import ClosedLoop, Transition
from codesign_mb.stages.training import stage_seeds

__all__ = [
    "NoisyController",
    "ReplayBufferWriter",
    "add_demonstrations",
    "clone_behaviour",
    "warm_up_critic",
]


class NoisyController:
    """A demonstrator with Gaussian action noise and epsilon-random steps.

    Each action is ``clip(a + noise_std * N(0, I))`` of the clipped demonstrator action ``a``;
    with probability ``random_prob`` it is uniform in the action box instead. The noise-free
    ``(observation, action)`` pairs are kept in :attr:`clean_observations` and
    :attr:`clean_actions` (float32, for behaviour cloning).
    """

    def __init__(
        self,
        controller: Controller,
        action_space: gym.spaces.Box,
        *,
        noise_std: float,
        rng: np.random.Generator,
        random_prob: float = 0.0,
    ) -> None:
        self.controller = controller
        self.low, self.high = action_space.low, action_space.high
        self.noise_std = float(noise_std)
        self.random_prob = float(random_prob)
        self._rng = rng
        self.clean_observations: list[NDArray[np.float32]] = []
        self.clean_actions: list[NDArray[np.float32]] = []

    def reset(self, *, seed: int | None = None) -> None:
        self.controller.reset(seed=seed)

    def act(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        clean = np.clip(
            np.asarray(self.controller.act(observation), dtype=np.float64), self.low, self.high
        )
        self.clean_observations.append(np.asarray(observation, dtype=np.float32))
        self.clean_actions.append(clean.astype(np.float32))
        noise = self.noise_std * self._rng.standard_normal(clean.shape)
        action = np.clip(clean + noise, self.low, self.high)
        if self.random_prob and self._rng.random() < self.random_prob:
            action = self._rng.uniform(self.low, self.high)
        return action


class ReplayBufferWriter:
    """A :class:`~codesign_mb.rollout.loop.Transition` observer filling SB3's replay buffer.

    Under ideal control the state the controller is given is the plant's observation; the next
    one is rebuilt the same way (the networked observation with the true remote state).
    Transitions are stored as SB3 stores its own: a time-limit end is a truncation, not a
    terminal state. Counts :attr:`steps` and whether the episode succeeded.
    """

    def __init__(self, model: Any, remote: slice) -> None:
        self.model = model
        self.remote = remote
        self.steps = 0
        self.success = False

    def start_episode(self, info: dict[str, Any]) -> None:
        self.success = bool(info.get("success", False))

    def __call__(self, step: Transition) -> None:
        next_obs = np.array(step.next_observation[:-1], dtype=float)
        next_obs[self.remote] = step.info["remote_true"]
        self.model.replay_buffer.add(
            np.asarray(step.state)[None],
            next_obs[None],
            self.model.policy.scale_action(step.action)[None],
            np.array([step.reward]),
            np.array([step.terminated or step.truncated]),
            [{"TimeLimit.truncated": bool(step.truncated and not step.terminated)}],
        )
        self.steps += 1
        self.success = self.success or bool(step.info.get("success", False))


def add_demonstrations(
    model: Any,
    env: gym.Env,
    controller: Controller,
    *,
    episodes: int,
    noise_std: float,
    seed: int,
    random_prob: float = 0.0,
) -> tuple[dict[str, float], tuple[np.ndarray, np.ndarray]]:
    """Put ``episodes`` of ``controller`` (with action noise) into ``model``'s replay buffer.

    ``env`` is the training plant (perfect state; its reward is what SAC learns). With
    probability ``random_prob`` a step's action is uniformly random. Returns the
    demonstrations' success rate and number of transitions, and the noise-free
    ``(observations, actions)`` of the demonstrator (for behaviour cloning).
    """
    if not isinstance(env.action_space, gym.spaces.Box):
        raise TypeError("demonstrations need a Box action space")
    perfect = LinkObservationWrapper(env, BernoulliLink(), StaticQos(1.0, 0))
    noisy = NoisyController(
        controller,
        env.action_space,
        noise_std=noise_std,
        rng=np.random.default_rng(seed),
        random_prob=random_prob,
    )
    writer = ReplayBufferWriter(model, perfect.remote_slice)
    loop = ClosedLoop(perfect, None, noisy, observer=writer, record=False)
    successes = []
    for s in stage_seeds(seed, episodes):
        writer.start_episode(loop.reset(seed=s))
        while not loop.done:
            loop.step()
        successes.append(writer.success)
    stats = {
        "demo_success_rate": float(np.mean(successes)) if episodes else 0.0,
        "demo_steps": writer.steps,
    }
    return stats, (np.asarray(noisy.clean_observations), np.asarray(noisy.clean_actions))


def clone_behaviour(
    model: Any,
    observations: np.ndarray,
    actions: np.ndarray,
    *,
    epochs: int,
    action_std: float,
    seed: int,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
) -> float:
    """Initialise SAC's actor by behaviour cloning (supervised MSE, torch) of demonstrations.

    The actor's mean action is fitted to the demonstrated actions (clipped to +-0.97, inside
    the tanh squashing) and its log standard deviation to ``log(action_std)``, so that SAC
    starts from the demonstrator with a moderate exploration noise. Returns the final loss.
    """
    import torch

    actor = model.actor
    obs = torch.as_tensor(observations, dtype=torch.float32)
    target = torch.as_tensor(np.clip(actions, -0.97, 0.97), dtype=torch.float32)
    target_log_std = float(np.log(action_std))
    optimiser = torch.optim.Adam(actor.parameters(), lr=learning_rate)
    gen = torch.Generator().manual_seed(seed)
    loss_value = float("nan")
    for _ in range(epochs):
        order = torch.randperm(len(obs), generator=gen)
        for start in range(0, len(obs), batch_size):
            idx = order[start : start + batch_size]
            mean, log_std, _ = actor.get_action_dist_params(obs[idx])
            loss = ((torch.tanh(mean) - target[idx]) ** 2).mean()
            loss = loss + 0.1 * ((log_std - target_log_std) ** 2).mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            loss_value = loss.item()
    return loss_value


def warm_up_critic(model: Any, steps: int) -> None:
    """SB3's own SAC updates with the actor frozen: the critic learns the cloned policy's value."""
    from stable_baselines3.common.logger import configure

    if steps <= 0:
        return
    model.set_logger(configure(None, []))
    actor_params = list(model.actor.parameters())
    for p in actor_params:
        p.requires_grad_(False)
    try:
        model.train(gradient_steps=steps, batch_size=model.batch_size)
    finally:
        for p in actor_params:
            p.requires_grad_(True)
