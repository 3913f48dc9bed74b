"""Stage B, QoS-aware state estimation (``eq_control_estimation``, ``eq_c_pol2``).

Rollouts of the stage-A controller go through a :class:`LinkObservationWrapper` whose QoS is
drawn from a :class:`DelayDistribution` (the paper's ``T``: per-episode reliability, uniform
per-packet latency; each packet is lost with probability ``1 - q``). Each step records the
networked observation ``(y_t, zeta_t)``, the previous action and the true remote state
``x_t``; the MLP and LSTM estimators of :mod:`codesign_mb.estimation.learned` are fitted to
it in torch with the MSE of ``eq_control_estimation``.

Data are collected (:mod:`~codesign_mb.stages.episodes`, through THE closed loop) with the
controller acting on the true state (the ideal trajectories of the expectation in
``eq_control_estimation``), then for ``dagger_rounds`` more rounds with the controller acting
on the estimator being trained (so it also sees the states its own errors lead to), each round
re-fitting (:mod:`~codesign_mb.stages.fitting`) on everything collected so far.

Any :class:`~codesign_mb.estimation.base.Estimator` can be scored on the same held-out
episodes with :func:`estimator_mse`, which is how the learned estimators are compared with the
model-based :class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor`: overall and
per phase of the object (:mod:`codesign_mb.plants.phases`), in ``training.json``.

The plant is any scenario's (``codesign train b --scenario realistic``: belt speeds drawn per
episode, perception errors, the packet carrying the perceived position only). Where the packet
has no velocity the estimators also estimate it and output the plant's ``state_layout``
(:func:`~codesign_mb.stages.episodes.estimates_velocity`); ``training.json`` records both
layouts, and tables skip a checkpoint trained on another layout.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from codesign_mb.core.config import EPISODES_CAP, WORKERS_CAP, check_range
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.estimation.base import Estimator
from codesign_mb.estimation.learned import LearnedEstimator, load_estimator
from codesign_mb.estimation.sequence import CELLS
from codesign_mb.stages.episodes import (
    DelayDistribution,
    EpisodeData,
    RandomQos,
    cached_episodes,
    collect_episodes,
    estimates_velocity,
    estimator_mse,
    position_slice,
    velocity_slice,
)
from codesign_mb.stages.fitting import EstimatorTraining, fit_estimator, new_estimator
from codesign_mb.stages.stage import StageRun
from codesign_mb.stages.training import (
    WIDTH_CAP,
    Progress,
    require_at_least,
    training_record,
    write_json,
    write_training_record,
)

__all__ = ["ESTIMATOR_KINDS", "StageBConfig", "train_stage_b"]

ESTIMATOR_KINDS = ("mlp", "lstm", "sequence")
"""The learned estimators stage B trains (their order fixes each one's DAgger seeds)."""


@dataclass(frozen=True)
class StageBConfig:
    """Configuration of stage B.

    Parameters
    ----------
    plant:
        The plant.
    controller:
        The ideal controller driving the rollouts (stage A's SAC by default; on the
        ``realistic`` scenario: ``checkpoints/stage_a_realistic/model.zip``, which reads the
        state layout, velocity included, given by ideal control or the estimators).
    delays:
        The QoS distribution ``T`` (``eq_control_estimation``): per-episode reliability and
        per-packet latency, both uniform (the paper's recipe).
    kinds:
        Estimators to train: ``"mlp"``, ``"lstm"`` (point estimates, the paper's) and/or
        ``"sequence"`` (the Gaussian sequence estimator, :mod:`codesign_mb.estimation.sequence`).
    train_episodes, val_episodes:
        Episodes collected with the controller on the true state, for fitting and held out.
    dagger_rounds, dagger_episodes:
        Extra rounds collected with the controller acting on the estimator being trained.
    mlp_hidden, lstm_hidden, sequence_hidden:
        Network sizes.
    sequence_cell:
        The sequence estimator's recurrent cell (``"gru"`` or ``"lstm"``).
    mlp, lstm, sequence:
        Optimiser settings of each (the first fit).
    sequence_dagger:
        The sequence estimator's settings in the DAgger rounds (continuing from the last fit;
        the MLP and LSTM repeat their own).
    workers:
        Processes collecting the episodes (the data do not depend on it).
    age_scale:
        The age enters the networks as ``zeta / age_scale``.
    compare:
        Other estimators scored on the same held-out episodes (``none``: the stale
        observation; ``predictor``: the model-based delay-compensating predictor).
    seed:
        Root seed (data, initialisation, minibatches).
    """

    plant: PlantSpec = field(default_factory=PlantSpec)
    controller: ComponentSpec = field(
        default_factory=lambda: ComponentSpec("sac", "checkpoints/stage_a/model.zip")
    )
    delays: DelayDistribution = field(default_factory=DelayDistribution)
    kinds: tuple[str, ...] = ("mlp", "lstm")
    train_episodes: int = 300
    val_episodes: int = 100
    dagger_rounds: int = 1
    dagger_episodes: int = 150
    mlp_hidden: tuple[int, ...] = (128, 128)
    lstm_hidden: int = 64
    mlp: EstimatorTraining = field(default_factory=EstimatorTraining)
    lstm: EstimatorTraining = field(default_factory=lambda: EstimatorTraining(epochs=60))
    sequence_hidden: int = 128
    sequence_cell: str = "gru"
    sequence: EstimatorTraining = field(
        default_factory=lambda: EstimatorTraining(
            epochs=60, sequence_batch_size=32, cosine_decay=True
        )
    )
    sequence_dagger: EstimatorTraining = field(
        default_factory=lambda: EstimatorTraining(
            epochs=30, learning_rate=5e-4, sequence_batch_size=32, cosine_decay=True
        )
    )
    workers: int = 1
    age_scale: float = 10.0
    compare: tuple[ComponentSpec, ...] = (ComponentSpec("none"), ComponentSpec("predictor"))
    seed: int = 0

    def __post_init__(self) -> None:
        bad = [k for k in self.kinds if k not in ESTIMATOR_KINDS]
        if bad or not self.kinds:
            raise ValueError(
                f"kinds must be a non-empty subset of {ESTIMATOR_KINDS}, got {self.kinds}"
            )
        if self.sequence_cell not in CELLS:
            raise ValueError(f"sequence_cell must be one of {CELLS}, got {self.sequence_cell!r}")
        check_range("sequence_hidden", self.sequence_hidden, ge=1, cap=WIDTH_CAP)
        check_range("workers", self.workers, ge=1, cap=WORKERS_CAP)
        require_at_least(self, 1, "train_episodes", "val_episodes", cap=EPISODES_CAP)
        require_at_least(self, 0, "dagger_rounds", "dagger_episodes", cap=EPISODES_CAP)
        check_range("mlp_hidden", self.mlp_hidden, ge=1, cap=WIDTH_CAP)
        check_range("lstm_hidden", self.lstm_hidden, ge=1, cap=WIDTH_CAP)
        object.__setattr__(
            self,
            "compare",
            tuple(c if isinstance(c, ComponentSpec) else ComponentSpec(**c) for c in self.compare),
        )


@dataclass
class _Collection:
    """Stage B's datasets, cached in the work folder; counts their steps and wall time."""

    config: StageBConfig
    work_dir: Path
    steps: dict[str, int] = field(default_factory=dict)
    wall_time_s: float = 0.0

    def __post_init__(self) -> None:
        self.qos = RandomQos(self.config.delays)

    def __call__(
        self, name: str, episodes: int, seed: int, behaviour: Estimator | None = None
    ) -> EpisodeData:
        started = time.perf_counter()
        data = cached_episodes(
            self.work_dir / f"{name}.npz",
            lambda: collect_episodes(
                self.config.plant,
                self.config.controller,  # built on the plant it steps
                self.qos,
                episodes=episodes,
                seed=seed,
                behaviour=behaviour,
                workers=self.config.workers,
            ),
        )
        self.wall_time_s += time.perf_counter() - started
        self.steps[name] = data.steps
        return data


def train_stage_b(
    config: StageBConfig,
    run: StageRun,
) -> dict[str, Any]:
    """Collect data, fit the estimators, compare them on held-out data; write ``out_dir``.

    ``out_dir`` receives ``<kind>.pt`` per estimator, ``training.json`` (settings, data and
    wall time, the held-out MSE table) and ``curve.json`` (loss per epoch). Collected data are
    cached in ``work_dir``; with ``resume`` a finished round or fit is not redone.
    """
    out_dir, work_dir = run.out_dir, run.prepare_work_dir((".npz", ".pt", "curves.json"))
    resume, progress, command = run.resume, run.progress, run.command
    started = time.perf_counter()
    probe = make_plant(config.plant)
    collect = _Collection(config, work_dir)
    where = {
        "remote": probe.unwrapped.remote_slice,
        "position": position_slice(probe),
        "velocity": velocity_slice(probe),
    }
    train0 = collect("train_round0", config.train_episodes, config.seed + 10)
    val = collect("val", config.val_episodes, config.seed + 20)
    curves_path = work_dir / "curves.json"
    curves: dict[str, list[dict[str, float]]] = (
        json.loads(curves_path.read_text()) if resume and curves_path.is_file() else {}
    )
    results: dict[str, dict[str, Any]] = {}
    for kind in config.kinds:
        estimator = _train_estimator(
            config, kind, probe, collect, train0, val, curves, resume=resume, progress=progress
        )
        out_dir.mkdir(parents=True, exist_ok=True)
        estimator.save(out_dir / f"{kind}.pt")
        results[kind] = estimator_mse(estimator, val, **where)
    results.update(_compare(config, probe, val, where))
    meta = training_record(
        stage="b",
        command=command,
        seed=config.seed,
        env_steps=sum(collect.steps.values()),
        wall_time_s=time.perf_counter() - started,
        config=config,
        env_steps_by_dataset=collect.steps,
        collection_wall_time_s=round(collect.wall_time_s, 1),
        held_out_mse=results,
        held_out_episodes=len(val),
        layout=_layouts(probe),
    )
    write_training_record(out_dir, meta, curves)
    probe.close()
    return {"env_steps": meta["env_steps"], "wall_time_s": meta["wall_time_s"], "mse": results}


def _train_estimator(
    config: StageBConfig,
    kind: str,
    probe: Any,
    collect: _Collection,
    train0: EpisodeData,
    val: EpisodeData,
    curves: dict[str, list[dict[str, float]]],
    *,
    resume: bool,
    progress: Progress,
) -> LearnedEstimator:
    """Fit one estimator on the ideal data, then DAgger rounds acting through it.

    Each round's fit is saved in the work folder (``<kind>_round<r>.pt``) with the curves;
    resuming loads a finished round instead of refitting it.
    """
    work_dir = collect.work_dir
    ckpt = work_dir / f"{kind}_round{config.dagger_rounds}.pt"
    if resume and ckpt.is_file():
        return load_estimator(ckpt)
    hidden = {"mlp": config.mlp_hidden, "lstm": config.lstm_hidden}.get(
        kind, config.sequence_hidden
    )
    settings = {"mlp": config.mlp, "lstm": config.lstm}.get(kind, config.sequence)
    estimator = new_estimator(
        kind,
        probe,
        hidden=hidden,
        age_scale=config.age_scale,
        seed=config.seed,
        cell=config.sequence_cell,
    )
    data = EpisodeData().extend(train0)
    curves.setdefault(kind, [])
    for round_ in range(config.dagger_rounds + 1):
        if round_ > 0:
            seed = config.seed + 100 * round_ + ESTIMATOR_KINDS.index(kind)
            name = f"train_{kind}_round{round_}"
            data.extend(collect(name, config.dagger_episodes, seed, behaviour=estimator))
        round_ckpt = work_dir / f"{kind}_round{round_}.pt"
        if resume and round_ckpt.is_file():
            estimator = load_estimator(round_ckpt)
            continue
        curve = fit_estimator(
            estimator,
            data,
            val,
            config.sequence_dagger if kind == "sequence" and round_ else settings,
            seed=config.seed + round_,
            fit_normalisation=round_ == 0,
            progress=progress,
            description=f"stage B: {kind} round {round_}",
        )
        curves[kind].extend({"round": round_, **p} for p in curve)
        estimator.save(round_ckpt)
        write_json(work_dir / "curves.json", curves)
    return estimator


def _layouts(probe: Any) -> dict[str, Any]:
    """The plant's observation and state layouts (name -> [start, stop]) and whether the
    estimators append the velocity the packet lacks."""
    plant = probe.unwrapped

    def spans(layout: dict[str, slice]) -> dict[str, list[int]]:
        return {name: [int(s.start), int(s.stop)] for name, s in layout.items()}

    observation = getattr(plant, "observation_layout", None) or {}
    state = getattr(plant, "state_layout", None) or observation
    return {
        "observation": spans(observation),
        "state": spans(state),
        "estimates_velocity": estimates_velocity(probe),
    }


def _compare(
    config: StageBConfig, probe: Any, val: EpisodeData, where: dict[str, Any]
) -> dict[str, dict[str, Any]]:
    """The held-out MSE of the ``compare`` estimators (an unavailable one is reported)."""
    results: dict[str, dict[str, Any]] = {}
    for spec in config.compare:
        try:
            baseline = build("estimator", spec, probe)
        except ImportError as exc:  # a part not written yet: report, do not fail the stage
            results[spec.kind] = {"error": f"unavailable: {exc}"}
            continue
        results[spec.kind] = estimator_mse(baseline, val, **where)
    return results
