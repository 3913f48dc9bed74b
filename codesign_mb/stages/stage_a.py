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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, CallbackList

from codesign_mb.control.sac import SacController
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.stages.training import (
    Progress,
    SacSpec,
    TrainingState,
    episode_success,
    load_state,
    make_sac,
    no_progress,
    resume_sac,
    train_sac_in_chunks,
    write_output,
)

__all__ = ["StageAConfig", "add_demonstrations", "evaluate_ideal", "train_stage_a"]


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
        if self.total_steps < 1:
            raise ValueError(f"total_steps must be >= 1, got {self.total_steps}")
        if self.chunk_steps < 1:
            raise ValueError(f"chunk_steps must be >= 1, got {self.chunk_steps}")
        if self.eval_episodes < 0:
            raise ValueError(f"eval_episodes must be >= 0, got {self.eval_episodes}")
        if self.demo_episodes < 0:
            raise ValueError(f"demo_episodes must be >= 0, got {self.demo_episodes}")
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
        if self.final_eval_episodes < 1:
            raise ValueError(f"final_eval_episodes must be >= 1, got {self.final_eval_episodes}")
        if self.bc_action_std <= 0:
            raise ValueError(f"bc_action_std must be > 0, got {self.bc_action_std}")


def evaluate_ideal(
    plant: PlantSpec, controller: Any, *, episodes: int, seed: int
) -> dict[str, float]:
    """Success rate and mean return of ``controller`` on the perfect state (no link)."""
    env = make_plant(plant)
    seeds = np.random.SeedSequence(seed).generate_state(max(episodes, 1))
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
        successes.append(episode_success(infos))
        returns.append(total)
    env.close()
    if not episodes:
        return {}
    return {"success_rate": float(np.mean(successes)), "mean_return": float(np.mean(returns))}


def add_demonstrations(
    model: Any,
    env: gym.Env,
    controller: Any,
    *,
    episodes: int,
    noise_std: float,
    seed: int,
    random_prob: float = 0.0,
) -> tuple[dict[str, float], tuple[np.ndarray, np.ndarray]]:
    """Put ``episodes`` of ``controller`` (with action noise) into ``model``'s replay buffer.

    Transitions are stored as SB3 stores its own (a time-limit end is a truncation, not a
    terminal state); with probability ``random_prob`` a step's action is uniformly random.
    Returns the demonstrations' success rate and number of transitions, and the noise-free
    ``(observations, actions)`` of the demonstrator (for behaviour cloning).
    """
    rng = np.random.default_rng(seed)
    seeds = np.random.SeedSequence(seed).generate_state(max(episodes, 1))
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
        successes.append(episode_success(infos))
    stats = {"demo_success_rate": float(np.mean(successes)) if episodes else 0.0, "demo_steps": n}
    return stats, (np.asarray(clean_obs), np.asarray(clean_actions))


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


class _Curriculum(BaseCallback):
    """Switch the training env's belt speed at fixed step counts (applied at the next reset)."""

    def __init__(self, schedule: list[tuple[int, float]]) -> None:
        super().__init__()
        self.schedule = schedule

    def _on_step(self) -> bool:
        self.training_env.env_method("set_belt_speed", _speed_at(self.schedule, self.num_timesteps))
        return True


class _FreezeActor(BaseCallback):
    """Keep SAC's actor frozen (critic-only updates) until ``until`` env steps."""

    def __init__(self, until: int) -> None:
        super().__init__()
        self.until = int(until)
        self._frozen: bool | None = None

    def _set(self, frozen: bool) -> None:
        if frozen != self._frozen:
            for p in self.model.actor.parameters():
                p.requires_grad_(not frozen)
            self._frozen = frozen

    def _on_training_start(self) -> None:
        self._set(self.num_timesteps < self.until)

    def _on_step(self) -> bool:
        self._set(self.num_timesteps < self.until)
        return True

    def _on_training_end(self) -> None:
        self._set(False)


def scale_actor_learning_rate(model: Any, scale: float) -> None:
    """Make SB3's per-update learning-rate setting give the actor ``scale`` times the rate."""
    import types

    from stable_baselines3.common.utils import update_learning_rate

    if scale == 1.0:
        return
    base = model._update_learning_rate

    def _update(self: Any, optimizers: Any) -> None:
        base(optimizers)
        rate = self.lr_schedule(self._current_progress_remaining) * scale
        update_learning_rate(self.actor.optimizer, rate)

    model._update_learning_rate = types.MethodType(_update, model)


def _speed_at(schedule: list[tuple[int, float]], steps: int) -> float:
    speed = schedule[0][1]
    for start, value in schedule:
        if steps >= start:
            speed = value
    return speed


def _plant_at_speed(plant: PlantSpec, speed: float) -> PlantSpec:
    return replace(plant, options={**plant.options, "belt_speed_mps": float(speed)})


class _SpeedSwitch(gym.Wrapper):
    """Rebuild the plant with another belt speed at the next reset (for the curriculum)."""

    def __init__(self, plant: PlantSpec) -> None:
        super().__init__(make_plant(plant))
        self._plant = plant
        self._speed = plant.options.get("belt_speed_mps")
        self._pending: float | None = None

    def set_belt_speed(self, speed: float) -> None:
        if speed != self._speed:
            self._pending = speed

    def reset(self, **kwargs: Any) -> Any:
        if self._pending is not None:
            self.env.close()
            self.env = make_plant(_plant_at_speed(self._plant, self._pending))
            self._speed, self._pending = self._pending, None
        return self.env.reset(**kwargs)


class _Shaping(gym.Wrapper):
    """Add ``w (d_t - gamma d_{t+1})`` (potential ``-w d``; ``d`` from ``info``) to the reward,
    and ``-grip_penalty`` when the grip closes farther than ``grip_radius_m`` from the object."""

    def __init__(
        self,
        env: gym.Env,
        weight: float,
        gamma: float,
        grip_penalty: float = 0.0,
        grip_radius_m: float = 0.04,
    ) -> None:
        super().__init__(env)
        self.weight, self.gamma = float(weight), float(gamma)
        self.grip_penalty, self.grip_radius_m = float(grip_penalty), float(grip_radius_m)
        self._distance = 0.0

    def reset(self, **kwargs: Any) -> Any:
        obs, info = self.env.reset(**kwargs)
        self._distance = float(info["gripper_object_distance"])
        return obs, info

    def step(self, action: Any) -> Any:
        closing_far = float(np.asarray(action)[-1]) > 0 and self._distance > self.grip_radius_m
        obs, reward, terminated, truncated, info = self.env.step(action)
        distance = float(info["gripper_object_distance"])
        bonus = self.weight * (self._distance - (0.0 if terminated else self.gamma) * distance)
        bonus -= self.grip_penalty * closing_far
        self._distance = distance
        return obs, float(reward) + bonus, terminated, truncated, info


def train_stage_a(
    config: StageAConfig,
    *,
    out_dir: str | Path,
    work_dir: str | Path,
    resume: bool = False,
    progress: Progress = no_progress,
    command: str | None = None,
) -> dict[str, Any]:
    """Train the ideal SAC controller; write the shipped checkpoint to ``out_dir``.

    Returns the summary written to ``out_dir/training.json`` (steps, wall time, evaluation).
    """

    work_dir = Path(work_dir)
    launched = time.perf_counter()
    final_speed = config.plant.options.get("belt_speed_mps")
    schedule: list[tuple[int, float]] = []
    if config.curriculum:
        if final_speed is None:
            raise ValueError("a curriculum needs plant.options.belt_speed_mps (the final speed)")
        speeds = [*config.curriculum, float(final_speed)]
        share = config.total_steps // len(speeds)
        schedule = [(i * share, s) for i, s in enumerate(speeds)]
    first = _plant_at_speed(config.plant, schedule[0][1]) if schedule else config.plant

    def shaped(env: gym.Env) -> gym.Env:
        if not (config.shaping_weight or config.grip_penalty):
            return env
        return _Shaping(
            env, config.shaping_weight, config.sac.gamma, config.grip_penalty, config.grip_radius_m
        )

    env = shaped(_SpeedSwitch(first))

    state = load_state(work_dir) if resume else None
    model = resume_sac(work_dir, env) if state is not None else None
    if model is None:
        state = TrainingState(stage="a", total_steps=config.total_steps)
        (work_dir / "best_model.zip").unlink(missing_ok=True)
        model = make_sac(env, config.sac, seed=config.seed)
        if config.demo_episodes:
            demo_env = shaped(make_plant(first))
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
                start = {
                    "steps": 0,
                    **evaluate_ideal(
                        config.plant,
                        SacController(model),
                        episodes=config.eval_episodes,
                        seed=config.seed + 2,
                    ),
                }
                state.curve.append(start)
                state.extra["best"] = {"steps": 0, "success_rate": start["success_rate"]}
                work_dir.mkdir(parents=True, exist_ok=True)
                model.save(work_dir / "best_model.zip", exclude=["_update_learning_rate"])
    assert state is not None
    state.total_steps = config.total_steps
    scale_actor_learning_rate(model, config.actor_lr_scale)

    def evaluate(m: Any) -> dict[str, float]:
        return evaluate_ideal(
            config.plant,
            SacController(m),
            episodes=config.eval_episodes,
            seed=config.seed + 2,
        )

    callbacks: list[BaseCallback] = []
    if schedule:
        callbacks.append(_Curriculum(schedule))
    if config.actor_freeze_steps:
        callbacks.append(_FreezeActor(config.actor_freeze_steps))
    callback = CallbackList(callbacks) if callbacks else None
    if "setup_wall_time_s" not in state.extra:  # demonstrations, cloning, critic warm-up
        state.extra["setup_wall_time_s"] = round(time.perf_counter() - launched, 1)
    started = time.perf_counter()
    train_sac_in_chunks(
        model,
        state,
        work_dir=work_dir,
        chunk_steps=config.chunk_steps,
        evaluate=evaluate if config.eval_episodes else None,
        callback=callback,
        progress=progress,
        description="stage A (SAC, ideal control)",
        keep_best="success_rate" if config.eval_episodes else None,
    )
    best_path = work_dir / "best_model.zip"
    if config.eval_episodes and best_path.is_file():
        from stable_baselines3 import SAC

        model = SAC.load(best_path, device="cpu")
    final = evaluate_ideal(
        config.plant,
        SacController(model),
        episodes=config.final_eval_episodes,
        seed=config.seed + 3,
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
        notes=(
            "SB3 SAC on the perfect state (no HER): plant reward + potential-based distance "
            "shaping + early-grip penalty; actor initialised by behaviour cloning of the "
            "demonstrations, critic pre-trained with SB3 SAC updates (actor frozen), then SAC; "
            "the shipped model is the best evaluation (see 'best' and curve.json). "
            "wall_time_s counts the SAC chunks; setup_wall_time_s the rest."
        ),
    )
    env.close()
    return {"env_steps": state.steps_done, "wall_time_s": state.wall_time_s, **final}
