"""Stage C, control-aware QoS adaptation (``eq_q_t_pol2``): SAC learns ``q_t = pi_q(y, zeta)``.

:class:`QosAdaptationEnv` turns "the plant behind a link, run by a fixed controller and
estimator" into a Gymnasium env whose agent is the QoS policy. One agent step is one packet:

* observation: ``(y_{t-1}, zeta_{t-1})`` as the link held it (``eq_q_pol``), plus optional
  extra features (:class:`~codesign_mb.adaptation.learned.QosFeatures`);
* action: the reliability ``q_t`` (and, optionally, the latency; fixed at one step by
  default, like the paper);
* the packet ``x_t`` is sent with it, the robot runs ``u_t = controller(estimator(y_t,
  zeta_t))`` (``eq_c_pol2``) and the plant steps;
* reward ``-(C(q_t) + lambda (L(x_t) - J_max / T))`` (``eq_q_t_pol2``);
* the plant's horizon ``T`` *terminates* the agent's episode (``terminal_horizon``): ``J``
  is scored at ``T`` and nothing follows, so the critic must not bootstrap past it as it
  would after a time limit (the failure loss is paid exactly on that step).

The controller/estimator pair is any :class:`~codesign_mb.control.Controller` and
:class:`~codesign_mb.estimation.Estimator`, given by configuration
(:class:`~codesign_mb.core.registry.ComponentSpec`): the learned stack (SAC + MLP), the
model-based one (MPC + predictor) or a mix reuse this trainer unchanged.

The task loss ``L`` (``StageCConfig.env.loss``) is one of

* ``"failure"``: ``1`` at the last step of an episode that never succeeded, else ``0``; the
  constraint ``E[sum_t L] <= J_max`` then bounds the failure rate by ``J_max``;
* ``"distance"``: the gripper-object distance in m at every step (a dense proxy);
* ``"estimation_error"``: the error of the estimator's remote estimate (norm) at every step.

``lambda`` is either fixed or updated by dual ascent on the measured constraint
(:class:`DualAscentCallback`): every ``every_episodes`` finished episodes,
``lambda <- clip(lambda + eta (mean J_episode - J_max), lambda_min, lambda_max)``. The
replay buffer keeps rewards computed with older multipliers (SB3's SAC has one critic); the
multiplier moves slowly compared with the buffer's turnover, which is the usual compromise.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray
from stable_baselines3.common.callbacks import BaseCallback

from codesign_mb.adaptation.learned import (
    LearnedQosPolicy,
    QosFeatures,
    QosInterface,
    make_features,
)
from codesign_mb.core.registry import (
    ComponentSpec,
    PlantSpec,
    build,
    make_plant,
    resolve_checkpoint,
)
from codesign_mb.network.link import BernoulliLink, Link
from codesign_mb.network.qos import QosCost, QosRequest, reliability_cost
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.stages.training import (
    Progress,
    SacSpec,
    TrainingState,
    load_state,
    make_sac,
    no_progress,
    resume_sac,
    train_sac_in_chunks,
    write_output,
)

__all__ = [
    "LOSSES",
    "DualAscent",
    "DualAscentCallback",
    "QosAdaptationEnv",
    "QosEnvConfig",
    "StageCConfig",
    "evaluate_qos_agent",
    "feasible_score",
    "train_stage_c",
    "warm_start_multiplier",
]

LOSSES = ("failure", "distance", "estimation_error")


@dataclass(frozen=True)
class QosEnvConfig:
    """The QoS agent's problem (``eq_q_t_pol2``).

    Parameters
    ----------
    latency_steps:
        Fixed latency ``tau`` when not learned (the paper: 1).
    learn_latency, max_latency_steps:
        Learn ``tau`` in ``[0, max_latency_steps]`` too.
    min_reliability:
        Lowest reliability the agent may request.
    age_scale:
        The age enters the observation as ``zeta / age_scale``.
    loss:
        The task loss ``L`` (see the module docstring).
    j_max:
        ``J_max``: the bound on the expected episode sum of ``L`` (for ``"failure"``, the
        tolerated failure rate).
    lam:
        ``lambda``: fixed, or the initial value under dual ascent.
    terminal_horizon:
        The plant's horizon ends the agent's episode as a termination (``J`` is scored at
        ``T``; the critic does not bootstrap past it); ``False`` reports it as a time limit
        (truncation), as the trainer did before (``checkpoints/stage_c_mpc`` was trained so).
    """

    latency_steps: int = 1
    learn_latency: bool = False
    max_latency_steps: int = 4
    min_reliability: float = 0.0
    age_scale: float = 10.0
    loss: str = "failure"
    j_max: float = 0.02
    lam: float = 50.0
    terminal_horizon: bool = True

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        if self.j_max < 0:
            raise ValueError(f"j_max must be >= 0, got {self.j_max}")
        if self.lam < 0:
            raise ValueError(f"lam must be >= 0, got {self.lam}")
        QosInterface(  # validates the shared fields
            remote_dim=1,
            latency_steps=self.latency_steps,
            learn_latency=self.learn_latency,
            max_latency_steps=self.max_latency_steps,
            min_reliability=self.min_reliability,
            age_scale=self.age_scale,
        )


class _ActionQos:
    """The wrapper's QoS policy inside :class:`QosAdaptationEnv`: whatever the agent chose."""

    def __init__(self) -> None:
        self.next = QosRequest(1.0, 0)

    def reset(self, *, seed: int | None = None) -> None:
        return None

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        return self.next


class QosAdaptationEnv(gym.Env):
    """The QoS policy's MDP (``eq_q_t_pol2``) around a fixed controller and estimator.

    Parameters
    ----------
    env_factory:
        Builds the plant env (a :class:`~codesign_mb.network.NetworkedPlant` with a
        ``horizon``); called once.
    estimator, controller:
        The robot side (``eq_c_pol2``); any implementations of the protocols.
    config:
        :class:`QosEnvConfig`.
    features:
        Extra observation features, or ``None``.
    link:
        The link (default :class:`~codesign_mb.network.BernoulliLink`).
    qos_cost:
        ``C(q, tau)`` (default ``C(q) = q``, ``eq_robot``).

    ``info`` of the last step of an episode holds ``"qos_episode"``: the episode's
    ``success``, ``constraint`` (sum of ``L``), ``mean_reliability`` and ``steps``.
    """

    metadata = {"render_modes": []}  # noqa: RUF012

    def __init__(
        self,
        env_factory: Callable[[], gym.Env],
        estimator: Any,
        controller: Any,
        *,
        config: QosEnvConfig | None = None,
        features: QosFeatures | None = None,
        link: Link | None = None,
        qos_cost: QosCost = reliability_cost,
    ) -> None:
        self.config = config or QosEnvConfig()
        plant = env_factory()
        self._qos = _ActionQos()
        self.wrapped = LinkObservationWrapper(plant, link or BernoulliLink(), self._qos, qos_cost)
        self.estimator = estimator
        self.controller = controller
        self.features = features
        unwrapped = plant.unwrapped
        horizon = getattr(unwrapped, "horizon", None)
        if horizon is None:
            raise ValueError("QosAdaptationEnv needs a plant with a horizon (J_max / T)")
        self.horizon = int(horizon)
        self._prior = np.asarray(unwrapped.remote_prior(), dtype=float)
        c = self.config
        self.interface = QosInterface(
            remote_dim=int(self._prior.size),
            feature_dim=0 if features is None else int(features.dim),
            latency_steps=c.latency_steps,
            learn_latency=c.learn_latency,
            max_latency_steps=c.max_latency_steps,
            min_reliability=c.min_reliability,
            age_scale=c.age_scale,
        )
        self.observation_space = gym.spaces.Box(
            -np.inf, np.inf, shape=(self.interface.observation_dim,), dtype=np.float32
        )
        self.action_space = gym.spaces.Box(
            -1.0, 1.0, shape=(self.interface.action_dim,), dtype=np.float32
        )
        self.lam = float(c.lam)
        self._started = False
        self._done = True
        self._estimate: NDArray[np.float64] | None = None
        self._episode_seed = 0
        self._stats: dict[str, float] = {}

    def set_lambda(self, lam: float) -> None:
        """Set the multiplier ``lambda`` (dual ascent does this between episodes)."""
        if lam < 0:
            raise ValueError(f"lambda must be >= 0, got {lam}")
        self.lam = float(lam)

    def _observe(self, held: NDArray[np.float64], age: int) -> NDArray[np.float32]:
        extra = None if self.features is None else self.features(held, age)
        return self.interface.observation(held, age, extra)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        super().reset(seed=seed)
        self._episode_seed = int(self.np_random.integers(2**31 - 1)) if seed is None else seed
        self._started = False
        self._done = False
        self._stats = {"constraint": 0.0, "reliability": 0.0, "steps": 0, "success": False}
        if self.features is not None:
            self.features.reset()
        # The first request sees the prior, of age 0 (the wrapper's convention).
        return self._observe(self._prior, 0), {}

    def step(
        self, action: NDArray
    ) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        if self._done:
            raise RuntimeError("call reset() before step()")
        qos = self.interface.request(action)
        self._qos.next = qos  # eq_q_pol: the packet sent now gets the agent's QoS
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
        assert rx is not None
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
        if c.terminal_horizon:  # the horizon ends the finite-horizon problem (J is scored at T)
            return next_obs, reward, done, False, info
        return next_obs, reward, bool(terminated), bool(truncated), info

    def _loss(self, info: dict[str, Any], done: bool) -> float:
        kind = self.config.loss
        if kind == "failure":
            return float(done and not self._stats["success"])
        if kind == "distance":
            return float(info.get("gripper_object_distance", 0.0))
        estimate = np.asarray(self._estimate)[self.wrapped.remote_slice]
        return float(np.linalg.norm(estimate - np.asarray(info["remote_true"])))

    def close(self) -> None:
        self.wrapped.close()


class DualAscentCallback(BaseCallback):
    """Records finished episodes of :class:`QosAdaptationEnv`; optionally does dual ascent.

    Every ``every_episodes`` episodes: ``lambda <- clip(lambda + learning_rate (mean J -
    j_max), lam_min, lam_max)`` when ``enabled``; the multiplier and the window's mean
    constraint, success and reliability are logged (SB3 logger keys ``dual/*``) and kept in
    :attr:`history`.
    """

    def __init__(
        self,
        *,
        j_max: float,
        lam: float,
        enabled: bool = True,
        learning_rate: float = 50.0,
        every_episodes: int = 20,
        lam_min: float = 0.0,
        lam_max: float = 500.0,
    ) -> None:
        super().__init__()
        if every_episodes < 1:
            raise ValueError(f"every_episodes must be >= 1, got {every_episodes}")
        if not 0 <= lam_min <= lam_max:
            raise ValueError(f"need 0 <= lam_min <= lam_max, got {lam_min}, {lam_max}")
        self.j_max = float(j_max)
        self.lam = float(np.clip(lam, lam_min, lam_max))
        self.enabled = enabled
        self.learning_rate = float(learning_rate)
        self.every_episodes = int(every_episodes)
        self.lam_min, self.lam_max = float(lam_min), float(lam_max)
        self.window: list[dict[str, Any]] = []
        self.recent: deque[dict[str, Any]] = deque(maxlen=100)
        self.history: list[dict[str, float]] = []
        self.episodes = 0

    def _on_training_start(self) -> None:
        self.training_env.env_method("set_lambda", self.lam)

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", []):
            episode = info.get("qos_episode")
            if episode is None:
                continue
            self.episodes += 1
            self.window.append(episode)
            self.recent.append(episode)
            if len(self.window) >= self.every_episodes:
                self._update()
        return True

    def _update(self) -> None:
        constraint = float(np.mean([e["constraint"] for e in self.window]))
        if self.enabled:
            step = self.learning_rate * (constraint - self.j_max)
            self.lam = float(np.clip(self.lam + step, self.lam_min, self.lam_max))
            self.training_env.env_method("set_lambda", self.lam)
        point = {
            "steps": int(self.num_timesteps),
            "episodes": self.episodes,
            "lambda": self.lam,
            "constraint": constraint,
            "success_rate": float(np.mean([e["success"] for e in self.window])),
            "mean_reliability": float(np.mean([e["mean_reliability"] for e in self.window])),
        }
        self.history.append(point)
        for key in ("lambda", "constraint", "success_rate", "mean_reliability"):
            self.logger.record(f"dual/{key}", point[key])
        self.window = []

    def summary(self) -> dict[str, float]:
        """Mean success, reliability and constraint over the last 100 training episodes."""
        if not self.recent:
            return {"lambda": self.lam}
        return {
            "lambda": self.lam,
            "train_success_rate": float(np.mean([e["success"] for e in self.recent])),
            "train_mean_reliability": float(np.mean([e["mean_reliability"] for e in self.recent])),
            "train_constraint": float(np.mean([e["constraint"] for e in self.recent])),
        }


@dataclass(frozen=True)
class DualAscent:
    """Primal-dual update of ``lambda`` (off: ``lambda`` stays at ``env.lam``)."""

    enabled: bool = True
    learning_rate: float = 50.0
    every_episodes: int = 20
    lam_min: float = 0.0
    lam_max: float = 500.0

    def __post_init__(self) -> None:
        if self.every_episodes < 1:
            raise ValueError(f"dual.every_episodes must be >= 1, got {self.every_episodes}")
        if self.learning_rate < 0:
            raise ValueError(f"dual.learning_rate must be >= 0, got {self.learning_rate}")
        if not 0 <= self.lam_min <= self.lam_max:
            raise ValueError(
                f"need 0 <= dual.lam_min <= dual.lam_max, got {self.lam_min}, {self.lam_max}"
            )


@dataclass(frozen=True)
class StageCConfig:
    """Configuration of stage C (and of the QoS re-training in stage D).

    Parameters
    ----------
    plant:
        The plant.
    controller, estimator:
        The robot side the QoS policy is learned for (``eq_c_pol2``): the stage-A SAC and the
        stage-B MLP by default; ``estimator.kind = "none"`` learns the "no estimator" policy;
        ``mpc`` + ``predictor`` the model-based stack.
    features, feature_options:
        Extra observation features (a kind of
        :data:`~codesign_mb.adaptation.learned.QOS_FEATURES`), or ``None``.
    env:
        :class:`QosEnvConfig` (loss, ``J_max``, ``lambda``, latency).
    dual:
        :class:`DualAscent`.
    sac:
        SAC hyper-parameters of the QoS agent.
    total_steps, chunk_steps:
        Agent steps (= env steps = packets) and steps between checkpoints.
    eval_episodes:
        Deterministic evaluation episodes after each chunk.
    warm_start:
        A saved QoS policy folder to continue from (stage D), or ``None``.
    warm_start_lambda:
        With ``warm_start``, start the multiplier where the warm-start run ended (its
        ``training.json`` ``lambda``) instead of at ``env.lam``: the dual variable belongs
        with the policy it was trained with.
    keep_best, target_success:
        Ship the best evaluated policy instead of the last iterate (primal-dual iterates
        oscillate around the constraint): among the evaluations (after each chunk) whose
        success rate reaches ``target_success``, the one with the lowest mean requested
        reliability; if none does, the most successful (:func:`feasible_score`). The final
        evaluation in ``training.json`` is of the shipped policy, on other seeds.
    seed:
        Root seed.
    """

    plant: PlantSpec = field(default_factory=PlantSpec)
    controller: ComponentSpec = field(
        default_factory=lambda: ComponentSpec("sac", "checkpoints/stage_a/model.zip")
    )
    estimator: ComponentSpec = field(
        default_factory=lambda: ComponentSpec("mlp", "checkpoints/stage_b/mlp.pt")
    )
    features: str | None = None
    feature_options: dict[str, Any] = field(default_factory=dict)
    env: QosEnvConfig = field(default_factory=QosEnvConfig)
    dual: DualAscent = field(default_factory=DualAscent)
    sac: SacSpec = field(
        default_factory=lambda: SacSpec(gamma=0.99, buffer_size=100_000, net_arch=(64, 64))
    )
    total_steps: int = 40_000
    chunk_steps: int = 5_000
    eval_episodes: int = 20
    warm_start: str | None = None
    warm_start_lambda: bool = True
    keep_best: bool = True
    target_success: float = 0.95
    seed: int = 0

    def __post_init__(self) -> None:
        if self.total_steps < 1:
            raise ValueError(f"total_steps must be >= 1, got {self.total_steps}")
        if self.chunk_steps < 1:
            raise ValueError(f"chunk_steps must be >= 1, got {self.chunk_steps}")
        if self.eval_episodes < 0:
            raise ValueError(f"eval_episodes must be >= 0, got {self.eval_episodes}")
        if not 0.0 <= self.target_success <= 1.0:
            raise ValueError(f"target_success must be in [0, 1], got {self.target_success}")


def make_qos_env(config: StageCConfig, *, estimator_spec: ComponentSpec | None = None) -> Any:
    """The :class:`QosAdaptationEnv` of ``config`` with freshly built components."""
    probe = make_plant(config.plant)
    estimator = build("estimator", estimator_spec or config.estimator, probe)
    controller = build("controller", config.controller, probe)
    features = make_features(config.features, probe, config.feature_options)
    probe.close()
    return QosAdaptationEnv(
        lambda: make_plant(config.plant),
        estimator,
        controller,
        config=config.env,
        features=features,
    )


def feasible_score(point: dict[str, Any], target_success: float) -> float | None:
    """Score of an evaluation for :attr:`StageCConfig.keep_best` (higher is better).

    Feasible evaluations (``eval_success_rate >= target_success``) score ``2 - mean
    reliability`` (in [1, 2]), the others their success rate (in [0, 1)): any feasible
    policy beats every infeasible one, and the cheapest feasible one wins.
    """
    if "eval_success_rate" not in point:
        return None
    success = float(point["eval_success_rate"])
    if success >= target_success:
        return 2.0 - float(point["eval_mean_reliability"])
    return success


def evaluate_qos_agent(env: QosAdaptationEnv, model: Any, *, episodes: int, seed: int) -> dict:
    """Deterministic episodes of ``model`` in ``env``: success rate, mean reliability."""
    seeds = np.random.SeedSequence(seed).generate_state(max(episodes, 1))
    results = []
    for i in range(episodes):
        obs, _ = env.reset(seed=int(seeds[i]))
        done = False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        results.append(info["qos_episode"])
    if not results:
        return {}
    return {
        "eval_success_rate": float(np.mean([r["success"] for r in results])),
        "eval_mean_reliability": float(np.mean([r["mean_reliability"] for r in results])),
        "eval_constraint": float(np.mean([r["constraint"] for r in results])),
    }


def train_stage_c(
    config: StageCConfig,
    *,
    out_dir: str | Path,
    work_dir: str | Path,
    resume: bool = False,
    progress: Progress = no_progress,
    command: str | None = None,
    stage: str = "c",
) -> dict[str, Any]:
    """Learn the QoS policy with SAC (+ dual ascent); write it to ``out_dir``.

    ``out_dir`` receives the :class:`~codesign_mb.adaptation.learned.LearnedQosPolicy`
    (``model.zip`` + ``qos_policy.json``), ``training.json`` and ``curve.json`` (per chunk:
    the evaluation, the multiplier and the training episodes' statistics; plus the dual
    ascent history in ``training.json``).
    """
    from stable_baselines3 import SAC

    work_dir = Path(work_dir)
    env = make_qos_env(config)
    eval_env = make_qos_env(config)
    state = load_state(work_dir) if resume else None
    model = resume_sac(work_dir, env) if state is not None else None
    if model is None:
        state = TrainingState(stage=stage, total_steps=config.total_steps)
        if config.warm_start:
            source = resolve_checkpoint(config.warm_start)
            model = SAC.load(source / "model.zip", env=env, device="cpu")
            model.set_random_seed(config.seed)
            model.num_timesteps = 0  # a new run: count this stage's steps from zero
            state.extra["warm_start"] = str(config.warm_start)
            if config.warm_start_lambda:
                state.extra["lambda"] = warm_start_multiplier(source, default=config.env.lam)
        else:
            model = make_sac(env, config.sac, seed=config.seed)
        (work_dir / "best_model.zip").unlink(missing_ok=True)
    assert state is not None
    state.total_steps = config.total_steps
    lam = float(state.extra.get("lambda", config.env.lam))
    d = config.dual
    callback = DualAscentCallback(
        j_max=config.env.j_max,
        lam=lam,
        enabled=d.enabled,
        learning_rate=d.learning_rate,
        every_episodes=d.every_episodes,
        lam_min=d.lam_min,
        lam_max=d.lam_max,
    )
    callback.history = list(state.extra.get("dual_history", []))
    callback.episodes = int(state.extra.get("episodes", 0))

    def on_chunk(m: Any, s: TrainingState) -> dict[str, Any]:
        s.extra["lambda"] = callback.lam
        s.extra["dual_history"] = callback.history
        s.extra["episodes"] = callback.episodes
        return callback.summary()

    def evaluate(m: Any) -> dict[str, float]:
        eval_env.set_lambda(callback.lam)
        return evaluate_qos_agent(eval_env, m, episodes=config.eval_episodes, seed=config.seed + 2)

    started = time.perf_counter()
    train_sac_in_chunks(
        model,
        state,
        work_dir=work_dir,
        chunk_steps=config.chunk_steps,
        evaluate=evaluate if config.eval_episodes else None,
        callback=callback,
        on_chunk=on_chunk,
        progress=progress,
        description=f"stage {stage.upper()} (SAC QoS policy)",
        keep_best=(lambda p: feasible_score(p, config.target_success))
        if config.keep_best and config.eval_episodes
        else None,
    )
    best_path = work_dir / "best_model.zip"
    if config.keep_best and config.eval_episodes and best_path.is_file():
        model = SAC.load(best_path, env=env, device="cpu")
        steps = state.extra["best"]["steps"]
        point = next(p for p in state.curve if p["steps"] == steps)
        state.extra["shipped"] = {"steps": steps, "lambda": point.get("lambda", callback.lam)}
    else:
        state.extra["shipped"] = {"steps": state.steps_done, "lambda": callback.lam}
    final = evaluate_qos_agent(
        eval_env, model, episodes=max(config.eval_episodes, 1), seed=config.seed + 3
    )
    state.extra["session_wall_time_s"] = round(time.perf_counter() - started, 1)
    write_output(
        out_dir,
        model=None,
        state=state,
        config=config,
        command=command,
        seed=config.seed,
        final=final,
        notes=(
            "SB3 SAC QoS agent (eq_q_t_pol2); "
            + ("lambda by dual ascent" if d.enabled else "fixed lambda")
            + (
                f"; shipped: the evaluated policy of step {state.extra['shipped']['steps']} "
                f"(lowest reliability at >= {config.target_success:.0%} evaluation success, "
                "else the most successful; see curve.json)"
                if config.keep_best and config.eval_episodes
                else "; shipped: the last iterate"
            )
        ),
    )
    LearnedQosPolicy(model, env.interface, features=env.features).save(
        out_dir,
        extra={
            "features": {"kind": config.features, "options": dict(config.feature_options)},
            "controller": _spec_json(config.controller),
            "estimator": _spec_json(config.estimator),
        },
    )
    env.close()
    eval_env.close()
    return {"env_steps": state.steps_done, "wall_time_s": state.wall_time_s, **final}


def warm_start_multiplier(policy_dir: str | Path, *, default: float) -> float:
    """The multiplier a saved QoS policy was trained with (``default`` if unrecorded).

    That of the shipped iterate (``training.json``'s ``shipped``), else the final one.
    """
    import json

    path = Path(policy_dir) / "training.json"
    if not path.is_file():
        return float(default)
    meta = json.loads(path.read_text())
    return float((meta.get("shipped") or {}).get("lambda", meta.get("lambda", default)))


def _spec_json(spec: ComponentSpec) -> dict[str, Any]:
    return {"kind": spec.kind, "checkpoint": spec.checkpoint, "options": dict(spec.options)}
