"""Stage A, the ideal control policy (``eq_control_ideal``): SB3 SAC from demonstrations.

The actor acts on the plant behind a perfect link (``q = 1``, ``tau = 0``: the tables'
``oracle``) seen through the stack's estimator (default ``predictor``: the ``realistic``
scenario's packet carries the perceived position only, the estimator adds the velocity), with
the plant's dense reward plus shaping. SAC is SB3's, with what works for manipulation from a
few demonstrations (:mod:`~codesign_mb.stages.sac_from_demos`; no RL algorithm is written here):

* demonstrations of the scripted pick (with action noise) in their own SB3 buffer, half of
  every SAC batch drawn from it (RLPD); LayerNorm critics; ``sac.gradient_steps`` updates per
  env step (update-to-data ratio);
* the actor starts from the behaviour clone of the demonstrations, kept as ``bc.zip``
  (controller kind ``bc``) and evaluated next to the SAC actor, and its loss has a decaying,
  Q-normalised behaviour-cloning term (TD3+BC);
* potential-based distance shaping and an early-grip penalty; a curriculum over belt speeds
  (the top of the per-episode speed range raised in steps to the plant's own).

Why the earlier SAC fine-tuning of the clone collapsed (``models/checkpoints/README.md``,
measured on the ``paper`` plant with the old settings; ``state.json``'s curve keeps the
entropy coefficient and SB3's losses per chunk): the clone is near-deterministic (its
log-probability on the demonstrations +6.9 nats, the entropy target -4), so SB3's automatic
entropy coefficient only grows (0.025 -> 0.075 in 4 000 steps) and its gradient, through the
tanh correction of the log-probability, pulls the saturated grip command towards 0; and the
critic, pre-trained on demonstrations that never close the gripper far from the object, rates
"close now" above the demonstrated action (Q 25.3 vs 24.4 before any actor update), so every
actor step, however small its learning rate, pushes the grip the same wrong way (Adam's step
size does not depend on the gradient's scale). Hence here: an entropy target below the
clone's (``target_entropy``) and a small initial coefficient, LayerNorm critics, demonstrations
in every batch and the BC term keeping the actor on the demonstrated grip.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer

from codesign_mb.control.sac import SacController
from codesign_mb.core.config import EPISODES_CAP, SEED_CAP, TRAINING_STEPS_CAP, check_range
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build
from codesign_mb.stages.demonstrations import add_demonstrations, clone_behaviour, warm_up_critic
from codesign_mb.stages.sac_from_demos import (
    ActorWarmup,
    BehaviourCloningTerm,
    make_sac_from_demos,
)
from codesign_mb.stages.stage import StageRun
from codesign_mb.stages.stage_a_aids import (
    Curriculum,
    EstimatedStateEnv,
    Shaping,
    curriculum_schedule,
    evaluate_ideal,
    speed_at,
)
from codesign_mb.stages.training import (
    EPOCHS_CAP,
    Progress,
    SacSpec,
    TrainingState,
    load_state,
    require_at_least,
    resume_sac,
    selection_seeds,
    stage_seeds,
    train_sac_in_chunks,
    write_output,
)

__all__ = ["StageAConfig", "train_stage_a"]


@dataclass(frozen=True)
class StageAConfig:
    """Configuration of stage A.

    Parameters
    ----------
    plant:
        The plant (default: the ``paper`` scenario's conveyor, as stages B-D, so that the
        default commands train one pipeline; ``codesign train a --scenario realistic`` for
        the benchmark's).
    estimator:
        What the actor is given: the plant behind a perfect link (``q = 1``, ``tau = 0``, the
        tables' ``oracle``) seen through this estimator (default ``predictor``: on a plant
        that perceives no velocity it appends its velocity estimate, which a feedforward
        actor needs; ``none``: the plant's observation). The same stack is evaluated.
    sac:
        SAC hyper-parameters; ``gradient_steps`` is the update-to-data ratio.
    layer_norm_critics:
        LayerNorm after each hidden layer of the critics (:class:`LayerNormSacPolicy`).
    n_critics:
        Critics in SB3's ensemble; SAC's target and actor loss take their minimum (2: SB3's
        clipped double Q; more: more pessimistic about actions the data never took).
    target_entropy:
        SAC's entropy target (nats); ``None``: SB3's ``-dim(action)``.
    total_steps:
        Env steps of SAC experience (demonstrations not counted).
    chunk_steps:
        Steps between checkpoints / evaluations.
    seed:
        Root seed (SAC, env, demonstrations, final evaluation).
    eval_episodes:
        Deterministic evaluation episodes after each chunk, on the ``dev`` seed set (the
        same episodes whatever ``seed``; :func:`~codesign_mb.stages.training.selection_seeds`).
        The shipped actor is the best of them (ties: the later), never the clone.
    demo:
        Demonstration controller (``None``: no demonstrations).
    demo_episodes:
        Episodes of ``demo`` in the demonstration buffer.
    demo_noise_std:
        Std of the Gaussian noise added to demonstration actions (in action units).
    demo_random_prob:
        Probability that a demonstration step takes a uniformly random action instead.
    demo_fraction:
        Share of every SAC batch drawn from the demonstrations (RLPD: 0.5).
    bc_epochs, bc_action_std:
        Behaviour-cloning epochs of the actor on the (noise-free) demonstrations before SAC,
        and the exploration std its log-std is fitted to. The clone is kept and evaluated
        (``bc.zip``, kind ``bc``); SAC starts from it. 0: SAC starts from scratch.
    bc_weight, bc_decay_steps:
        The behaviour-cloning term of the actor loss (:class:`BehaviourCloningTerm`): weight
        relative to the critic's scale, falling linearly to 0 over ``bc_decay_steps`` env
        steps. 0: off.
    critic_warmup_steps:
        SAC gradient steps on the demonstrations with the actor frozen, before learning.
    actor_freeze_steps, actor_ramp_steps:
        Env steps of SAC's own experience with the actor's learning rate at 0 (the critic
        learns the clone's rollouts), then steps over which it rises linearly to
        ``sac.learning_rate`` (:class:`ActorWarmup`). 0, 0: the actor learns from the start.
    curriculum:
        Top belt speeds (m/s) of SAC's own episodes before the plant's own, each for an
        equal share of ``total_steps`` (:func:`~codesign_mb.stages.stage_a_aids.plant_at_speed`);
        the demonstrations cover the plant's own speeds.
    shaping_weight:
        Potential-based shaping (Ng et al. 1999) added to the plant's reward,
        ``w (d_t - gamma d_{t+1})`` with ``d`` the gripper-object distance in m. 0: off.
    grip_penalty, grip_radius_m:
        Reward ``-grip_penalty`` for every step the gripper is commanded closed while the
        object is farther than ``grip_radius_m`` from it. 0: off.
    final_eval_episodes:
        Episodes of the final evaluation of the shipped actor and of the clone.
    """

    plant: PlantSpec = field(default_factory=PlantSpec)
    estimator: ComponentSpec = field(default_factory=lambda: ComponentSpec("predictor"))
    sac: SacSpec = field(
        default_factory=lambda: SacSpec(
            gamma=0.97,
            tau=0.005,
            ent_coef="auto_0.01",
            learning_rate=1e-4,
            learning_starts=0,
            gradient_steps=1,
        )
    )
    layer_norm_critics: bool = True
    n_critics: int = 2
    target_entropy: float | None = -8.0
    total_steps: int = 20_000
    chunk_steps: int = 5_000
    seed: int = 0
    eval_episodes: int = 50
    demo: ComponentSpec | None = field(default_factory=lambda: ComponentSpec("scripted"))
    demo_episodes: int = 200
    demo_noise_std: float = 0.1
    demo_random_prob: float = 0.0
    demo_fraction: float = 0.5
    bc_epochs: int = 50
    bc_action_std: float = 0.2
    bc_weight: float = 10.0
    bc_decay_steps: int = 100_000
    critic_warmup_steps: int = 2_000
    actor_freeze_steps: int = 0
    actor_ramp_steps: int = 0
    curriculum: tuple[float, ...] = (0.35,)
    shaping_weight: float = 5.0
    grip_penalty: float = 1.0
    grip_radius_m: float = 0.04
    final_eval_episodes: int = 200

    def __post_init__(self) -> None:
        require_at_least(self, 1, "total_steps", "chunk_steps", cap=TRAINING_STEPS_CAP)
        require_at_least(self, 0, "eval_episodes", "demo_episodes", cap=EPISODES_CAP)
        check_range("seed", self.seed, ge=0, cap=SEED_CAP)
        check_range("n_critics", self.n_critics, ge=1, le=16)
        require_at_least(
            self,
            0,
            "critic_warmup_steps",
            "actor_freeze_steps",
            "actor_ramp_steps",
            cap=TRAINING_STEPS_CAP,
        )
        require_at_least(self, 1, "bc_decay_steps", cap=TRAINING_STEPS_CAP)
        require_at_least(self, 0, "bc_epochs", cap=EPOCHS_CAP)
        require_at_least(self, 0, "demo_noise_std", "bc_weight", "shaping_weight")
        if self.demo_episodes and self.demo is None:
            raise ValueError("demo_episodes > 0 needs a demo controller (demo.kind)")
        for name in ("demo_random_prob", "demo_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if any(v < 0 for v in self.curriculum):
            raise ValueError(f"curriculum belt speeds must be >= 0, got {self.curriculum}")
        if self.grip_penalty < 0 or self.grip_radius_m <= 0:
            raise ValueError("grip_penalty must be >= 0 and grip_radius_m > 0")
        if self.actor_freeze_steps >= self.total_steps:
            raise ValueError("actor_freeze_steps must be < total_steps (the actor must learn)")
        uses_demos = self.bc_epochs or self.critic_warmup_steps or self.bc_weight
        if uses_demos and not self.demo_episodes:
            raise ValueError("bc_epochs / bc_weight / critic_warmup_steps need demo_episodes > 0")
        require_at_least(self, 1, "final_eval_episodes", cap=EPISODES_CAP)
        if self.bc_action_std <= 0:
            raise ValueError(f"bc_action_std must be > 0, got {self.bc_action_std}")


_NOTES = (
    "SB3 SAC from demonstrations (RLPD-style): half of each batch from scripted "
    "demonstrations, LayerNorm critics, update-to-data ratio sac.gradient_steps, a decaying "
    "Q-normalised behaviour-cloning term in the actor loss, potential-based distance shaping "
    "+ early-grip penalty, a curriculum over belt speeds; the actor acts on the estimator's "
    "output behind a perfect link (oracle). SAC starts from the behaviour clone of the "
    "demonstrations, kept as bc.zip (kind 'bc') with its own evaluation ('bc_*' in "
    "final_evaluation, curve step 0); the shipped model.zip is the best dev-set evaluation "
    "after SAC updates (never the clone; see 'best' and curve.json). wall_time_s counts the "
    "SAC chunks; setup_wall_time_s the demonstrations, cloning and critic warm-up."
)


def train_stage_a(
    config: StageAConfig,
    run: StageRun,
) -> dict[str, Any]:
    """Train the ideal SAC controller; write the checkpoint (and the clone) to ``out_dir``.

    Steps: build the (shaped, curriculum) training env; resume from ``work_dir`` or start a
    new SAC from demonstrations (buffer, clone, critic warm-up); train in chunks keeping the
    best evaluation; evaluate the shipped actor and the clone; write ``out_dir``. Returns the
    summary written to ``out_dir/training.json`` (steps, wall time, evaluation).
    """
    out_dir, work_dir = run.out_dir, run.work_dir
    resume, progress, command = run.resume, run.progress, run.command
    launched = time.perf_counter()
    schedule = curriculum_schedule(config.plant, config.curriculum, config.total_steps)
    env = _shaped(config, EstimatedStateEnv(config.plant, config.estimator))
    state = load_state(work_dir) if resume else None
    model = resume_sac(work_dir, env) if state is not None else None
    if model is None:  # demonstrations on the plant's own belt speeds, all of them
        model, state = _start(config, env, work_dir)
    if schedule:  # SAC's own episodes: where the curriculum is (resumed: where it was)
        env.get_wrapper_attr("set_top_speed")(speed_at(schedule, int(model.num_timesteps)))
    assert state is not None
    state.total_steps = config.total_steps
    bc_term = _bc_term(config, model, work_dir)
    warmup = (  # a hook on every actor step only when it changes the rate
        ActorWarmup(
            model, freeze_steps=config.actor_freeze_steps, ramp_steps=config.actor_ramp_steps
        )
        if config.actor_freeze_steps or config.actor_ramp_steps
        else None
    )
    if "setup_wall_time_s" not in state.extra:  # demonstrations, cloning, critic warm-up
        state.extra["setup_wall_time_s"] = round(time.perf_counter() - launched, 1)
    started = time.perf_counter()
    _learn(config, model, state, work_dir=work_dir, schedule=schedule, progress=progress)
    for hook in (bc_term, warmup):
        if hook is not None:
            hook.remove()
    model = _shipped(config, model, work_dir)
    final = _final_evaluation(config, model, work_dir)
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
    if (work_dir / "bc.zip").is_file():
        shutil.copyfile(work_dir / "bc.zip", Path(out_dir) / "bc.zip")
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
        config.plant,
        SacController(model),
        seeds=selection_seeds(config.eval_episodes),
        estimator=config.estimator,
    )


def _final_evaluation(config: StageAConfig, model: Any, work_dir: Path) -> dict[str, float]:
    """The shipped actor's and the clone's (``bc_*``) success and return on other seeds."""
    seeds = stage_seeds(config.seed + 3, config.final_eval_episodes)
    final = evaluate_ideal(
        config.plant, SacController(model), seeds=seeds, estimator=config.estimator
    )
    clone = work_dir / "bc.zip"
    if clone.is_file():
        bc = evaluate_ideal(
            config.plant, SacController.load(clone), seeds=seeds, estimator=config.estimator
        )
        final.update({f"bc_{k}": v for k, v in bc.items()})
    return final


def _start(config: StageAConfig, env: gym.Env, work_dir: Path) -> tuple[Any, TrainingState]:
    """A new SAC and its state; with demonstrations, warm-started from them."""
    state = TrainingState(stage="a", total_steps=config.total_steps)
    for name in ("best_model.zip", "bc.zip", "demonstrations.npz"):
        (work_dir / name).unlink(missing_ok=True)
    model = make_sac_from_demos(
        env,
        config.sac,
        seed=config.seed,
        demo_fraction=config.demo_fraction if config.demo_episodes else 0.0,
        layer_norm_critics=config.layer_norm_critics,
        n_critics=config.n_critics,
        target_entropy=config.target_entropy,
    )
    if config.demo_episodes:
        _warm_start(config, model, state, env, work_dir)
    return model, state


def _warm_start(
    config: StageAConfig, model: Any, state: TrainingState, env: gym.Env, work_dir: Path
) -> None:
    """Demonstration buffer, behaviour cloning (kept as ``bc.zip``), critic warm-up.

    The clone's evaluation is the curve's step 0; it is never the shipped model.
    """
    assert config.demo is not None  # StageAConfig checks it
    demo_buffer = ReplayBuffer(
        config.demo_episodes * _horizon(env) + 1,
        model.observation_space,
        model.action_space,
        device="cpu",
    )
    demo = build("controller", config.demo, env.unwrapped.plant)
    stats, (demo_obs, demo_actions) = add_demonstrations(
        demo_buffer,
        env,
        demo,
        episodes=config.demo_episodes,
        noise_std=config.demo_noise_std,
        seed=config.seed + 1,
        random_prob=config.demo_random_prob,
    )
    model.replay_buffer.set_demonstrations(demo_buffer)
    work_dir.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(work_dir / "demonstrations.npz", obs=demo_obs, actions=demo_actions)
    if config.bc_epochs:
        stats["bc_loss"] = clone_behaviour(
            model,
            demo_obs,
            demo_actions,
            epochs=config.bc_epochs,
            action_std=config.bc_action_std,
            seed=config.seed + 4,
        )
        model.save(work_dir / "bc.zip", exclude=["replay_buffer"])
        if config.eval_episodes:
            state.curve.append({"steps": 0, "actor": "bc", **_evaluate(config, model)})
    warm_up_critic(model, config.critic_warmup_steps)
    stats["critic_warmup_steps"] = config.critic_warmup_steps
    state.extra["demonstrations"] = stats


def _horizon(env: gym.Env) -> int:
    return int(getattr(env.unwrapped.plant, "horizon", 100))


def _bc_term(config: StageAConfig, model: Any, work_dir: Path) -> BehaviourCloningTerm | None:
    """The actor loss's decaying BC term on the saved demonstrations (also on resume)."""
    path = work_dir / "demonstrations.npz"
    if not config.bc_weight or not path.is_file():
        return None
    with np.load(path) as data:
        obs, actions = data["obs"], data["actions"]
    return BehaviourCloningTerm(
        model,
        obs,
        actions,
        weight=config.bc_weight,
        decay_steps=config.bc_decay_steps,
        batch_size=config.sac.batch_size,
        seed=config.seed + 5,
    )


def _learn(
    config: StageAConfig,
    model: Any,
    state: TrainingState,
    *,
    work_dir: Path,
    schedule: list[tuple[int, float]],
    progress: Progress,
) -> None:
    """SAC in chunks with the curriculum, keeping the best evaluation."""
    train_sac_in_chunks(
        model,
        state,
        work_dir=work_dir,
        chunk_steps=config.chunk_steps,
        evaluate=(lambda m: _evaluate(config, m)) if config.eval_episodes else None,
        on_chunk=lambda m, s: _diagnostics(m, config.actor_freeze_steps),
        callback=Curriculum(schedule) if schedule else None,
        progress=progress,
        description="stage A (SAC, ideal control)",
        keep_best=_sac_score if config.eval_episodes else None,
    )


def _sac_score(point: Mapping[str, Any]) -> float | None:
    """``keep_best``'s score: the dev success of a SAC-updated actor; ``None`` for the clone.

    While :class:`ActorWarmup` holds the actor at learning rate 0 its evaluations are the
    clone's; they are on the curve but may never be shipped as ``model.zip``.
    """
    return float(point["success_rate"]) if point.get("actor") == "sac" else None


def _diagnostics(model: Any, freeze_steps: int) -> dict[str, Any]:
    """What the collapse diagnosis watches: entropy coefficient, SB3's last losses.

    ``actor`` is ``sac`` once SAC has updated the actor, ``bc (frozen)`` before.
    """
    values = getattr(model.logger, "name_to_value", {})
    out = {
        key.split("/")[-1]: float(values[key])
        for key in ("train/ent_coef", "train/actor_loss", "train/critic_loss")
        if key in values
    }
    updated = int(model.num_timesteps) > freeze_steps
    return {**out, "actor": "sac" if updated else "bc (frozen)"}


def _shipped(config: StageAConfig, model: Any, work_dir: Path) -> Any:
    """The model to ship: the best evaluated one when evaluations ran, else ``model``."""
    best_path = work_dir / "best_model.zip"
    if config.eval_episodes and best_path.is_file():
        return SAC.load(best_path, device="cpu")
    return model
