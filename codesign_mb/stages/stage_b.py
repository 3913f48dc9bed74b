"""Stage B, QoS-aware state estimation (``eq_control_estimation``, ``eq_c_pol2``).

Rollouts of the stage-A controller go through a :class:`LinkObservationWrapper` whose QoS is
drawn from a :class:`DelayDistribution` (the paper's ``T``: per-episode reliability, uniform
per-packet latency; each packet is lost with probability ``1 - q``). Each step records the
networked observation ``(y_t, zeta_t)``, the previous action and the true remote state
``x_t``; the MLP and LSTM estimators of :mod:`codesign_mb.estimation.learned` are fitted to
it in torch with the MSE of ``eq_control_estimation``.

Data are collected with the controller acting on the true state (the ideal trajectories of
the expectation in ``eq_control_estimation``), then for ``dagger_rounds`` more rounds with the
controller acting on the estimator being trained (so it also sees the states its own errors
lead to), each round re-fitting on everything collected so far.

Any :class:`~codesign_mb.estimation.base.Estimator` can be scored on the same held-out
episodes with :func:`estimator_mse`, which is how the learned estimators are compared with the
model-based :class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor`.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from codesign_mb.core.config import to_mapping
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.core.results import atomic_write, package_version
from codesign_mb.estimation.learned import (
    EstimatorFeatures,
    LearnedEstimator,
    LstmEstimator,
    MlpEstimator,
    load_estimator,
)
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.qos import QosRequest
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.stages.training import Progress, no_progress, write_json

__all__ = [
    "DelayDistribution",
    "EpisodeData",
    "EstimatorTraining",
    "RandomQos",
    "StageBConfig",
    "collect_episodes",
    "estimator_mse",
    "fit_estimator",
    "train_stage_b",
]


@dataclass(frozen=True)
class DelayDistribution:
    """The QoS distribution ``T`` the estimators are trained under.

    Each episode draws its reliability ``q ~ U[reliability_low, reliability_high]``; each
    packet is delivered with probability ``q`` (Bernoulli loss, ``eq_d``) after a latency
    ``tau ~ U{latency_low, ..., latency_high}`` steps. The age ``zeta_t`` follows from both.
    """

    reliability_low: float = 0.0
    reliability_high: float = 1.0
    latency_low: int = 0
    latency_high: int = 4

    def __post_init__(self) -> None:
        if not 0.0 <= self.reliability_low <= self.reliability_high <= 1.0:
            raise ValueError(
                "need 0 <= reliability_low <= reliability_high <= 1, got "
                f"{self.reliability_low}, {self.reliability_high}"
            )
        if not 0 <= self.latency_low <= self.latency_high:
            raise ValueError(
                "need 0 <= latency_low <= latency_high, got "
                f"{self.latency_low}, {self.latency_high}"
            )


class RandomQos:
    """A :class:`~codesign_mb.adaptation.QosPolicy` drawing from a :class:`DelayDistribution`."""

    def __init__(self, distribution: DelayDistribution, seed: int | None = None) -> None:
        self.distribution = distribution
        self._rng = np.random.default_rng(seed)
        self.reliability = distribution.reliability_high

    def reset(self, *, seed: int | None = None) -> None:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        d = self.distribution
        self.reliability = float(self._rng.uniform(d.reliability_low, d.reliability_high))

    def request(self, observation: np.ndarray, age: int) -> QosRequest:
        d = self.distribution
        tau = int(self._rng.integers(d.latency_low, d.latency_high + 1))
        return QosRequest(self.reliability, tau)


@dataclass
class EpisodeData:
    """Recorded episodes, one array per episode (``T_i + 1`` steps each, from the reset on).

    ``networked[i][t]`` is the wrapped observation (plant layout with ``y_t``, then
    ``zeta_t``), ``prev_actions[i][t]`` the action applied before it (zeros at ``t = 0``),
    ``truth[i][t]`` the true remote state ``x_t``, ``reliability[i][t]`` the requested ``q``.
    """

    networked: list[np.ndarray] = field(default_factory=list)
    prev_actions: list[np.ndarray] = field(default_factory=list)
    truth: list[np.ndarray] = field(default_factory=list)
    reliability: list[np.ndarray] = field(default_factory=list)
    success: list[bool] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.networked)

    @property
    def steps(self) -> int:
        return int(sum(len(x) for x in self.networked))

    def extend(self, other: EpisodeData) -> EpisodeData:
        for name in ("networked", "prev_actions", "truth", "reliability", "success"):
            getattr(self, name).extend(getattr(other, name))
        return self

    def save(self, path: str | Path) -> None:
        """Write to one ``.npz`` (episodes concatenated, with their lengths)."""

        lengths = np.array([len(x) for x in self.networked], dtype=np.int64)
        with atomic_write(path) as fh:
            np.savez_compressed(
                fh,
                lengths=lengths,
                networked=np.concatenate(self.networked),
                prev_actions=np.concatenate(self.prev_actions),
                truth=np.concatenate(self.truth),
                reliability=np.concatenate(self.reliability),
                success=np.asarray(self.success, dtype=bool),
            )

    @classmethod
    def load(cls, path: str | Path) -> EpisodeData:
        with np.load(path) as z:
            cuts = np.cumsum(z["lengths"])[:-1]
            return cls(
                networked=list(np.split(z["networked"], cuts)),
                prev_actions=list(np.split(z["prev_actions"], cuts)),
                truth=list(np.split(z["truth"], cuts)),
                reliability=list(np.split(z["reliability"], cuts)),
                success=[bool(s) for s in z["success"]],
            )


def _episode_seeds(seed: int, n: int) -> list[int]:
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(max(n, 1))[:n]]


def collect_episodes(
    plant: PlantSpec,
    controller: Any,
    qos_policy: Any,
    *,
    episodes: int,
    seed: int,
    behaviour: Any = None,
) -> EpisodeData:
    """Roll ``controller`` out through a Bernoulli link with ``qos_policy`` and record it.

    ``behaviour`` is the estimator the controller acts through (``None``: the true state,
    i.e. the ideal trajectories). Episode ``i`` is seeded from ``SeedSequence(seed)``.
    """
    env = LinkObservationWrapper(make_plant(plant), BernoulliLink(), qos_policy)
    remote = env.remote_slice
    data = EpisodeData()
    for s in _episode_seeds(seed, episodes):
        obs, info = env.reset(seed=s)
        controller.reset(seed=s)
        estimate = behaviour.reset(obs) if behaviour is not None else None
        act_dim = int(np.prod(env.action_space.shape))
        nets, prevs, truths, qs = [obs], [np.zeros(act_dim)], [info["remote_true"]], []
        qs.append(info["qos_reliability"])
        success, done = bool(info.get("success", False)), False
        while not done:
            if behaviour is None:
                state = np.asarray(obs[:-1], dtype=float).copy()
                state[remote] = info["remote_true"]
            else:
                state = estimate
            action = np.asarray(controller.act(state), dtype=float)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
            success = success or bool(info.get("success", False))
            if behaviour is not None and not done:
                estimate = behaviour.estimate(obs, action)
            nets.append(obs)
            prevs.append(action)
            truths.append(info["remote_true"])
            qs.append(info["qos_reliability"])
        data.networked.append(np.asarray(nets, dtype=np.float32))
        data.prev_actions.append(np.asarray(prevs, dtype=np.float32))
        data.truth.append(np.asarray(truths, dtype=np.float32))
        data.reliability.append(np.asarray(qs, dtype=np.float32))
        data.success.append(success)
    env.close()
    return data


def estimator_mse(
    estimator: Any, data: EpisodeData, *, remote: slice, position: slice | None = None
) -> dict[str, float]:
    """Score any :class:`~codesign_mb.estimation.base.Estimator` on recorded episodes.

    Runs ``reset``/``estimate`` along each episode exactly as a rollout does and returns the
    mean squared error of the remote estimate over all steps (``mse``, summed over the remote
    entries). With ``position`` (the ``object_pos`` slice of the plant observation) also the
    object position's ``mse_position`` (m^2) and RMSE, overall and split into the steps where
    the object rides the belt and where it is off it (more than 1 cm above its first height:
    grasped and lifted), since the two phases have different dynamics.
    """
    sq, n = 0.0, 0
    sq_pos = np.zeros(2)
    n_pos = np.zeros(2)
    for nets, prevs, truth in zip(data.networked, data.prev_actions, data.truth, strict=True):
        nets64 = np.asarray(nets, dtype=np.float64)
        estimates = [estimator.reset(nets64[0])]
        for t in range(1, len(nets64)):
            estimates.append(estimator.estimate(nets64[t], np.asarray(prevs[t], dtype=np.float64)))
        est = np.asarray(estimates)
        sq += float(np.sum((est[:, remote] - truth) ** 2))
        n += len(nets64)
        if position is not None:
            true_pos = _position_truth(truth, remote, position)
            err = np.sum((est[:, position] - true_pos) ** 2, axis=1)
            off = true_pos[:, 2] > true_pos[0, 2] + 0.01
            for i, mask in enumerate((~off, off)):
                sq_pos[i] += float(err[mask].sum())
                n_pos[i] += int(mask.sum())
    out = {"mse": sq / max(n, 1)}
    if position is not None:
        out["mse_position"] = float(sq_pos.sum() / max(n, 1))
        out["rmse_position_m"] = float(np.sqrt(out["mse_position"]))
        for i, phase in enumerate(("on_belt", "off_belt")):
            if n_pos[i]:
                out[f"rmse_position_{phase}_m"] = float(np.sqrt(sq_pos[i] / n_pos[i]))
    return out


def _position_truth(truth: np.ndarray, remote: slice, position: slice) -> np.ndarray:
    start = position.start - remote.start
    return truth[:, start : start + (position.stop - position.start)]


# -- fitting -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class EstimatorTraining:
    """Optimiser settings for one estimator fit (Adam on the normalised MSE)."""

    epochs: int = 40
    learning_rate: float = 1e-3
    batch_size: int = 256
    sequence_batch_size: int = 16
    weight_decay: float = 0.0

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "sequence_batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.learning_rate <= 0:
            raise ValueError(f"learning_rate must be > 0, got {self.learning_rate}")


def _arrays(estimator: LearnedEstimator, data: EpisodeData) -> tuple[list[np.ndarray], list]:
    f = estimator.features
    feats, residuals = [], []
    for nets, prevs, truth in zip(data.networked, data.prev_actions, data.truth, strict=True):
        feats.append(f(nets, prevs))
        residuals.append(truth - nets[:, f.remote_slice])
    return feats, residuals


def fit_estimator(
    estimator: LearnedEstimator,
    train: EpisodeData,
    val: EpisodeData | None,
    settings: EstimatorTraining,
    *,
    seed: int,
    fit_normalisation: bool = True,
    progress: Progress = no_progress,
    description: str = "estimator",
) -> list[dict[str, float]]:
    """Fit ``estimator`` (MLP or LSTM) to ``train``: the MSE of ``eq_control_estimation``.

    The loss is the MSE of the residual ``x_t - y_t`` in units of its training spread (so the
    position and velocity entries weigh alike). Returns one curve point per epoch
    (``train_loss``, and ``val_loss`` when ``val`` is given). ``fit_normalisation=False``
    keeps the input/output scaling (stage D continues a fit).
    """
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = estimator.net
    feats, residuals = _arrays(estimator, train)
    if fit_normalisation:
        net.set_normalisation(np.concatenate(feats), np.concatenate(residuals))
    optimiser = torch.optim.Adam(
        net.parameters(), lr=settings.learning_rate, weight_decay=settings.weight_decay
    )
    recurrent = isinstance(estimator, LstmEstimator)
    val_arrays = _arrays(estimator, val) if val is not None and len(val) else None
    curve = []
    net.train()
    for epoch in progress(range(settings.epochs), total=settings.epochs, description=description):
        if recurrent:
            loss = _lstm_epoch(net, optimiser, feats, residuals, settings, rng)
        else:
            loss = _mlp_epoch(net, optimiser, feats, residuals, settings, gen)
        point = {"epoch": epoch + 1, "train_loss": loss}
        if val_arrays is not None:
            point["val_loss"] = _loss(net, *val_arrays, recurrent=recurrent)
        curve.append(point)
    net.eval()
    return curve


def _normalised_mse(net: Any, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (((pred - target) / net.out_std) ** 2).mean()


def _mlp_epoch(net, optimiser, feats, residuals, settings, gen) -> float:
    x = torch.as_tensor(np.concatenate(feats))
    y = torch.as_tensor(np.concatenate(residuals))
    order = torch.randperm(len(x), generator=gen)
    total, count = 0.0, 0
    for start in range(0, len(x), settings.batch_size):
        idx = order[start : start + settings.batch_size]
        loss = _normalised_mse(net, net(x[idx]), y[idx])
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        total += loss.item() * len(idx)
        count += len(idx)
    return total / max(count, 1)


def _pad(seqs: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    longest = max(len(s) for s in seqs)
    out = np.zeros((len(seqs), longest, seqs[0].shape[-1]), dtype=np.float32)
    mask = np.zeros((len(seqs), longest), dtype=np.float32)
    for i, s in enumerate(seqs):
        out[i, : len(s)] = s
        mask[i, : len(s)] = 1.0
    return torch.as_tensor(out), torch.as_tensor(mask)


def _masked_loss(net, x, y, mask) -> torch.Tensor:
    pred, _ = net(x)
    per_step = (((pred - y) / net.out_std) ** 2).mean(-1)
    return (per_step * mask).sum() / mask.sum()


def _lstm_epoch(net, optimiser, feats, residuals, settings, rng) -> float:
    order = rng.permutation(len(feats))
    total, count = 0.0, 0
    for start in range(0, len(order), settings.sequence_batch_size):
        idx = order[start : start + settings.sequence_batch_size]
        x, mask = _pad([feats[i] for i in idx])
        y, _ = _pad([residuals[i] for i in idx])
        loss = _masked_loss(net, x, y, mask)
        optimiser.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        optimiser.step()
        weight = float(mask.sum())
        total += loss.item() * weight
        count += weight
    return total / max(count, 1.0)


def _loss(net, feats, residuals, *, recurrent: bool) -> float:
    net.eval()
    with torch.no_grad():
        if recurrent:
            x, mask = _pad(feats)
            y, _ = _pad(residuals)
            value = float(_masked_loss(net, x, y, mask))
        else:
            x = torch.as_tensor(np.concatenate(feats))
            y = torch.as_tensor(np.concatenate(residuals))
            value = float(_normalised_mse(net, net(x), y))
    net.train()
    return value


# -- the stage ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class StageBConfig:
    """Configuration of stage B.

    Parameters
    ----------
    plant:
        The plant.
    controller:
        The ideal controller driving the rollouts (stage A's SAC by default).
    delays:
        The QoS distribution ``T`` (``eq_control_estimation``).
    kinds:
        Estimators to train: ``"mlp"`` and/or ``"lstm"``.
    train_episodes, val_episodes:
        Episodes collected with the controller on the true state, for fitting and held out.
    dagger_rounds, dagger_episodes:
        Extra rounds collected with the controller acting on the estimator being trained.
    mlp_hidden, lstm_hidden:
        Network sizes.
    mlp, lstm:
        Optimiser settings of each.
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
    age_scale: float = 10.0
    compare: tuple[ComponentSpec, ...] = (ComponentSpec("none"), ComponentSpec("predictor"))
    seed: int = 0

    def __post_init__(self) -> None:
        bad = [k for k in self.kinds if k not in ("mlp", "lstm")]
        if bad or not self.kinds:
            raise ValueError(
                f"kinds must be a non-empty subset of ('mlp', 'lstm'), got {self.kinds}"
            )
        for name in ("train_episodes", "val_episodes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("dagger_rounds", "dagger_episodes"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        object.__setattr__(
            self,
            "compare",
            tuple(c if isinstance(c, ComponentSpec) else ComponentSpec(**c) for c in self.compare),
        )


def new_estimator(
    kind: str, env: Any, *, hidden: Any, age_scale: float, seed: int
) -> LearnedEstimator:
    """An untrained estimator of ``kind`` for the plant ``env``."""
    plant = env.unwrapped
    remote = plant.remote_slice
    features = EstimatorFeatures(
        obs_dim=int(np.prod(env.observation_space.shape)),
        action_dim=int(np.prod(env.action_space.shape)),
        remote_start=int(remote.start),
        remote_stop=int(remote.stop),
        age_scale=age_scale,
        use_action=kind == "lstm",
    )
    if kind == "mlp":
        return MlpEstimator.create(features, hidden=tuple(hidden), seed=seed)
    return LstmEstimator.create(features, hidden=int(hidden), seed=seed)


def position_slice(env: Any) -> slice | None:
    """The ``object_pos`` slice of a plant's layout (``None`` without one)."""
    layout = getattr(env.unwrapped, "observation_layout", None) or {}
    return layout.get("object_pos")


def _cached(path: Path, make: Any) -> EpisodeData:
    if path.is_file():
        return EpisodeData.load(path)
    data = make()
    data.save(path)
    return data


def train_stage_b(
    config: StageBConfig,
    *,
    out_dir: str | Path,
    work_dir: str | Path,
    resume: bool = False,
    progress: Progress = no_progress,
    command: str | None = None,
) -> dict[str, Any]:
    """Collect data, fit the estimators, compare them on held-out data; write ``out_dir``.

    ``out_dir`` receives ``<kind>.pt`` per estimator, ``training.json`` (settings, data and
    wall time, the held-out MSE table) and ``curve.json`` (loss per epoch). Collected data are
    cached in ``work_dir``; with ``resume`` a finished round or fit is not redone.
    """

    out_dir, work_dir = Path(out_dir), Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    if not resume:
        for old in work_dir.glob("*"):
            if old.suffix in (".npz", ".pt") or old.name == "curves.json":
                old.unlink()
    started = time.perf_counter()
    probe = make_plant(config.plant)
    controller = build("controller", config.controller, probe)
    qos = RandomQos(config.delays)
    remote = probe.unwrapped.remote_slice
    position = position_slice(probe)

    def collect(name: str, episodes: int, seed: int, behaviour: Any = None) -> EpisodeData:
        return _cached(
            work_dir / f"{name}.npz",
            lambda: collect_episodes(
                config.plant, controller, qos, episodes=episodes, seed=seed, behaviour=behaviour
            ),
        )

    t0 = time.perf_counter()
    train0 = collect("train_round0", config.train_episodes, config.seed + 10)
    val = collect("val", config.val_episodes, config.seed + 20)
    collect_s = time.perf_counter() - t0
    curves_path = work_dir / "curves.json"
    curves: dict[str, list[dict[str, float]]] = (
        json.loads(curves_path.read_text()) if resume and curves_path.is_file() else {}
    )
    results: dict[str, dict[str, float]] = {}
    steps = {"train_round0": train0.steps, "val": val.steps}
    for kind in config.kinds:
        hidden = config.mlp_hidden if kind == "mlp" else config.lstm_hidden
        settings = config.mlp if kind == "mlp" else config.lstm
        ckpt = work_dir / f"{kind}_round{config.dagger_rounds}.pt"
        if resume and ckpt.is_file():
            estimator = load_estimator(ckpt)
        else:
            estimator = new_estimator(
                kind, probe, hidden=hidden, age_scale=config.age_scale, seed=config.seed
            )
            data = EpisodeData().extend(train0)
            curves.setdefault(kind, [])
            for round_ in range(config.dagger_rounds + 1):
                if round_ > 0:
                    t0 = time.perf_counter()
                    more = collect(
                        f"train_{kind}_round{round_}",
                        config.dagger_episodes,
                        config.seed + 100 * round_ + (1 if kind == "lstm" else 0),
                        behaviour=estimator,
                    )
                    collect_s += time.perf_counter() - t0
                    steps[f"train_{kind}_round{round_}"] = more.steps
                    data.extend(more)
                round_ckpt = work_dir / f"{kind}_round{round_}.pt"
                if resume and round_ckpt.is_file():
                    estimator = load_estimator(round_ckpt)
                    continue
                curve = fit_estimator(
                    estimator,
                    data,
                    val,
                    settings,
                    seed=config.seed + round_,
                    fit_normalisation=round_ == 0,
                    progress=progress,
                    description=f"stage B: {kind} round {round_}",
                )
                curves[kind].extend({"round": round_, **p} for p in curve)
                estimator.save(round_ckpt)
                write_json(curves_path, curves)
        out_dir.mkdir(parents=True, exist_ok=True)
        estimator.save(out_dir / f"{kind}.pt")
        results[kind] = estimator_mse(estimator, val, remote=remote, position=position)
    for spec in config.compare:
        try:
            baseline = build("estimator", spec, probe)
        except ImportError as exc:  # a part not written yet: report, do not fail the stage
            results[spec.kind] = {"error": f"unavailable: {exc}"}
            continue
        results[spec.kind] = estimator_mse(baseline, val, remote=remote, position=position)
    wall = time.perf_counter() - started
    meta = {
        "stage": "b",
        "command": command,
        "seed": config.seed,
        "env_steps": int(sum(steps.values())),
        "env_steps_by_dataset": steps,
        "collection_wall_time_s": round(collect_s, 1),
        "wall_time_s": round(wall, 1),
        "held_out_mse": results,
        "held_out_episodes": len(val),
        "package_version": package_version(),
        "config": to_mapping(config),
    }
    write_json(out_dir / "training.json", meta)
    write_json(out_dir / "curve.json", curves)
    probe.close()
    return {"env_steps": meta["env_steps"], "wall_time_s": meta["wall_time_s"], "mse": results}
