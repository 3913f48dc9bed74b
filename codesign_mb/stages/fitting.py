"""Fitting the learned estimators (MLP, LSTM) to recorded episodes: ``eq_control_estimation``.

The networks of :mod:`codesign_mb.estimation.learned` are fitted in torch to the residual
``x_t - y_t`` (and, where the packet carries no velocity, to the object's true velocity) of
:class:`~codesign_mb.stages.episodes.EpisodeData` (MSE in units of its training spread);
stages B and D use it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from codesign_mb.estimation.learned import (
    EstimatorFeatures,
    LearnedEstimator,
    LstmEstimator,
    MlpEstimator,
)
from codesign_mb.estimation.sequence import (
    GaussianSequenceEstimator,
    GaussianSequenceNet,
    SequenceFeatures,
    sequence_features,
)
from codesign_mb.stages.episodes import EpisodeData, estimates_velocity
from codesign_mb.stages.training import (
    BUFFER_CAP,
    EPOCHS_CAP,
    Progress,
    no_progress,
    require_at_least,
)

__all__ = ["EstimatorTraining", "fit_estimator", "new_estimator"]


@dataclass(frozen=True)
class EstimatorTraining:
    """Optimiser settings for one estimator fit (Adam on the normalised MSE)."""

    epochs: int = 40
    learning_rate: float = 1e-3
    batch_size: int = 256
    sequence_batch_size: int = 16
    weight_decay: float = 0.0
    cosine_decay: bool = False  # anneal the learning rate to a tenth along the epochs

    def __post_init__(self) -> None:
        require_at_least(self, 1, "epochs", cap=EPOCHS_CAP)
        require_at_least(self, 1, "batch_size", "sequence_batch_size", cap=BUFFER_CAP)
        if self.learning_rate <= 0:
            raise ValueError(f"learning_rate must be > 0, got {self.learning_rate}")


def _arrays(estimator: LearnedEstimator, data: EpisodeData) -> tuple[list[np.ndarray], list]:
    f = estimator.features
    featurise = f.sequence if isinstance(f, SequenceFeatures) else f
    feats, residuals = [], []
    for nets, prevs, truth in zip(data.networked, data.prev_actions, data.truth, strict=True):
        feats.append(featurise(nets, prevs))
        residuals.append(truth - f.baseline(nets))
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
    recurrent = isinstance(estimator, (LstmEstimator, GaussianSequenceEstimator))
    gaussian = isinstance(estimator, GaussianSequenceEstimator)
    val_arrays = _arrays(estimator, val) if val is not None and len(val) else None
    schedule = (
        torch.optim.lr_scheduler.CosineAnnealingLR(
            optimiser, settings.epochs, eta_min=settings.learning_rate / 10
        )
        if settings.cosine_decay
        else None
    )
    curve = []
    net.train()
    for epoch in progress(range(settings.epochs), total=settings.epochs, description=description):
        if recurrent:
            loss = _sequence_epoch(net, optimiser, feats, residuals, settings, rng)
        else:
            loss = _mlp_epoch(net, optimiser, feats, residuals, settings, gen)
        if schedule is not None:
            schedule.step()
        point = {"epoch": epoch + 1, "train_loss": loss}
        if val_arrays is not None:
            point["val_loss"] = _loss(net, *val_arrays, recurrent=recurrent)
            if gaussian:
                point["val_rmse"] = _loss(net, *val_arrays, recurrent=True, metric="rmse")
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


NLL_BETA = 0.5
"""The beta of the beta-NLL (Seitzer et al., ICLR 2022): each step's Gaussian NLL weighted by
its (detached) variance to the beta, so the mean is not neglected where the variance is large."""


def _masked_loss(net, x, y, mask, metric: str = "loss") -> torch.Tensor:
    """The masked mean over steps: the normalised MSE (point nets) or the beta-NLL (Gaussian
    nets); ``metric="rmse"``: the RMS error of the first three entries in physical units."""
    gaussian = isinstance(net, GaussianSequenceNet)
    out = net(x)
    if metric == "rmse":
        err = ((out[0] * net.out_std if gaussian else out[0]) - y)[..., :3]
        return ((err**2).sum(-1) * mask).sum().div(mask.sum()).sqrt()
    if gaussian:  # beta-NLL in units of the training spread (the net's mean is normalised)
        mean, log_var = out[0], out[1]
        var = log_var.exp()
        residual = y / net.out_std - mean
        per_step = 0.5 * (log_var + residual**2 / var) * var.detach() ** NLL_BETA
    else:  # point estimate: the MSE of eq_control_estimation
        per_step = ((out[0] - y) / net.out_std) ** 2
    return (per_step.mean(-1) * mask).sum() / mask.sum()


def _sequence_epoch(net, optimiser, feats, residuals, settings, rng) -> float:
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


def _loss(net, feats, residuals, *, recurrent: bool, metric: str = "loss") -> float:
    net.eval()
    with torch.no_grad():
        if recurrent:
            x, mask = _pad(feats)
            y, _ = _pad(residuals)
            value = float(_masked_loss(net, x, y, mask, metric))
        else:
            x = torch.as_tensor(np.concatenate(feats))
            y = torch.as_tensor(np.concatenate(residuals))
            value = float(_normalised_mse(net, net(x), y))
    net.train()
    return value


def new_estimator(
    kind: str, env: Any, *, hidden: Any, age_scale: float, seed: int, cell: str = "gru"
) -> LearnedEstimator:
    """An untrained estimator of ``kind`` for the plant ``env``.

    Where the plant's ``state_layout`` has an ``object_vel`` its observation lacks (the packet
    carries the position only), the estimator also estimates the velocity
    (:func:`estimates_velocity`). ``cell`` is the recurrent cell of kind ``sequence``.
    """
    plant = env.unwrapped
    remote = plant.remote_slice
    features = EstimatorFeatures(
        obs_dim=int(np.prod(env.observation_space.shape)),
        action_dim=int(np.prod(env.action_space.shape)),
        remote_start=int(remote.start),
        remote_stop=int(remote.stop),
        age_scale=age_scale,
        use_action=kind == "lstm",
        output_velocity=estimates_velocity(env),
    )
    if kind == "mlp":
        return MlpEstimator.create(features, hidden=tuple(hidden), seed=seed)
    if kind == "sequence":
        gripper = (getattr(plant, "observation_layout", None) or {}).get("gripper_pos")
        seq = sequence_features(features, -1 if gripper is None else int(gripper.start))
        return GaussianSequenceEstimator.create(seq, hidden=int(hidden), cell=cell, seed=seed)
    return LstmEstimator.create(features, hidden=int(hidden), seed=seed)
