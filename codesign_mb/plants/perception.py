"""Perception at the edge: how the object's position the camera reports differs from the truth.

DESIGN.md's data flow, step 1: a camera frame (or its calibrated error model) gives the
perceived object position, with noise, bias and missed detections. The conveyor env asks a
:class:`PerceptionErrorModel` once per control step for the measured position; ``None`` is a
missed detection.

What a missed detection looks like downstream: the edge has no fresh measurement, so it sends
no state packet that step. The env reports ``info["perceived"] = False``; the
:class:`~codesign_mb.network.LinkObservationWrapper` then hands the link the request
``(q = 0, tau)`` (nothing to deliver), so the robot keeps what it held and the age grows, as
after a lost packet. The estimators need nothing new for that: a Kalman predictor predicts
open loop, a learned one sees a larger age. The env's own observation keeps the last perceived
position in its remote slice (the edge's last output), never a made-up value.

Models are looked up by name in the registry's ``perception`` role (the config's
``perception_model``); :class:`GaussianPerception` (``"gaussian"``) is the default. A model
calibrated from rendered camera frames plugs in by registering its factory there
(:mod:`codesign_mb.plants.kinds`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from codesign_mb.core.registry import create
from codesign_mb.plants.camera_perception import CameraPerception

if TYPE_CHECKING:
    from codesign_mb.plants.conveyor_config import ConveyorConfig

__all__ = [
    "GaussianPerception",
    "PerceptionErrorModel",
    "camera_perception",
    "make_perception",
    "reset_perception",
]


@runtime_checkable
class PerceptionErrorModel(Protocol):
    """The edge's measurement of the object's position.

    ``sample(position, rng)`` takes the true centre (m, world frame, shape ``(3,)``) and the
    env's generator and returns the measured centre (a new array) or ``None`` for a missed
    detection. A model with per-episode state (a calibration bias) may also define
    ``reset(rng)``; the env calls it at every episode start (:func:`reset_perception`).
    """

    def sample(
        self, position: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64] | None: ...


def reset_perception(model: PerceptionErrorModel, rng: np.random.Generator) -> None:
    """Start an episode of ``model``: call its ``reset(rng)`` if it has one."""
    reset = getattr(model, "reset", None)
    if callable(reset):
        reset(rng)


class GaussianPerception:
    """Gaussian noise, a bias and i.i.d. missed detections (the default error model).

    ``z = p + b + n`` with ``n ~ N(0, noise_std_m^2 I)`` drawn per step and
    ``b = bias_m + N(0, bias_std_m^2 I)`` drawn per episode (:meth:`reset`); with probability
    ``miss_probability`` per step there is no measurement (``None``). Draws from ``rng`` only
    what is switched on, in the order: miss, noise (the paper's noise-only perception draws
    exactly ``rng.normal(0, noise_std_m, 3)`` per step).

    Parameters
    ----------
    noise_std_m:
        Per-axis standard deviation of the measurement noise (m).
    bias_m:
        Fixed bias (m, shape ``(3,)``).
    bias_std_m:
        Per-axis standard deviation of the per-episode random bias (m).
    miss_probability:
        Probability of a missed detection per step, in [0, 1].
    """

    def __init__(
        self,
        noise_std_m: float = 0.0,
        bias_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        bias_std_m: float = 0.0,
        miss_probability: float = 0.0,
    ) -> None:
        for name, value in (
            ("noise_std_m", noise_std_m),
            ("bias_std_m", bias_std_m),
            ("miss_probability", miss_probability),
        ):
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0, got {value!r}")
        if miss_probability > 1:
            raise ValueError(f"miss_probability must be <= 1, got {miss_probability!r}")
        self.noise_std_m = float(noise_std_m)
        self.bias_m = np.array(bias_m, dtype=float).reshape(3)
        self.bias_std_m = float(bias_std_m)
        self.miss_probability = float(miss_probability)
        self.bias = self.bias_m.copy()
        """This episode's bias ``b`` (m)."""

    @classmethod
    def from_config(cls, config: ConveyorConfig) -> GaussianPerception:
        """The model of a conveyor config's ``perception_*`` fields."""
        return cls(
            noise_std_m=config.perception_noise_std_m,
            bias_m=config.perception_bias_m,
            bias_std_m=config.perception_bias_std_m,
            miss_probability=config.perception_miss_probability,
        )

    @property
    def exact(self) -> bool:
        """Whether the model reports the true position always (the paper's perception)."""
        return (
            self.noise_std_m == 0
            and self.bias_std_m == 0
            and self.miss_probability == 0
            and not self.bias_m.any()
        )

    def reset(self, rng: np.random.Generator) -> None:
        """Draw this episode's bias (uses ``rng`` only if ``bias_std_m > 0``)."""
        self.bias = self.bias_m.copy()
        if self.bias_std_m > 0:
            self.bias += rng.normal(0.0, self.bias_std_m, 3)

    def sample(
        self, position: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64] | None:
        if self.miss_probability > 0 and rng.random() < self.miss_probability:
            return None
        measured = np.asarray(position, dtype=float) + self.bias
        if self.noise_std_m > 0:
            measured += rng.normal(0.0, self.noise_std_m, 3)
        return measured


def camera_perception(config: ConveyorConfig) -> PerceptionErrorModel:
    """The error model calibrated from the edge camera's rendered frames (perception kind
    ``camera``, :mod:`codesign_mb.plants.kinds`)."""
    return CameraPerception.load(config.object)


def make_perception(config: ConveyorConfig) -> PerceptionErrorModel:
    """The perception error model a conveyor config names."""
    return create("perception", config.perception_model, config)
