"""Edge perception's error model, calibrated from the camera path (:mod:`codesign_mb.robot.camera`).

Rendering a frame and detecting the object costs milliseconds; mass evaluations instead draw
the perceived position from :class:`CameraPerception`, whose parameters
(:class:`PerceptionCalibration`) were measured on the camera path by
``codesign calibrate-perception`` (:mod:`codesign_mb.studies.perception`) and are shipped as
``models/perception/edge_<object>.json``. The model reproduces what the detector does:

- **out of view**: no detection when the object's centre is outside the camera's footprint
  on the belt (``view_low`` .. ``view_high``, in x and y);
- **missed detections**: with probability ``miss_rate`` when the gripper is far, and with the
  miss rate of the cell of the object's horizontal offset from the gripper
  (``occlusion_miss``, on a grid of ``occlusion_cell_m`` cells, ``dx, dy`` in
  ``+-occlusion_extent_m``) when the gripper position is given (the arm hides the object);
- **parallax**: the detector back-projects onto the plane of a resting object's centre
  (``plane_z``), so an object above it (lifted) is seen along the camera's ray, scaled away
  from the camera's nadir: exact geometry, from ``camera_position``;
- **noise and bias** on x and y: ``bias + bias_gradient @ (xy - view_centre)`` (the blob's
  centroid moves with the perspective across the view) plus independent Gaussian noise of
  standard deviation ``std``; z is the plane's height (the detector's output).

Examples
--------
>>> model = CameraPerception.load("cube")
>>> rng = np.random.default_rng(0)
>>> measured = model.sample(np.array([0.5, -0.3, 0.0825]), rng)
>>> measured is None or bool(abs(measured[1] + 0.3) < 0.05)
True
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from codesign_mb.robot.assets import asset_path

__all__ = ["LIFTED_M", "CameraPerception", "PerceptionCalibration", "calibration_asset"]

LIFTED_M = 0.01
"""An object more than this above its resting height is lifted (in the gripper)."""


def calibration_asset(object_kind: str) -> str:
    """Package-data path of the shipped calibration for ``object_kind``."""
    return f"perception/edge_{object_kind}.json"


@dataclass(frozen=True)
class PerceptionCalibration:
    """Measured error statistics of the edge camera path (lengths in m).

    See the module docstring for how each field enters :class:`CameraPerception`.
    """

    object_kind: str
    plane_z: float
    camera_position: tuple[float, float, float]
    view_low: tuple[float, float]
    view_high: tuple[float, float]
    view_centre: tuple[float, float]
    bias: tuple[float, float]
    bias_gradient: tuple[tuple[float, float], tuple[float, float]]
    std: tuple[float, float]
    miss_rate: float
    lifted_miss_rate: float
    occlusion_cell_m: float
    occlusion_extent_m: float
    occlusion_miss: tuple[tuple[float, ...], ...]
    provenance: dict[str, Any] = field(default_factory=dict)
    """How it was measured: command, seeds, frame counts, measured summary."""

    def __post_init__(self) -> None:
        for name in ("miss_rate", "lifted_miss_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")
        if min(self.std) < 0:
            raise ValueError(f"std must be >= 0, got {self.std!r}")
        grid = np.asarray(self.occlusion_miss, dtype=float)
        n = round(2 * self.occlusion_extent_m / self.occlusion_cell_m)
        if grid.shape != (n, n) or grid.min() < 0 or grid.max() > 1:
            raise ValueError(
                f"occlusion_miss must be a {n}x{n} grid of probabilities, got shape {grid.shape}"
            )

    def to_json(self, path: str | Path) -> None:
        """Write as JSON (the shipped file's format)."""
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(asdict(self), indent=1) + "\n")

    @classmethod
    def from_json(cls, path: str | Path) -> PerceptionCalibration:
        """Read a file written by :meth:`to_json`."""
        raw = json.loads(Path(path).read_text())

        def tuples(value: Any) -> Any:
            return tuple(tuples(v) for v in value) if isinstance(value, list) else value

        return cls(**{k: v if k == "provenance" else tuples(v) for k, v in raw.items()})


class CameraPerception:
    """Draw the edge detector's output for a true object position (see the module docstring).

    Parameters
    ----------
    calibration:
        The measured statistics.
    """

    def __init__(self, calibration: PerceptionCalibration) -> None:
        c = calibration
        self.calibration = c
        self._low = np.asarray(c.view_low, dtype=float)
        self._high = np.asarray(c.view_high, dtype=float)
        self._centre = np.asarray(c.view_centre, dtype=float)
        self._bias = np.asarray(c.bias, dtype=float)
        self._gradient = np.asarray(c.bias_gradient, dtype=float)
        self._std = np.asarray(c.std, dtype=float)
        self._camera = np.asarray(c.camera_position, dtype=float)
        self._grid = np.asarray(c.occlusion_miss, dtype=float)

    @classmethod
    def load(cls, object_kind: str = "cube") -> CameraPerception:
        """The model of the shipped calibration of ``object_kind``."""
        return cls(PerceptionCalibration.from_json(asset_path(calibration_asset(object_kind))))

    def miss_probability(
        self, position: ArrayLike, gripper_position: ArrayLike | None = None
    ) -> float:
        """Probability of no detection at ``position`` (1 out of view)."""
        p = np.asarray(position, dtype=float)
        if np.any(p[:2] < self._low) or np.any(p[:2] > self._high):
            return 1.0
        c = self.calibration
        if p[2] > c.plane_z + LIFTED_M:
            return c.lifted_miss_rate
        if gripper_position is None:
            return c.miss_rate
        offset = p[:2] - np.asarray(gripper_position, dtype=float)[:2]
        if np.any(np.abs(offset) >= c.occlusion_extent_m):
            return c.miss_rate
        i, j = np.floor((offset + c.occlusion_extent_m) / c.occlusion_cell_m).astype(int)
        return float(self._grid[i, j])

    def sample(
        self,
        position: ArrayLike,
        rng: np.random.Generator,
        gripper_position: ArrayLike | None = None,
    ) -> NDArray[np.float64] | None:
        """The perceived position (3,) of an object at ``position`` (3,), or None if missed.

        Parameters
        ----------
        position:
            True object centre (m, world frame).
        rng:
            The caller's generator (two or three draws per call).
        gripper_position:
            The TCP position (m), for occlusion by the arm; None: the gripper is far.
        """
        p = np.asarray(position, dtype=float)
        miss = self.miss_probability(p, gripper_position)
        if miss >= 1.0 or (miss > 0.0 and rng.random() < miss):
            return None
        c = self.calibration
        height = self._camera[2] - c.plane_z
        depth = self._camera[2] - p[2]
        seen = self._camera[:2] + (p[:2] - self._camera[:2]) * (height / depth)
        error = self._bias + self._gradient @ (p[:2] - self._centre)
        xy = seen + error + self._std * rng.standard_normal(2)
        return np.array([xy[0], xy[1], c.plane_z])

    def describe(self) -> dict[str, float]:
        """Headline figures in mm and as a rate (for reports)."""
        c = self.calibration
        return {
            "bias_x_mm": 1e3 * c.bias[0],
            "bias_y_mm": 1e3 * c.bias[1],
            "std_x_mm": 1e3 * c.std[0],
            "std_y_mm": 1e3 * c.std[1],
            "miss_rate": c.miss_rate,
            "view_y_mm": 1e3 * (c.view_high[1] - c.view_low[1]),
            "max_bias_across_view_mm": 1e3
            * math.hypot(*(np.abs(self._gradient) @ ((self._high - self._low) / 2))),
        }
