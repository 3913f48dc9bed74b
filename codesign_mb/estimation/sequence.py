"""The Gaussian sequence estimator of stage B (``eq_control_estimation``): a recurrent network
over what the edge delivers, with its own uncertainty.

Where :mod:`~codesign_mb.estimation.learned`'s MLP sees one networked observation and its LSTM
regresses a point, this estimator reads the whole history of the networked observation
(``y_t``, the age ``zeta_t``, the robot's own gripper and fingers) and the previous action, and
outputs a Gaussian over the object's present state: the mean ``x_hat_t = y_t + r_t`` (the remote
part, then the velocity where the packet carries none) and a diagonal variance. It is trained
by the beta-weighted Gaussian negative log-likelihood (Seitzer et al., *On the Pitfalls of
Heteroscedastic Uncertainty Estimation with Probabilistic Neural Networks*, ICLR 2022, beta =
0.5: the mean fits as well as under the MSE while the variance is calibrated), in
:mod:`codesign_mb.stages.fitting`.

It exposes ``state`` and ``covariance`` like the model-based filters (``position`` then
``velocity``; :func:`~codesign_mb.estimation.consistency.has_covariance`), so the tables report
its NEES and 95 % coverage, and a QoS policy can read its ``position_std`` as it reads the belt
IMM's. Nothing in it is a model of the belt: the inputs are the delivered observations and a
few causal transforms of them that a recurrent cell finds hard to form from raw positions
(:class:`SequenceFeatures`): whether a new packet arrived, the displacement between the last two
delivered positions per step of capture time (a finite difference, not a filter), and the
object's position relative to the gripper.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

from codesign_mb.estimation.learned import EstimatorFeatures, LearnedEstimator, _Normalised

__all__ = [
    "CELLS",
    "GaussianSequenceEstimator",
    "GaussianSequenceNet",
    "SequenceFeatures",
    "sequence_features",
]

CELLS = ("gru", "lstm")
"""Recurrent cells the sequence estimator can use."""

_LOG_VAR_RANGE = (-14.0, 6.0)  # normalised units: a std from 1e-3 to 20 training spreads


@dataclass(frozen=True)
class SequenceFeatures(EstimatorFeatures):
    """:class:`EstimatorFeatures` plus the causal transforms of the delivered history.

    ``gripper_start`` is where the gripper's position (3) starts in the plant observation
    (-1: the plant has none; the relative position is then left out). The extra features of
    step ``t``, after the base ones, are ``fresh_t`` (a packet newer than the one held at
    ``t - 1`` arrived), the held position's last jump per step of capture time
    ``(y_c - y_c') / (c - c')`` for the last two captures ``c' < c`` (kept until the next
    packet), ``(c - c') / age_scale`` and ``y_t - gripper_t``.
    """

    gripper_start: int = -1

    @property
    def extra_dim(self) -> int:
        return 1 + 3 + 1 + (3 if self.gripper_start >= 0 else 0)

    @property
    def in_dim(self) -> int:
        return super().in_dim + self.extra_dim

    def sequence(self, networked: NDArray, prev_actions: NDArray | None = None) -> NDArray:
        """Features of a whole episode ``(T, obs_dim + 1) -> (T, in_dim)`` (causal)."""
        networked = np.asarray(networked, dtype=np.float32)
        memory = _Increments()
        extras = [memory.update(self, row, t) for t, row in enumerate(networked)]
        return np.concatenate([self(networked, prev_actions), np.asarray(extras)], axis=-1)


class _Increments:
    """The running part of :class:`SequenceFeatures`: the last capture and its jump."""

    def __init__(self) -> None:
        self.capture = -np.inf
        self.position: NDArray[np.float32] | None = None
        self.rate = np.zeros(3, dtype=np.float32)
        self.gap = 0.0

    def update(self, f: SequenceFeatures, networked: NDArray, t: int) -> NDArray[np.float32]:
        y = np.asarray(networked[f.remote_start : f.remote_start + 3], dtype=np.float32)
        capture = t - float(networked[-1])
        fresh = capture > self.capture
        if fresh:
            if self.position is not None and np.isfinite(self.capture):
                self.gap = capture - self.capture
                self.rate = (y - self.position) / self.gap
            self.capture, self.position = capture, y
        parts: list[NDArray[np.float32]] = [
            np.array([float(fresh)], dtype=np.float32),
            self.rate,
            np.array([self.gap / f.age_scale], dtype=np.float32),
        ]
        if f.gripper_start >= 0:
            parts.append(y - networked[f.gripper_start : f.gripper_start + 3])
        return np.concatenate(parts).astype(np.float32)


class GaussianSequenceNet(_Normalised):
    """Features ``(batch, time, in_dim)`` -> residual mean and log variance (normalised)."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 128, cell: str = "gru") -> None:
        super().__init__(in_dim, out_dim)
        if cell not in CELLS:
            raise ValueError(f"cell must be one of {CELLS}, got {cell!r}")
        self.hidden_size, self.cell = int(hidden), cell
        self.encoder = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU())
        recurrent = nn.GRU if cell == "gru" else nn.LSTM
        self.recurrent = recurrent(hidden, hidden, batch_first=True)
        self.head = nn.Sequential(
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 2 * out_dim)
        )

    def forward(self, features: torch.Tensor, state: Any = None) -> tuple[torch.Tensor, ...]:
        """``(mean / out_std, log variance of the residual / out_std, recurrent state)``."""
        z = self.encoder((features - self.in_mean) / self.in_std)
        out, state = self.recurrent(z, state)
        mean, log_var = self.head(out).chunk(2, dim=-1)
        return mean, log_var.clamp(*_LOG_VAR_RANGE), state


class GaussianSequenceEstimator(LearnedEstimator):
    """The Gaussian sequence estimator (kind ``sequence``); see the module docstring.

    Examples
    --------
    >>> f = SequenceFeatures(obs_dim=3, action_dim=1, remote_start=0, remote_stop=3)
    >>> est = GaussianSequenceEstimator.create(f, hidden=8)
    >>> est.reset(np.array([0.0, 1.0, 2.0, 0.0])).shape, est.covariance.shape
    ((3,), (3, 3))
    """

    kind = "sequence"

    def __init__(self, net: GaussianSequenceNet, features: SequenceFeatures) -> None:
        super().__init__(net, features)
        self.features: SequenceFeatures = features
        self._state: Any = None
        self._memory = _Increments()
        self._t = 0
        self._var = np.ones(features.out_dim)
        self._output = np.zeros(features.obs_dim + features.velocity_dim)

    @classmethod
    def create(
        cls, features: SequenceFeatures, *, hidden: int = 128, cell: str = "gru", seed: int = 0
    ) -> GaussianSequenceEstimator:
        """A fresh (untrained) estimator; weights initialised from ``seed``."""
        with torch.random.fork_rng(devices=[]):  # seeded init, global RNG left untouched
            torch.manual_seed(seed)
            net = GaussianSequenceNet(features.in_dim, features.out_dim, hidden, cell)
        return cls(net, features)

    # -- what a QoS policy and the consistency columns read -------------------------------
    @property
    def state(self) -> NDArray[np.float64]:
        """The estimated entries (position, then velocity where estimated), as the filters'."""
        return self._output[self.features.target_slice].copy()

    @property
    def covariance(self) -> NDArray[np.float64]:
        """The network's (diagonal) covariance of :attr:`state`."""
        return np.diag(self._var)

    @property
    def output(self) -> NDArray[np.float64]:
        """The last estimate as the controller got it (the plant's state layout: the robot's
        own gripper and fingers, the estimated object)."""
        return self._output.copy()

    @property
    def position_std(self) -> float:
        """``sqrt(var_x + var_y)``: the lateral RMS uncertainty, as the belt IMM reports it."""
        return float(np.sqrt(self._var[0] + self._var[1]))

    # -- internals ---------------------------------------------------------------------------
    def _reset_memory(self) -> None:
        self._state, self._memory, self._t = None, _Increments(), 0

    def _estimate(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        observation = np.asarray(observation, dtype=np.float64)
        f = self.features
        extra = self._memory.update(f, observation, self._t)
        self._t += 1
        feats = np.concatenate([f(observation, self._prev_action), extra])
        net = self.net
        assert isinstance(net, GaussianSequenceNet)
        with torch.no_grad():
            mean, log_var, self._state = net(torch.as_tensor(feats)[None, None], self._state)
        scale = net.out_std.numpy().astype(np.float64)
        residual = mean.numpy().reshape(-1) * scale
        self._var = np.exp(log_var.numpy().reshape(-1).astype(np.float64)) * scale**2
        out = self._output_of(observation, residual)
        self._output = out.copy()
        return out

    def _net_config(self) -> dict[str, Any]:
        return {"hidden": self.net.hidden_size, "cell": self.net.cell}

    @classmethod
    def from_blob(cls, blob: dict[str, Any]) -> GaussianSequenceEstimator:
        """Rebuild from what :meth:`save` wrote (used by ``load_estimator``)."""
        features = SequenceFeatures(**blob["features"])
        cfg = blob["net"]
        net = GaussianSequenceNet(features.in_dim, features.out_dim, cfg["hidden"], cfg["cell"])
        net.load_state_dict(blob["state_dict"])
        return cls(net, features)


def sequence_features(base: EstimatorFeatures, gripper_start: int = -1) -> SequenceFeatures:
    """The :class:`SequenceFeatures` of ``base`` (previous action always on)."""
    fields = {**dataclasses.asdict(base), "use_action": True, "gripper_start": gripper_start}
    return SequenceFeatures(**fields)
