"""Stage D, co-design synthesis (paper.tex sec. 4.4).

1. Continue the estimator's training (``eq_control_estimation``) with the generic delay
   distribution ``T`` replaced by the learned QoS policy's delivery pattern: episodes are
   collected through the link with the stage-C policy choosing ``q_t`` and the controller
   acting on the estimator (the deployed loop), optionally mixed with fresh episodes from
   ``T`` so the estimator keeps covering other patterns; the fit continues from the stage-B
   weights and normalisation.
2. Re-train the QoS policy (``eq_q_t_pol2``) for the new estimator, warm-started from the
   stage-C policy.

Any learned estimator (MLP or LSTM) and any controller can be given; the model-based stack
has no estimator weights to continue, so only step 2 applies to it (run stage C with
``warm_start``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from codesign_mb.adaptation.learned import LearnedQosPolicy
from codesign_mb.core.config import EPISODES_CAP
from codesign_mb.core.registry import (
    ComponentSpec,
    PlantSpec,
    make_plant,
    resolve_checkpoint,
)
from codesign_mb.estimation.learned import LearnedEstimator, load_estimator
from codesign_mb.stages.episodes import (
    DelayDistribution,
    EpisodeData,
    RandomQos,
    cached_episodes,
    collect_episodes,
    estimator_mse,
    position_slice,
)
from codesign_mb.stages.fitting import EstimatorTraining, fit_estimator
from codesign_mb.stages.qos_env import QosEnvConfig
from codesign_mb.stages.stage import StageRun
from codesign_mb.stages.stage_c import StageCConfig, train_stage_c
from codesign_mb.stages.training import (
    Progress,
    require_at_least,
    seeded_torch,
    training_record,
    write_training_record,
)

__all__ = ["StageDConfig", "train_stage_d"]


@dataclass(frozen=True)
class StageDConfig:
    """Configuration of stage D.

    Parameters
    ----------
    plant:
        The plant.
    controller:
        The ideal controller (stage A).
    estimator:
        The learned estimator to continue (stage B's ``mlp.pt`` by default).
    qos_policy:
        The learned QoS policy folder (stage C) whose deliveries the estimator adapts to;
        also the warm start of the re-trained policy.
    episodes, val_episodes:
        Episodes collected under the learned QoS policy (fit / held out).
    sample_qos:
        Sample the QoS policy's actions (more varied delivery patterns) instead of its mean.
    mix_episodes, delays:
        Episodes from the generic distribution ``T`` mixed into the fit (0: none).
    estimator_training:
        Optimiser settings of the continued fit.
    qos:
        Stage-C settings of the re-training; its ``plant``, ``controller``, ``estimator``,
        ``warm_start`` and ``features`` are set by this stage (the features, and the env's
        latency and reliability-range settings, are the stage-C policy's; the multiplier
        starts at its final value, ``warm_start_lambda``).
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
    qos_policy: str = "checkpoints/stage_c_mlp"
    episodes: int = 200
    val_episodes: int = 50
    sample_qos: bool = True
    mix_episodes: int = 100
    delays: DelayDistribution = field(default_factory=DelayDistribution)
    estimator_training: EstimatorTraining = field(
        default_factory=lambda: EstimatorTraining(epochs=20, learning_rate=3e-4)
    )
    qos: StageCConfig = field(default_factory=lambda: StageCConfig(total_steps=20_000))
    seed: int = 0

    def __post_init__(self) -> None:
        if self.estimator.kind not in ("mlp", "lstm"):
            raise ValueError(
                f"stage D continues a learned estimator (mlp or lstm), got {self.estimator.kind!r}"
            )
        if not self.estimator.checkpoint:
            raise ValueError("stage D needs estimator.checkpoint (the stage-B estimator)")
        require_at_least(self, 1, "episodes", "val_episodes", cap=EPISODES_CAP)
        require_at_least(self, 0, "mix_episodes", cap=EPISODES_CAP)


def train_stage_d(
    config: StageDConfig,
    run: StageRun,
) -> dict[str, Any]:
    """Run the synthesis; write ``<kind>.pt``, ``qos/`` and ``training.json`` to ``out_dir``.

    Steps: check the stage-C policy's features; collect episodes under it (and from ``T``);
    continue the estimator's fit; re-train the QoS policy for it (stage C, warm-started);
    write ``training.json`` and ``curve.json``.
    """
    out_dir, work_dir = run.out_dir, run.prepare_work_dir((".npz", ".pt"))
    resume, progress, command = run.resume, run.progress, run.command
    started = time.perf_counter()
    probe = make_plant(config.plant)
    qos_dir = resolve_checkpoint(config.qos_policy)
    meta = LearnedQosPolicy.read_meta(qos_dir)
    saved = _stage_c_features(config, meta, qos_dir)
    interface = _stage_c_interface(config, meta, qos_dir)
    # 1. the estimator under the learned QoS policy's deliveries
    fit = _continue_estimator(
        config, probe, qos_dir, out_dir=out_dir, work_dir=work_dir, resume=resume, progress=progress
    )
    estimator_s = time.perf_counter() - started
    # 2. the QoS policy re-trained for the new estimator
    qos_config = dataclasses.replace(
        config.qos,
        plant=config.plant,
        controller=config.controller,
        estimator=ComponentSpec(config.estimator.kind, str(fit.path)),
        env=dataclasses.replace(config.qos.env, **interface),
        warm_start=str(qos_dir),
        features=saved.get("kind"),
        feature_options=dict(saved.get("options") or {}),
    )
    qos_run = StageRun(out_dir / "qos", work_dir / "qos", resume, progress, command)
    qos_result = train_stage_c(qos_config, qos_run, stage="d")
    env_steps = int(sum(fit.steps.values()))
    meta = training_record(
        stage="d",
        command=command,
        seed=config.seed,
        env_steps=env_steps + int(qos_result["env_steps"]),
        wall_time_s=time.perf_counter() - started,
        config=config,
        estimator={
            "env_steps": env_steps,
            "env_steps_by_dataset": fit.steps,
            "collection_wall_time_s": round(fit.collection_wall_time_s, 1),
            "wall_time_s": round(estimator_s, 1),
            "held_out_mse_under_learned_qos": {"before": fit.before, "after": fit.after},
        },
        qos=qos_result,
    )
    write_training_record(out_dir, meta, {"estimator": fit.curve})
    probe.close()
    return {
        "env_steps": meta["env_steps"],
        "wall_time_s": meta["wall_time_s"],
        "estimator_mse_before": fit.before["mse"],
        "estimator_mse_after": fit.after["mse"],
        **{k: v for k, v in qos_result.items() if k.startswith("eval_")},
    }


def _stage_c_features(
    config: StageDConfig, meta: Mapping[str, Any], qos_dir: Path
) -> dict[str, Any]:
    """The stage-C policy's features (``meta``: its ``qos_policy.json``; the warm start fixes
    the observation); checks ``qos``."""
    saved = meta.get("features") or {}
    if config.qos.features is not None and config.qos.features != saved.get("kind"):
        raise ValueError(
            f"qos.features={config.qos.features!r} but the stage-C policy {qos_dir} was "
            f"trained with {saved.get('kind')!r}"
        )
    return saved


_INTERFACE_FIELDS = ("latency_steps", "learn_latency", "max_latency_steps", "min_reliability",
                     "age_scale")  # fmt: skip
"""The QoS env settings that define the policy's actions and observations."""


def _stage_c_interface(
    config: StageDConfig, meta: Mapping[str, Any], qos_dir: Path
) -> dict[str, Any]:
    """The stage-C policy's action/observation settings (``meta``: its ``qos_policy.json``;
    the warm start fixes them, as its features): a ``qos.env`` value set to something else
    than both the default and the policy's is an error, never silently replaced."""
    saved = meta.get("interface") or {}
    default = QosEnvConfig()
    out: dict[str, Any] = {}
    for name in _INTERFACE_FIELDS:
        if name not in saved:
            continue
        given, theirs = getattr(config.qos.env, name), saved[name]
        if given != theirs and given != getattr(default, name):
            raise ValueError(
                f"qos.env.{name}={given!r} but the stage-C policy {qos_dir} was trained with "
                f"{theirs!r}"
            )
        out[name] = type(getattr(default, name))(theirs)
    return out


@dataclass
class _EstimatorFit:
    """What step 1 produced: the saved estimator, its data, curve and held-out MSE."""

    path: Path
    steps: dict[str, int]
    collection_wall_time_s: float
    curve: list[dict[str, float]]
    before: dict[str, float]
    after: dict[str, float]


def _collect(
    config: StageDConfig, qos_dir: Path, probe: Any, work_dir: Path
) -> tuple[EpisodeData, EpisodeData, dict[str, int]]:
    """Episodes under the learned QoS policy (fit, held out), plus ``mix_episodes`` from ``T``.

    The controller (built on the plant each collection steps) acts on the stage-B estimator
    (the deployed loop); cached in ``work_dir``.
    Returns the fitting data, the held-out data and the steps per dataset.
    """
    qos_policy = LearnedQosPolicy.from_env(probe, qos_dir, deterministic=not config.sample_qos)

    def under_policy(name: str, episodes: int, seed: int) -> EpisodeData:
        behaviour = load_estimator(resolve_checkpoint(config.estimator.checkpoint))

        def make() -> EpisodeData:
            with seeded_torch(seed):  # the sampled QoS actions draw from torch's RNG
                return collect_episodes(
                    config.plant,
                    config.controller,
                    qos_policy,
                    episodes=episodes,
                    seed=seed,
                    behaviour=behaviour,
                )

        return cached_episodes(work_dir / f"{name}.npz", make)

    train = under_policy("train_policy", config.episodes, config.seed + 30)
    val = under_policy("val_policy", config.val_episodes, config.seed + 40)
    steps = {"train_policy": train.steps, "val_policy": val.steps}
    data = EpisodeData().extend(train)
    if config.mix_episodes:
        mix = cached_episodes(
            work_dir / "train_mix.npz",
            lambda: collect_episodes(
                config.plant,
                config.controller,
                RandomQos(config.delays),
                episodes=config.mix_episodes,
                seed=config.seed + 50,
            ),
        )
        steps["train_mix"] = mix.steps
        data.extend(mix)
    return data, val, steps


def _continue_estimator(
    config: StageDConfig,
    probe: Any,
    qos_dir: Path,
    *,
    out_dir: Path,
    work_dir: Path,
    resume: bool,
    progress: Progress,
) -> _EstimatorFit:
    """Step 1: continue the stage-B estimator's fit on episodes under the learned QoS."""
    kind = config.estimator.kind
    remote, position = probe.unwrapped.remote_slice, position_slice(probe)
    estimator_ckpt = work_dir / f"{kind}.pt"
    estimator: LearnedEstimator = load_estimator(resolve_checkpoint(config.estimator.checkpoint))
    started = time.perf_counter()
    data, val, steps = _collect(config, qos_dir, probe, work_dir)
    collect_s = time.perf_counter() - started
    before = estimator_mse(estimator, val, remote=remote, position=position)
    if resume and estimator_ckpt.is_file():
        estimator = load_estimator(estimator_ckpt)
        curve: list[dict[str, float]] = []
    else:
        curve = fit_estimator(
            estimator,
            data,
            val,
            config.estimator_training,
            seed=config.seed + 60,
            fit_normalisation=False,
            progress=progress,
            description=f"stage D: {kind} under the learned QoS",
        )
        estimator.save(estimator_ckpt)
    after = estimator_mse(estimator, val, remote=remote, position=position)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = Path(estimator.save(out_dir / f"{kind}.pt"))
    return _EstimatorFit(path, steps, collect_s, curve, before, after)
