"""Learned QoS-aware state estimators of stage B (``eq_control_estimation``): MLP and LSTM.

Both read the networked observation of :class:`~codesign_mb.network.LinkObservationWrapper`
(the plant observation whose remote part is ``y_t = x_{t - zeta_t}``, then the age
``zeta_t``) and predict the *current* remote state ``x_t``. They output the plant-layout
observation with the remote part replaced by the estimate, so ``controller.act(estimate)``
is the QoS-aware controller of ``eq_c_pol2``.

The networks predict a residual: ``x_hat_t = y_t + s * f(normalise(features))``, where the
features are the full networked observation with the age scaled by ``age_scale`` (and, for
the LSTM, the previous action), and ``s`` is the per-dimension spread of the training
residuals. With no information (``f = 0``) the estimate is the stale observation itself, the
"no estimator" baseline.

When the packet carries the object's position only (the ``realistic`` scenario, whose
plant's ``state_layout`` puts ``object_vel`` after the observation), an estimator built with
``output_velocity`` also estimates the object's velocity and appends it there, as the
model-based :class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor` does: its
output has the plant's state layout, so a controller gets an estimated velocity.

* :class:`MlpEstimator` is the paper's ``pi_e(y_t, zeta_t)``: memoryless.
* :class:`LstmEstimator` runs an LSTM over the whole history of features.

Training lives in :mod:`codesign_mb.stages.stage_b`; this module holds the networks, the
feature map shared by training and inference, and save/load (a single ``.pt`` file loadable
with ``torch.load(weights_only=True)``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

from codesign_mb.core.checkpoints import reading_checkpoint
from codesign_mb.core.results import atomic_write

__all__ = [
    "EstimatorFeatures",
    "LearnedEstimator",
    "LstmEstimator",
    "LstmEstimatorNet",
    "MlpEstimator",
    "MlpEstimatorNet",
    "load_estimator",
]


@dataclass(frozen=True)
class EstimatorFeatures:
    """The map from networked observations (and actions) to network inputs.

    Parameters
    ----------
    obs_dim:
        Length of the *plant* observation (the networked one has one more entry, the age).
    action_dim:
        Length of the action vector.
    remote_start, remote_stop:
        The remote part of the plant observation, ``obs[remote_start:remote_stop]``.
    age_scale:
        The age enters the network as ``zeta / age_scale``.
    use_action:
        Append the previous action ``u_{t-1}`` (zeros at ``t = 0``) to the features.
    output_velocity:
        Also estimate the object's velocity (3 entries, not in the observation) and append it
        to the output, where the plant's ``state_layout`` puts ``object_vel``.
    """

    obs_dim: int
    action_dim: int
    remote_start: int
    remote_stop: int
    age_scale: float = 10.0
    use_action: bool = False
    output_velocity: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.remote_start < self.remote_stop <= self.obs_dim:
            raise ValueError(
                f"remote part [{self.remote_start}, {self.remote_stop}) must lie inside the "
                f"observation of length {self.obs_dim}"
            )
        if self.age_scale <= 0:
            raise ValueError(f"age_scale must be > 0, got {self.age_scale}")
        if self.output_velocity and self.remote_stop != self.obs_dim:
            raise ValueError("output_velocity needs the remote part at the end of the observation")

    @property
    def remote_slice(self) -> slice:
        return slice(self.remote_start, self.remote_stop)

    @property
    def remote_dim(self) -> int:
        return self.remote_stop - self.remote_start

    @property
    def velocity_dim(self) -> int:
        """Entries appended to the output: the estimated velocity (0 or 3)."""
        return 3 if self.output_velocity else 0

    @property
    def out_dim(self) -> int:
        """Entries the network predicts: the remote part's residual, then the velocity."""
        return self.remote_dim + self.velocity_dim

    @property
    def target_slice(self) -> slice:
        """Where the estimated entries sit in the output: the remote part and, with
        ``output_velocity``, the appended velocity (contiguous: the remote part ends the
        observation)."""
        return slice(self.remote_start, self.remote_stop + self.velocity_dim)

    def baseline(self, networked: NDArray) -> NDArray:
        """What the residual is added to: ``y_t``, and zeros for the velocity (batch-wise)."""
        networked = np.asarray(networked, dtype=np.float32)
        y = networked[..., self.remote_slice]
        if not self.velocity_dim:
            return y
        zeros = np.zeros((*y.shape[:-1], self.velocity_dim), dtype=np.float32)
        return np.concatenate([y, zeros], axis=-1)

    @property
    def in_dim(self) -> int:
        return self.obs_dim + 1 + (self.action_dim if self.use_action else 0)

    def __call__(self, networked: NDArray, prev_action: NDArray | None = None) -> NDArray:
        """Features of one step ``(obs_dim + 1,)`` or of a batch ``(..., obs_dim + 1)``.

        ``prev_action`` has the matching leading shape, or is ``None`` (zeros).
        """
        networked = np.asarray(networked, dtype=np.float32)
        if networked.shape[-1] != self.obs_dim + 1:
            raise ValueError(
                f"networked observation must have {self.obs_dim + 1} entries (plant observation "
                f"+ age), got {networked.shape[-1]}: the estimator was trained on another plant "
                "(the shipped checkpoints: the paper scenario's; `codesign train --scenario "
                "NAME` trains for another)"
            )
        feats = networked.copy()
        feats[..., -1] = feats[..., -1] / self.age_scale
        if not self.use_action:
            return feats
        if prev_action is None:
            prev_action = np.zeros((*networked.shape[:-1], self.action_dim), dtype=np.float32)
        prev_action = np.asarray(prev_action, dtype=np.float32)
        return np.concatenate([feats, prev_action], axis=-1)


class _Normalised(nn.Module):
    """Input standardisation and output scaling held as buffers (saved with the weights)."""

    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__()
        self.in_mean: torch.Tensor
        self.in_std: torch.Tensor
        self.out_std: torch.Tensor
        self.register_buffer("in_mean", torch.zeros(in_dim))
        self.register_buffer("in_std", torch.ones(in_dim))
        self.register_buffer("out_std", torch.ones(out_dim))

    def set_normalisation(
        self, inputs: NDArray[np.float32], residuals: NDArray[np.float32], floor: float = 1e-3
    ) -> None:
        """Fit the input mean/std and the residual spread on training data (2-D arrays)."""
        x = torch.as_tensor(np.asarray(inputs, dtype=np.float32))
        r = torch.as_tensor(np.asarray(residuals, dtype=np.float32))
        self.in_mean.copy_(x.mean(0))
        self.in_std.copy_(x.std(0).clamp_min(floor))
        self.out_std.copy_(r.pow(2).mean(0).sqrt().clamp_min(floor))


class MlpEstimatorNet(_Normalised):
    """``f(features) -> residual / out_std``: a ReLU MLP over one step's features."""

    def __init__(self, in_dim: int, out_dim: int, hidden: tuple[int, ...] = (128, 128)) -> None:
        super().__init__(in_dim, out_dim)
        self.hidden = tuple(int(h) for h in hidden)
        layers: list[nn.Module] = []
        width = in_dim
        for h in self.hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        layers.append(nn.Linear(width, out_dim))
        self.body = nn.Sequential(*layers)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Residual (in physical units) for features of shape ``(..., in_dim)``."""
        return self.body((features - self.in_mean) / self.in_std) * self.out_std


class LstmEstimatorNet(_Normalised):
    """``f(features_0..t) -> residual_t``: a linear encoder, an LSTM and a linear head."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 64, layers: int = 1) -> None:
        super().__init__(in_dim, out_dim)
        self.hidden_size = int(hidden)
        self.num_layers = int(layers)
        self.encoder = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU())
        self.lstm = nn.LSTM(hidden, hidden, num_layers=layers, batch_first=True)
        self.head = nn.Linear(hidden, out_dim)

    def forward(
        self,
        features: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """Residuals for a batch of sequences ``(batch, time, in_dim)`` and the final state."""
        z = self.encoder((features - self.in_mean) / self.in_std)
        out, state = self.lstm(z, state)
        return self.head(out) * self.out_std, state


class LearnedEstimator:
    """Common part of the learned estimators: features, residual, output layout, save/load."""

    kind: ClassVar[str] = ""

    def __init__(self, net: nn.Module, features: EstimatorFeatures) -> None:
        self.net = net.eval()
        self.features = features
        self._prev_action: NDArray[np.float32] | None = None

    # -- Estimator protocol -------------------------------------------------------------
    def reset(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        self._prev_action = None
        self._reset_memory()
        return self._estimate(observation)

    def estimate(
        self, observation: NDArray[np.float64], action: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        self._prev_action = np.asarray(action, dtype=np.float32).reshape(-1)
        return self._estimate(observation)

    # -- internals -------------------------------------------------------------------------
    def _reset_memory(self) -> None:
        return None

    def _residual(self, feats: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _estimate(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        observation = np.asarray(observation, dtype=np.float64)
        feats = self.features(observation, self._prev_action)
        with torch.no_grad():
            residual = self._residual(torch.as_tensor(feats)[None]).numpy().reshape(-1)
        return self._output_of(observation, residual)

    def _output_of(
        self, observation: NDArray[np.float64], residual: NDArray[Any]
    ) -> NDArray[np.float64]:
        """The plant's state layout: the networked observation (its age dropped), the velocity
        slot appended where estimated, the estimated entries moved by ``residual``."""
        f = self.features
        out = observation[:-1].copy()
        if f.velocity_dim:  # the velocity slot of the state layout, after the observation
            out = np.concatenate([out, np.zeros(f.velocity_dim)])
        out[f.target_slice] += residual
        return out

    def _net_config(self) -> dict[str, Any]:
        raise NotImplementedError

    def save(self, path: str | Path) -> Path:
        """Write the estimator to one ``.pt`` file (atomically) and return its path."""

        path = Path(path)
        blob = {
            "kind": self.kind,
            "features": dataclasses.asdict(self.features),
            "net": self._net_config(),
            "state_dict": self.net.state_dict(),
        }
        with atomic_write(path) as fh:
            torch.save(blob, fh)
        return path

    def load_state_from(self, other: LearnedEstimator) -> None:
        """Copy another estimator's weights (same architecture) into this one."""
        self.net.load_state_dict(other.net.state_dict())


class MlpEstimator(LearnedEstimator):
    """The paper's MLP estimator ``pi_e(y_t, zeta_t)`` (memoryless).

    Examples
    --------
    >>> f = EstimatorFeatures(obs_dim=3, action_dim=1, remote_start=1, remote_stop=3)
    >>> est = MlpEstimator.create(f, hidden=(8,))
    >>> est.reset(np.array([0.0, 1.0, 2.0, 0.0])).shape
    (3,)
    """

    kind = "mlp"

    @classmethod
    def create(
        cls, features: EstimatorFeatures, *, hidden: tuple[int, ...] = (128, 128), seed: int = 0
    ) -> MlpEstimator:
        """A fresh (untrained) estimator; weights initialised from ``seed``."""
        with torch.random.fork_rng(devices=[]):  # seeded init, global RNG left untouched
            torch.manual_seed(seed)
            net = MlpEstimatorNet(features.in_dim, features.out_dim, hidden)
        return cls(net, features)

    def _residual(self, feats: torch.Tensor) -> torch.Tensor:
        return self.net(feats)

    def _net_config(self) -> dict[str, Any]:
        assert isinstance(self.net, MlpEstimatorNet)
        return {"hidden": list(self.net.hidden)}


class LstmEstimator(LearnedEstimator):
    """An LSTM estimator over the history of features (and previous actions)."""

    kind = "lstm"

    def __init__(self, net: LstmEstimatorNet, features: EstimatorFeatures) -> None:
        super().__init__(net, features)
        self._state: tuple[torch.Tensor, torch.Tensor] | None = None

    @classmethod
    def create(
        cls, features: EstimatorFeatures, *, hidden: int = 64, layers: int = 1, seed: int = 0
    ) -> LstmEstimator:
        """A fresh (untrained) estimator; weights initialised from ``seed``."""
        with torch.random.fork_rng(devices=[]):  # seeded init, global RNG left untouched
            torch.manual_seed(seed)
            net = LstmEstimatorNet(features.in_dim, features.out_dim, hidden, layers)
        return cls(net, features)

    def _reset_memory(self) -> None:
        self._state = None

    def _residual(self, feats: torch.Tensor) -> torch.Tensor:
        out, self._state = self.net(feats[:, None, :], self._state)
        return out[:, -1]

    def _net_config(self) -> dict[str, Any]:
        return {"hidden": self.net.hidden_size, "layers": self.net.num_layers}


def load_estimator(path: str | Path) -> LearnedEstimator:
    """Load an estimator written by :meth:`LearnedEstimator.save` (MLP, LSTM or sequence)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(
            f"estimator checkpoint {str(path)!r} does not exist; train one with `codesign train b`"
        )
    with reading_checkpoint(path, remedy="train it again with `codesign train b`"):
        blob = torch.load(path, map_location="cpu", weights_only=True)
        kind = blob.get("kind")
        if kind == "sequence":  # its module builds on this one: imported here, not above
            from codesign_mb.estimation.sequence import GaussianSequenceEstimator

            return GaussianSequenceEstimator.from_blob(blob)
        if kind not in ("mlp", "lstm"):
            raise ValueError(f"it holds an unknown estimator kind {kind!r}")
        features = EstimatorFeatures(**blob["features"])
        cls: type[LearnedEstimator] = MlpEstimator if kind == "mlp" else LstmEstimator
        net_cfg = blob["net"]
        if kind == "mlp":
            net: nn.Module = MlpEstimatorNet(
                features.in_dim, features.out_dim, tuple(net_cfg["hidden"])
            )
        else:
            net = LstmEstimatorNet(
                features.in_dim, features.out_dim, net_cfg["hidden"], net_cfg["layers"]
            )
        net.load_state_dict(blob["state_dict"])
    return cls(net, features)
