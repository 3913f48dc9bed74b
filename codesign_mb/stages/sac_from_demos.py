"""SB3 SAC from demonstrations (RLPD-style): demo-mixed batches, LayerNorm critics, a BC term.

What the field uses to learn manipulation from a few demonstrations with SAC, as additions to
stable-baselines3's own :class:`~stable_baselines3.SAC` (its update, its buffers, its nets):

* :class:`DemoMixedReplayBuffer`: SB3's :class:`~stable_baselines3.common.buffers.ReplayBuffer`
  whose ``sample`` takes a fixed fraction of every batch from a second SB3 buffer holding the
  demonstrations ("symmetric sampling", RLPD, Ball et al. 2023);
* :class:`LayerNormSacPolicy`: SB3's SAC policy with LayerNorm after each hidden layer of the
  critics (RLPD: bounds the Q extrapolation on actions the data never took);
* :class:`BehaviourCloningTerm`: adds ``beta(t) * mean|Q| * ||pi(s) - a_demo||^2`` on a
  demonstration batch to every actor step (TD3+BC's Q-normalised BC term, Fujimoto & Gu
  2021), ``beta`` decaying linearly to 0, through a step pre-hook of the actor's optimiser so
  that SB3's SAC update itself is unchanged;
* the update-to-data ratio is SB3's ``gradient_steps``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.sac.policies import SACPolicy
from torch import nn

from codesign_mb.stages.training import make_sac

__all__ = [
    "ActorWarmup",
    "BehaviourCloningTerm",
    "DemoMixedReplayBuffer",
    "LayerNormSacPolicy",
    "make_sac_from_demos",
]


class DemoMixedReplayBuffer(ReplayBuffer):
    """SB3's replay buffer whose batches are ``demo_fraction`` demonstrations, the rest online.

    ``demo`` is a plain SB3 :class:`ReplayBuffer` filled once with the demonstrations
    (:meth:`set_demonstrations`); online transitions go into this buffer as usual. Before
    any online transition is stored the whole batch comes from the demonstrations. Saved and
    loaded with the model's replay buffer (the demo buffer is pickled inside it).
    """

    def __init__(self, *args: Any, demo_fraction: float = 0.5, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if not 0.0 <= demo_fraction <= 1.0:
            raise ValueError(f"demo_fraction must be in [0, 1], got {demo_fraction}")
        self.demo_fraction = float(demo_fraction)
        self.demo: ReplayBuffer | None = None

    def set_demonstrations(self, demo: ReplayBuffer) -> None:
        """The buffer the demonstration part of each batch is drawn from."""
        self.demo = demo

    def demo_count(self, batch_size: int) -> int:
        """How many of a batch of ``batch_size`` come from the demonstrations."""
        if self.demo is None or self.demo.size() == 0:
            return 0
        if self.size() == 0:
            return batch_size
        return round(self.demo_fraction * batch_size)

    def sample(self, batch_size: int, env: Any = None) -> ReplayBufferSamples:
        n_demo = self.demo_count(batch_size)
        if n_demo == 0:
            return super().sample(batch_size, env=env)
        assert self.demo is not None
        demo = self.demo.sample(n_demo, env=env)
        if n_demo == batch_size:
            return demo
        online = super().sample(batch_size - n_demo, env=env)
        return ReplayBufferSamples(
            *(None if a is None else torch.cat([a, b]) for a, b in zip(demo, online, strict=True))
        )


class LayerNormSacPolicy(SACPolicy):
    """SB3's ``MlpPolicy`` for SAC with LayerNorm after every hidden layer of the critics."""

    def make_critic(self, features_extractor: Any = None) -> ContinuousCritic:
        critic = super().make_critic(features_extractor)
        net_arch = list(self.critic_kwargs["net_arch"])
        in_dim = critic.features_extractor.features_dim + int(np.prod(self.action_space.shape))
        critic.q_networks = []
        for idx in range(critic.n_critics):
            layers = create_mlp(
                in_dim,
                1,
                net_arch,
                self.critic_kwargs["activation_fn"],
                post_linear_modules=[nn.LayerNorm],
            )
            q_net = nn.Sequential(*layers).to(self.device)
            critic.add_module(f"qf{idx}", q_net)  # replaces SB3's qf{idx}
            critic.q_networks.append(q_net)
        return critic


class BehaviourCloningTerm:
    """A decaying behaviour-cloning term added to SB3 SAC's actor loss (TD3+BC's form).

    Registered as a step pre-hook of the actor's optimiser: after SB3 has back-propagated
    its actor loss ``alpha log pi - min Q`` and before the optimiser steps, it draws
    ``batch_size`` demonstration pairs ``(s, a)`` and back-propagates
    ``beta(t) * mean|Q(s, pi(s))| * mean ||pi(s) - a||^2`` (``pi(s)`` the actor's mean
    action, ``|Q|`` detached, so ``beta`` is relative to the critic's scale). ``beta`` falls
    linearly from ``weight`` at env step ``start_step`` to 0 at ``start_step + decay_steps``
    (``model.num_timesteps``). Not saved with the model: register it again on resume.
    """

    def __init__(
        self,
        model: Any,
        observations: np.ndarray,
        actions: np.ndarray,
        *,
        weight: float,
        decay_steps: int,
        start_step: int = 0,
        batch_size: int = 256,
        seed: int = 0,
    ) -> None:
        if weight < 0 or decay_steps < 1:
            raise ValueError("weight must be >= 0 and decay_steps >= 1")
        self.model = model
        self.observations = torch.as_tensor(observations, dtype=torch.float32)
        scaled = np.clip(model.policy.scale_action(actions), -0.97, 0.97)  # inside the tanh
        self.actions = torch.as_tensor(scaled, dtype=torch.float32)
        self.weight, self.decay_steps = float(weight), int(decay_steps)
        self.start_step = int(start_step)
        self.batch_size = int(batch_size)
        self._gen = torch.Generator().manual_seed(seed)
        self.last_loss = 0.0
        self._handle = model.actor.optimizer.register_step_pre_hook(self._hook)

    def beta(self) -> float:
        """The weight now: linear from ``weight`` to 0 over ``decay_steps`` env steps."""
        done = (int(self.model.num_timesteps) - self.start_step) / self.decay_steps
        return self.weight * min(max(1.0 - done, 0.0), 1.0)

    def remove(self) -> None:
        self._handle.remove()

    def _hook(self, optimizer: Any, args: Any, kwargs: Any) -> None:
        beta = self.beta()
        if beta <= 0.0:
            self.last_loss = 0.0
            return
        idx = torch.randint(len(self.observations), (self.batch_size,), generator=self._gen)
        obs, target = self.observations[idx], self.actions[idx]
        actor, critic = self.model.actor, self.model.critic
        mean_action = actor(obs, deterministic=True)
        with torch.no_grad():
            q_scale = torch.cat(critic(obs, mean_action), dim=1).abs().mean()
        loss = beta * q_scale * ((mean_action - target) ** 2).sum(dim=1).mean()
        loss.backward()
        self.last_loss = float(loss.detach())


class ActorWarmup:
    """The actor's learning rate: 0 for ``freeze_steps`` env steps, then a linear ramp.

    A SAC started from a behaviour clone has a critic that has seen the demonstrations but
    not the clone's own states; the first actor steps then follow the critic's extrapolation
    (measured: a clone at 100 % fell to 86 % within 2 000 updates at any BC weight). Holding
    the actor still while the critic learns the clone's rollouts, then raising its learning
    rate from 0 to SB3's over ``ramp_steps``, is the critic-only phase and learning-rate
    warm-up of PIRLNav (Ramrakhya et al. 2023). A step pre-hook of the actor's optimiser
    rescales the rate SB3 set for this update (SB3's update itself is unchanged; Adam's
    moment estimates keep accumulating while the rate is 0). Not saved with the model:
    register it again on resume (it reads ``model.num_timesteps`` only).
    """

    def __init__(self, model: Any, *, freeze_steps: int, ramp_steps: int) -> None:
        if freeze_steps < 0 or ramp_steps < 0:
            raise ValueError("freeze_steps and ramp_steps must be >= 0")
        self.model = model
        self.freeze_steps, self.ramp_steps = int(freeze_steps), int(ramp_steps)
        self._handle = model.actor.optimizer.register_step_pre_hook(self._hook)

    def factor(self) -> float:
        """The share of SB3's learning rate the actor uses at the current env step."""
        past = int(self.model.num_timesteps) - self.freeze_steps
        if past <= 0:
            return 0.0
        return 1.0 if self.ramp_steps == 0 else min(past / self.ramp_steps, 1.0)

    def remove(self) -> None:
        self._handle.remove()

    def _hook(self, optimizer: Any, args: Any, kwargs: Any) -> None:
        rate = float(self.model.lr_schedule(self.model._current_progress_remaining))
        for group in optimizer.param_groups:
            group["lr"] = rate * self.factor()


def make_sac_from_demos(
    env: Any,
    spec: Any,
    *,
    seed: int,
    demo_fraction: float = 0.5,
    layer_norm_critics: bool = True,
    target_entropy: float | None = None,
    n_critics: int = 2,
) -> Any:
    """A fresh SB3 SAC (CPU, one torch thread) with the demo-mixed buffer and LayerNorm critics.

    ``spec`` is a :class:`~codesign_mb.stages.training.SacSpec`; its ``gradient_steps`` is
    the update-to-data ratio; ``n_critics`` SB3's critic ensemble (its target and actor loss
    take the minimum over all of them: more critics, a more pessimistic Q). Fill the
    demonstrations with ``model.replay_buffer.set_demonstrations(buffer)``.
    """
    return make_sac(
        env,
        spec,
        seed=seed,
        policy=LayerNormSacPolicy if layer_norm_critics else "MlpPolicy",
        policy_kwargs={"optimizer_kwargs": {"foreach": True}, "n_critics": int(n_critics)},
        target_entropy="auto" if target_entropy is None else float(target_entropy),
        replay_buffer_class=DemoMixedReplayBuffer,
        replay_buffer_kwargs={"demo_fraction": demo_fraction},
    )
