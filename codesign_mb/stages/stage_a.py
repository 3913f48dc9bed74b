"""Stage A, the ideal control policy (``eq_control_ideal``): SB3 SAC on the perfect state.

The plant is trained without a link (perfect state, the paper's "ideal" controller), with the
plant's own dense reward. Two optional accelerators keep the cost inside the shared machine's
budget, both plain SB3 usage (no RL algorithm is written here):

* ``demo_episodes``: episodes of a demonstration controller (e.g. the scripted or MPC pick,
  with Gaussian action noise) are put in SAC's replay buffer before learning (SAC from
  demonstrations); SAC then learns off-policy from them and from its own experience;
* ``curriculum``: belt speeds (m/s) stepped through in equal parts of the step budget, ending
  at the plant's configured speed.

Hindsight experience replay is not used: the conveyor's goal (lift the object) is fixed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, CallbackList

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.base import Controller
from codesign_mb.control.sac import SacController
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.rollout.loop import rollout
from codesign_mb.stages.demonstrations import add_demonstrations, clone_behaviour, warm_up_critic
from codesign_mb.stages.stage_a_aids import (
    Curriculum,
    FreezeActor,
    Shaping,
    SpeedSwitch,
    curriculum_schedule,
    plant_at_speed,
    scale_actor_learning_rate,
)
from codesign_mb.stages.training import (
    Progress,
    SacSpec,
    TrainingState,
    load_state,
    make_sac,
    no_progress,
    require_at_least,
    resume_sac,
    stage_seeds,
    train_sac_in_chunks,
    write_output,
)

__all__ = ["StageAConfig", "evaluate_ideal", "train_stage_a"]


@dataclass(frozen=True)
class StageAConfig:
    """Configuration of stage A.

    Parameters
    ----------
    plant:
        The plant (perfect state: no link).
    sac:
        SAC hyper-parameters.
    total_steps:
        Env steps of SAC experience (demonstrations not counted).
    chunk_steps:
        Steps between checkpoints / evaluations.
    seed:
        Root seed (SAC, env, demonstrations, evaluation).
    eval_episodes:
        Deterministic evaluation episodes after each chunk.
    demo:
        Demonstration controller (``None``: no demonstrations).
    demo_episodes:
        Episodes of ``demo`` put in the replay buffer before learning.
    demo_noise_std:
        Std of the Gaussian noise added to demonstration actions (in action units).
    demo_random_prob:
        Probability that a demonstration step takes a uniformly random action instead
        (epsilon-exploration): the critic then also sees what the demonstrator never does
        (e.g. closing the gripper far from the object), which keeps it from crediting the
        grip with the value of the states where the demonstrator happens to close it.
    curriculum:
        Belt speeds (``belt_speed_mps``, m/s) trained on before the plant's own, each for an
        equal share of ``total_steps``. Empty: no curriculum.
    shaping_weight:
        Potential-based shaping (Ng et al. 1999) added to the plant's reward,
        ``w (d_t - gamma d_{t+1})`` with ``d`` the gripper-object distance in m: a gradient
        towards the object where the plant's ``1 - tanh(10 d)`` is flat (``d > 0.2`` m);
        it leaves the optimal policy unchanged. 0: off.
    grip_penalty, grip_radius_m:
        Reward ``-grip_penalty`` for every step the gripper is commanded closed while the
        object is farther than ``grip_radius_m`` from it. Closing early costs nothing in the
        plant's reward for many steps (the failure shows only at the grasp), so without this
        the critic credits the grip with the value of the holding phase and SAC's actor learns
        to close at once. 0: off.
    bc_epochs, bc_action_std:
        Behaviour-cloning epochs initialising the actor on the (noise-free) demonstrations,
        and the exploration std its log-std is fitted to. 0: no cloning.
    critic_warmup_steps:
        SAC gradient steps on the demonstrations with the actor frozen, before learning.
    actor_freeze_steps:
        For the first ``actor_freeze_steps`` env steps SAC updates the critic only (the actor
        is frozen): the critic first learns the value of the cloned policy from its own
        experience, so that the actor's first updates follow a meaningful gradient instead of
        unlearning the demonstrations (the offline-to-online collapse).
    actor_lr_scale:
        The actor's learning rate is ``sac.learning_rate * actor_lr_scale`` (the critic's is
        ``sac.learning_rate``): Adam moves every weight by about its learning rate per step,
        which at SAC's usual rate unlearns a cloned policy within a few updates.
    final_eval_episodes:
        Episodes of the final evaluation of the shipped (best) model.

    The shipped model is the best of the evaluations after each chunk and of the one before
    online learning (ties: the later), as SB3's ``EvalCallback`` keeps it.
    """

    plant: PlantSpec = field(default_factory=PlantSpec)
    sac: SacSpec = field(
        default_factory=lambda: SacSpec(
            gamma=0.9, tau=0.02, ent_coef="auto_0.01", learning_rate=3e-4
        )
    )
    total_steps: int = 20_000
    chunk_steps: int = 5_000
    seed: int = 0
    eval_episodes: int = 20
    demo: ComponentSpec | None = field(default_factory=lambda: ComponentSpec("scripted"))
    demo_episodes: int = 100
    demo_noise_std: float = 0.1
    demo_random_prob: float = 0.0
    curriculum: tuple[float, ...] = ()
    shaping_weight: float = 5.0
    grip_penalty: float = 1.0
    grip_radius_m: float = 0.04
    bc_epochs: int = 50
    bc_action_std: float = 0.2
    critic_warmup_steps: int = 10_000
    actor_freeze_steps: int = 5_000
    actor_lr_scale: float = 0.01
    final_eval_episodes: int = 100

    def __post_init__(self) -> None:
        require_at_least(self, 1, "total_steps", "chunk_steps", "final_eval_episodes")
        require_at_least(self, 0, "eval_episodes", "demo_episodes")
        if self.demo_episodes and self.demo is None:
            raise ValueError("demo_episodes > 0 needs a demo controller (demo.kind)")
        if not 0.0 <= self.demo_random_prob <= 1.0:
            raise ValueError(f"demo_random_prob must be in [0, 1], got {self.demo_random_prob}")
        if self.demo_noise_std < 0:
            raise ValueError(f"demo_noise_std must be >= 0, got {self.demo_noise_std}")
        if any(v < 0 for v in self.curriculum):
            raise ValueError(f"curriculum belt speeds must be >= 0, got {self.curriculum}")
        if self.shaping_weight < 0:
            raise ValueError(f"shaping_weight must be >= 0, got {self.shaping_weight}")
        if self.grip_penalty < 0 or self.grip_radius_m <= 0:
            raise ValueError("grip_penalty must be >= 0 and grip_radius_m > 0")
        if self.bc_epochs < 0 or self.critic_warmup_steps < 0:
            raise ValueError("bc_epochs and critic_warmup_steps must be >= 0")
        if (self.bc_epochs or self.critic_warmup_steps) and not self.demo_episodes:
            raise ValueError("bc_epochs / critic_warmup_steps need demo_episodes > 0")
        if self.actor_lr_scale <= 0:
            raise ValueError(f"actor_lr_scale must be > 0, got {self.actor_lr_scale}")
        if self.bc_action_std <= 0:
            raise ValueError(f"bc_action_std must be > 0, got {self.bc_action_std}")


