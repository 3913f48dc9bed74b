"""The edge camera and its detector: an RGB frame of the belt -> the object's position.

A fixed camera (``edge`` in ``models/scene_conveyor.xml``) looks straight down at the pick zone.
Each control step the edge renders its frame (headless, :mod:`codesign_mb.robot.render`), adds
seeded sensor noise, and locates the object:

1. **colour segmentation**: the object's colour is known from the scene; a pixel belongs to
   the object when its hue is close to the object's and it is saturated and bright enough
   (:func:`segment_colour`);
2. **centroid** of the largest connected blob of those pixels (pixel centres at ``i + 0.5``);
3. **back-projection**: the pixel's ray, from the camera's pose and field of view read from the
   ``MjModel``, is intersected with the horizontal plane of the object's centre when it lies on
   the belt (``BELT_SURFACE_Z`` + half height).

A detection is *missed* when fewer than ``min_pixels`` pixels match (occluded by the arm, out of
view) or when the blob touches the frame's border (truncated, its centroid would be biased).
The frame is sent raw (uint8 RGB, ``width * height * 3`` bytes): at the camera's 120 x 37
pixels that is 13,320 B, within the paper's 13,500 B uplink frame (:data:`FRAME_BUDGET_BYTES`).

Examples
--------
>>> from codesign_mb.robot.scene import build_scene
>>> camera = PinholeCamera.from_model(build_scene().model)
>>> camera.width, camera.height, camera.frame_bytes
(120, 37, 13320)
>>> pixel = camera.project([[0.5, 0.0, 0.0825]])
>>> bool(np.allclose(pixel, [[60.0, 18.5]]))
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
from matplotlib.colors import rgb_to_hsv
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from codesign_mb.robot.render import OffscreenRenderer
from codesign_mb.robot.scene import BELT_SURFACE_Z, Scene

__all__ = [
    "EDGE_CAMERA",
    "FRAME_BUDGET_BYTES",
    "Detection",
    "EdgeCamera",
    "PinholeCamera",
    "segment_colour",
]

EDGE_CAMERA = "edge"
"""Name of the perception camera in the scene."""
FRAME_BUDGET_BYTES = 13_500
"""The paper's RGB camera frame size on the uplink (bytes, Table of simulation settings)."""


@dataclass(frozen=True)
class PinholeCamera:
    """A MuJoCo camera as a pinhole: pose in the world and intrinsics of a frame size.

    MuJoCo's camera frame has x right, y up and looks along -z; ``rotation``'s columns are
    those axes in world coordinates (``MjData.cam_xmat``). Pixels are (column u, row v) with
    row 0 at the top and pixel ``(i, j)`` covering ``[i, i + 1) x [j, j + 1)``.
    """

    position: NDArray[np.float64]
    rotation: NDArray[np.float64]
    width: int
    height: int
    fovy_deg: float

    @classmethod
    def from_model(
        cls,
        model: mujoco.MjModel,
        camera: str = EDGE_CAMERA,
        width: int | None = None,
        height: int | None = None,
    ) -> PinholeCamera:
        """The camera ``camera`` of ``model``; frame size from its ``resolution`` unless given.

        The pose is the one at the model's reference configuration (the camera is fixed).
        """
        cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if cam < 0:
            raise ValueError(f"camera {camera!r} not in the model")
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        mujoco.mj_camlight(model, data)
        res_w, res_h = (int(v) for v in model.cam_resolution[cam])
        return cls(
            position=data.cam_xpos[cam].copy(),
            rotation=data.cam_xmat[cam].reshape(3, 3).copy(),
            width=int(width or res_w),
            height=int(height or res_h),
            fovy_deg=float(model.cam_fovy[cam]),
        )

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (square pixels; ``fovy`` spans the frame's height)."""
        return 0.5 * self.height / math.tan(math.radians(self.fovy_deg) / 2.0)

    @property
    def frame_bytes(self) -> int:
        """Size of one raw uint8 RGB frame (bytes)."""
        return self.width * self.height * 3

    def project(self, points: ArrayLike) -> NDArray[np.float64]:
        """Pixel coordinates ``(n, 2)`` (u, v) of world points ``(n, 3)`` in front of the camera."""
        p = (np.atleast_2d(np.asarray(points, dtype=float)) - self.position) @ self.rotation
        depth = -p[:, 2]
        u = self.width / 2.0 + self.focal_px * p[:, 0] / depth
        v = self.height / 2.0 - self.focal_px * p[:, 1] / depth
        return np.column_stack([u, v])

    def back_project(self, pixels: ArrayLike, plane_z: float) -> NDArray[np.float64]:
        """World points ``(n, 3)`` where the rays of ``pixels`` ``(n, 2)`` meet ``z = plane_z``."""
        uv = np.atleast_2d(np.asarray(pixels, dtype=float))
        rays_cam = np.column_stack(
            [
                (uv[:, 0] - self.width / 2.0) / self.focal_px,
                -(uv[:, 1] - self.height / 2.0) / self.focal_px,
                -np.ones(len(uv)),
            ]
        )
        rays = rays_cam @ self.rotation.T
        scale = (plane_z - self.position[2]) / rays[:, 2]
        return self.position + scale[:, None] * rays


def segment_colour(
    frame: NDArray[np.uint8],
    rgb: ArrayLike,
    *,
    hue_tolerance_deg: float = 12.0,
    min_saturation: float = 0.4,
    min_value: float = 0.15,
) -> NDArray[np.bool_]:
    """Mask of the pixels of ``frame`` (h, w, 3) of the hue of ``rgb`` (in [0, 1]).

    HSV thresholding: hue within ``hue_tolerance_deg`` of the object's (shading and highlights
    change value and saturation, hardly hue), saturation at least ``min_saturation`` (the belt,
    the stripes and the arm are grey) and value at least ``min_value`` (too dark to tell).
    """
    target_hue = float(rgb_to_hsv(np.asarray(rgb, dtype=float)[:3])[0])
    hsv = rgb_to_hsv(frame.astype(np.float64) / 255.0)
    gap = np.abs(hsv[..., 0] - target_hue)
    gap = np.minimum(gap, 1.0 - gap) * 360.0
    return (gap <= hue_tolerance_deg) & (hsv[..., 1] >= min_saturation) & (hsv[..., 2] >= min_value)


@dataclass(frozen=True)
class Detection:
    """One frame's result: the object's position (None if missed) and its blob's pixels."""

    position: NDArray[np.float64] | None
    pixel: NDArray[np.float64] | None
    n_pixels: int
    reason: str = ""
    """Why it was missed: ``"too few pixels"`` or ``"at the border"`` (empty if detected)."""


class EdgeCamera:
    """The edge camera of a conveyor scene: render a frame, detect the object in it.

    Parameters
    ----------
    scene:
        The compiled scene (object colour and size, model with the camera).
    camera:
        The camera's name.
    pixel_noise_std:
        Standard deviation of the Gaussian sensor noise added to each channel (8-bit counts).
    min_pixels:
        Fewest matching pixels for a detection.
    hue_tolerance_deg, min_saturation:
        Segmentation settings (:func:`segment_colour`).

    Raises
    ------
    ValueError
        If the camera's raw frame exceeds :data:`FRAME_BUDGET_BYTES`.
    """

    def __init__(
        self,
        scene: Scene,
        *,
        camera: str = EDGE_CAMERA,
        pixel_noise_std: float = 2.0,
        min_pixels: int = 6,
        hue_tolerance_deg: float = 12.0,
        min_saturation: float = 0.4,
    ) -> None:
        self.camera = PinholeCamera.from_model(scene.model, camera)
        if self.camera.frame_bytes > FRAME_BUDGET_BYTES:
            raise ValueError(
                f"camera {camera!r} frame {self.camera.width}x{self.camera.height} RGB is "
                f"{self.camera.frame_bytes} B, over the {FRAME_BUDGET_BYTES} B uplink budget"
            )
        if pixel_noise_std < 0:
            raise ValueError(f"pixel_noise_std must be >= 0, got {pixel_noise_std!r}")
        if min_pixels < 1:
            raise ValueError(f"min_pixels must be >= 1, got {min_pixels!r}")
        self.object_rgb = np.asarray(scene.object_shape.rgba[:3], dtype=float)
        self.plane_z = BELT_SURFACE_Z + scene.object_shape.half_height
        self.pixel_noise_std = float(pixel_noise_std)
        self.min_pixels = int(min_pixels)
        self.hue_tolerance_deg = float(hue_tolerance_deg)
        self.min_saturation = float(min_saturation)
        self._model = scene.model
        self._camera_name = camera
        self._renderer: OffscreenRenderer | None = None

    def capture(
        self, data: mujoco.MjData, rng: np.random.Generator | None = None
    ) -> NDArray[np.uint8]:
        """The uint8 RGB frame (height, width, 3) of ``data``, with sensor noise if ``rng``."""
        if self._renderer is None:
            self._renderer = OffscreenRenderer(
                self._model,
                self.camera.width,
                self.camera.height,
                self._camera_name,
                shadows=False,
                reflections=False,
            )
        frame = self._renderer.render(data)
        if rng is None or self.pixel_noise_std == 0:
            return frame
        noisy = frame + rng.normal(0.0, self.pixel_noise_std, frame.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)

    def detect(self, frame: NDArray[np.uint8]) -> Detection:
        """Locate the object in ``frame`` (see the module docstring)."""
        mask = segment_colour(
            frame,
            self.object_rgb,
            hue_tolerance_deg=self.hue_tolerance_deg,
            min_saturation=self.min_saturation,
        )
        labels, n_blobs = ndimage.label(mask)
        if n_blobs == 0:
            return Detection(None, None, 0, "too few pixels")
        sizes = np.bincount(labels.ravel())[1:]
        rows, cols = np.nonzero(labels == 1 + int(np.argmax(sizes)))
        n = len(rows)
        if n < self.min_pixels:
            return Detection(None, None, n, "too few pixels")
        pixel = np.array([cols.mean() + 0.5, rows.mean() + 0.5])
        h, w = mask.shape
        if rows.min() == 0 or cols.min() == 0 or rows.max() == h - 1 or cols.max() == w - 1:
            return Detection(None, pixel, n, "at the border")
        position = self.camera.back_project(pixel[None, :], self.plane_z)[0]
        return Detection(position, pixel, n)

    def locate(self, data: mujoco.MjData, rng: np.random.Generator | None = None) -> Detection:
        """:meth:`capture` then :meth:`detect`: the camera path of one control step."""
        return self.detect(self.capture(data, rng))

    def close(self) -> None:
        """Free the renderer."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
