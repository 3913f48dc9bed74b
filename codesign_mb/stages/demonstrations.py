"""Stage A's start from demonstrations: their replay buffer, behaviour cloning, critic warm-up.

Demonstrations run in stage A's training env (the plant behind the perfect link, seen through
the stack's estimator: :class:`~codesign_mb.stages.stage_a_aids.EstimatedStateEnv`), so the
demonstrator acts on exactly the actor's input; a :class:`NoisyController` perturbs its
actions and every transition goes into an SB3 replay buffer (stage A's demonstration buffer,
from which half of each SAC batch is drawn).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from codesign_mb.control.base import Controller
from codesign_mb.stages.training import stage_seeds

__all__ = [
    "NoisyController",
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


def add_demonstrations(
    buffer: Any,
    env: gym.Env,
    controller: Controller,
    *,
    episodes: int,
    noise_std: float,
    seed: int,
    random_prob: float = 0.0,
) -> tuple[dict[str, float], tuple[np.ndarray, np.ndarray]]:
    """Put ``episodes`` of ``controller`` (with action noise) into the SB3 replay ``buffer``.

    ``env`` is the training env (stage A: the plant behind the perfect link seen through
    the estimator, with the shaped reward), so the demonstrator acts on the actor's input
    and its transitions carry the reward SAC learns. Transitions are stored as SB3 stores
    its own (actions scaled to [-1, 1]; a time-limit end is a truncation, not a terminal
    state). With probability
    ``random_prob`` a step's action is uniformly random. Returns the demonstrations'
    success rate and number of transitions, and the noise-free ``(observations, actions)``
    of the demonstrator (for behaviour cloning).
    """
    if not isinstance(env.action_space, gym.spaces.Box):
        raise TypeError("demonstrations need a Box action space")
    noisy = NoisyController(
        controller,
        env.action_space,
        noise_std=noise_std,
        rng=np.random.default_rng(seed),
        random_prob=random_prob,
    )
    low, high = env.action_space.low, env.action_space.high
    successes, steps = [], 0
    for s in stage_seeds(seed, episodes):
        obs, info = env.reset(seed=s)
        noisy.reset(seed=s)
        success, done = False, False
        while not done:
            action = noisy.act(np.asarray(obs, dtype=float))
            next_obs, reward, terminated, truncated, info = env.step(action)
            done = bool(terminated or truncated)
            buffer.add(
                np.asarray(obs)[None],
                np.asarray(next_obs)[None],
                (2.0 * ((action - low) / (high - low)) - 1.0)[None],  # SB3's scale_action
                np.array([reward]),
                np.array([done]),
                [{"TimeLimit.truncated": bool(truncated and not terminated)}],
            )
            obs, steps = next_obs, steps + 1
            success = success or bool(info.get("success", False))
        successes.append(success)
    stats = {
        "demo_success_rate": float(np.mean(successes)) if episodes else 0.0,
        "demo_steps": steps,
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
