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
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback, CallbackList

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.base import Controller
from codesign_mb.control.sac import SacController
from codesign_mb.core.config import EPISODES_CAP, TRAINING_STEPS_CAP
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
    EPOCHS_CAP,
    Progress,
    SacSpec,
    TrainingState,
    load_state,
    make_sac,
    no_progress,
    require_at_least,
    resume_sac,
    selection_seeds,
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
        Root seed (SAC, env, demonstrations, final evaluation).
    eval_episodes:
        Deterministic evaluation episodes after each chunk, on the ``dev`` seed set (the
        same episodes whatever ``seed``; :func:`~codesign_mb.stages.training.selection_seeds`).
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
        require_at_least(self, 1, "total_steps", "chunk_steps", cap=TRAINING_STEPS_CAP)
        require_at_least(self, 0, "eval_episodes", "demo_episodes", cap=EPISODES_CAP)
        require_at_least(
            self, 0, "critic_warmup_steps", "actor_freeze_steps", cap=TRAINING_STEPS_CAP
        )
        require_at_least(self, 0, "bc_epochs", cap=EPOCHS_CAP)
        if self.demo_episodes and self.demo is None:
            raise ValueError("demo_episodes > 0 needs a demo controller (demo.kind)")
        if not 0.0 <= self.demo_random_prob <= 1.0:
            raise ValueError(f"demo_random_prob must be in [0, 1], got {self.demo_random_prob}")
        require_at_least(self, 0, "demo_noise_std")
        if any(v < 0 for v in self.curriculum):
            raise ValueError(f"curriculum belt speeds must be >= 0, got {self.curriculum}")
        require_at_least(self, 0, "shaping_weight")
        if self.grip_penalty < 0 or self.grip_radius_m <= 0:
            raise ValueError("grip_penalty must be >= 0 and grip_radius_m > 0")
        if self.bc_epochs < 0 or self.critic_warmup_steps < 0:
            raise ValueError("bc_epochs and critic_warmup_steps must be >= 0")
        if (self.bc_epochs or self.critic_warmup_steps) and not self.demo_episodes:
            raise ValueError("bc_epochs / critic_warmup_steps need demo_episodes > 0")
        if self.actor_lr_scale <= 0:
            raise ValueError(f"actor_lr_scale must be > 0, got {self.actor_lr_scale}")
        require_at_least(self, 1, "final_eval_episodes", cap=EPISODES_CAP)
        if self.bc_action_std <= 0:
            raise ValueError(f"bc_action_std must be > 0, got {self.bc_action_std}")


def evaluate_ideal(
    plant: PlantSpec, controller: Controller, *, seeds: Sequence[int]
) -> dict[str, float]:
    """Success rate and mean return of ``controller`` on the perfect state, one episode a seed.

    Each episode is :func:`~codesign_mb.rollout.rollout` with ideal control
    (``estimator=None``: the controller sees the plant's observation) behind a perfect link
    (``q = 1``, ``tau = 0``, which changes nothing the plant or the controller sees).
    """
    if not seeds:
        return {}
    env = LinkObservationWrapper(make_plant(plant), BernoulliLink(), StaticQos(1.0, 0))
    successes, returns = [], []
    for s in seeds:
        table = rollout(env, None, controller, seed=s)
        successes.append("success" in table and bool(table["success"].any()))
        total = 0.0
        for reward in table["reward"]:  # summed in step order, as SAC's episode return
            total += float(reward)
        returns.append(total)
    env.close()
    return {"success_rate": float(np.mean(successes)), "mean_return": float(np.mean(returns))}


_NOTES = (
    "SB3 SAC on the perfect state (no HER): plant reward + potential-based distance "
    "shaping + early-grip penalty; actor initialised by behaviour cloning of the "
    "demonstrations, critic pre-trained with SB3 SAC updates (actor frozen), then SAC; "
    "the shipped model is the best evaluation, on the dev seed set (see 'best' and "
    "curve.json). "
    "wall_time_s counts the SAC chunks; setup_wall_time_s the demonstrations, cloning and "
    "critic warm-up; the command's total_wall_time_s everything of this session."
)


def train_stage_a(
    config: StageAConfig,
    *,
    out_dir: str | Path,
    work_dir: str | Path,
    resume: bool = False,
    progress: Progress = no_progress,
    command: str | None = None,
) -> dict[str, Any]:
    """Train the ideal SAC controller; write the checkpoint to ``out_dir``.

    Steps: build the (shaped, curriculum) training env; resume from ``work_dir`` or start a
    new SAC, warm-started from demonstrations; train in chunks keeping the best evaluation;
    evaluate the shipped model; write ``out_dir``. Returns the summary written to
    ``out_dir/training.json`` (steps, wall time, evaluation).
    """
    work_dir = Path(work_dir)
    launched = time.perf_counter()
    schedule = curriculum_schedule(config.plant, config.curriculum, config.total_steps)
    first = plant_at_speed(config.plant, schedule[0][1]) if schedule else config.plant
    env = _shaped(config, SpeedSwitch(first))
    state = load_state(work_dir) if resume else None
    model = resume_sac(work_dir, env) if state is not None else None
    if model is None:
        model, state = _start(config, env, first, work_dir)
    assert state is not None
    state.total_steps = config.total_steps
    scale_actor_learning_rate(model, config.actor_lr_scale)
    if "setup_wall_time_s" not in state.extra:  # demonstrations, cloning, critic warm-up
        state.extra["setup_wall_time_s"] = round(time.perf_counter() - launched, 1)
    started = time.perf_counter()
    _learn(config, model, state, work_dir=work_dir, schedule=schedule, progress=progress)
    model = _shipped(config, model, work_dir)
    final = evaluate_ideal(
        config.plant,
        SacController(model),
        seeds=stage_seeds(config.seed + 3, config.final_eval_episodes),
    )
    state.extra["session_wall_time_s"] = round(time.perf_counter() - started, 1)
    write_output(
        out_dir,
        model=model,
        state=state,
        config=config,
        command=command,
        seed=config.seed,
        final=final,
        notes=_NOTES,
    )
    env.close()
    total = round(time.perf_counter() - launched, 1)  # setup, SAC, final evaluation: all of it
    return {
        "env_steps": state.steps_done,
        "wall_time_s": state.wall_time_s,
        "total_wall_time_s": total,
        **final,
    }


def _shaped(config: StageAConfig, env: gym.Env) -> gym.Env:
    """``env`` with the distance shaping and the early-grip penalty (when either is on)."""
    if not (config.shaping_weight or config.grip_penalty):
        return env
    return Shaping(
        env, config.shaping_weight, config.sac.gamma, config.grip_penalty, config.grip_radius_m
    )


def _evaluate(config: StageAConfig, model: Any) -> dict[str, float]:
    """The evaluation ``keep_best`` selects on: the ``dev`` seeds (:func:`selection_seeds`)."""
    return evaluate_ideal(
        config.plant, SacController(model), seeds=selection_seeds(config.eval_episodes)
    )


def _start(
    config: StageAConfig, env: gym.Env, first: PlantSpec, work_dir: Path
) -> tuple[Any, TrainingState]:
    """A new SAC and its state; with demonstrations, warm-started from them."""
    state = TrainingState(stage="a", total_steps=config.total_steps)
    (work_dir / "best_model.zip").unlink(missing_ok=True)
    model = make_sac(env, config.sac, seed=config.seed)
    if config.demo_episodes:
        _warm_start(config, model, state, first, work_dir)
    return model, state


def _warm_start(
    config: StageAConfig, model: Any, state: TrainingState, first: PlantSpec, work_dir: Path
) -> None:
    """Demonstrations into the replay buffer, behaviour cloning, critic warm-up, evaluation.

    The evaluation before online learning is the curve's step 0 and the first best model.
    """
    assert config.demo is not None  # StageAConfig checks it
    demo_env = _shaped(config, make_plant(first))
    demo = build("controller", config.demo, demo_env)
    stats, (demo_obs, demo_actions) = add_demonstrations(
        model,
        demo_env,
        demo,
        episodes=config.demo_episodes,
        noise_std=config.demo_noise_std,
        seed=config.seed + 1,
        random_prob=config.demo_random_prob,
    )
    if config.bc_epochs:
        stats["bc_loss"] = clone_behaviour(
            model,
            demo_obs,
            demo_actions,
            epochs=config.bc_epochs,
            action_std=config.bc_action_std,
            seed=config.seed + 4,
        )
    warm_up_critic(model, config.critic_warmup_steps)
    stats["critic_warmup_steps"] = config.critic_warmup_steps
    state.extra["demonstrations"] = stats
    if config.eval_episodes:
        start = {"steps": 0, **_evaluate(config, model)}
        state.curve.append(start)
        state.extra["best"] = {"steps": 0, "success_rate": start["success_rate"]}
        work_dir.mkdir(parents=True, exist_ok=True)
        model.save(work_dir / "best_model.zip", exclude=["_update_learning_rate"])


def _learn(
    config: StageAConfig,
    model: Any,
    state: TrainingState,
    *,
    work_dir: Path,
    schedule: list[tuple[int, float]],
    progress: Progress,
) -> None:
    """SAC in chunks with the curriculum and the actor freeze, keeping the best evaluation."""
    callbacks: list[BaseCallback] = []
    if schedule:
        callbacks.append(Curriculum(schedule))
    if config.actor_freeze_steps:
        callbacks.append(FreezeActor(config.actor_freeze_steps))
    train_sac_in_chunks(
        model,
        state,
        work_dir=work_dir,
        chunk_steps=config.chunk_steps,
        evaluate=(lambda m: _evaluate(config, m)) if config.eval_episodes else None,
        callback=CallbackList(callbacks) if callbacks else None,
        progress=progress,
        description="stage A (SAC, ideal control)",
        keep_best="success_rate" if config.eval_episodes else None,
    )


def _shipped(config: StageAConfig, model: Any, work_dir: Path) -> Any:
    """The model to ship: the best evaluated one when evaluations ran, else ``model``."""
    best_path = work_dir / "best_model.zip"
    if config.eval_episodes and best_path.is_file():
        return SAC.load(best_path, device="cpu")
    return model
