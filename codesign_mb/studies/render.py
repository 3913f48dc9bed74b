"""Render one conveyor episode of the scripted pick to a GIF or MP4 (``codesign render``).

The episode is :class:`~codesign_mb.plants.conveyor.ConveyorPickPlace` with perfect state
driven by :class:`~codesign_mb.control.scripted.ScriptedPickController`, rendered headless
(EGL or OSMesa, see :mod:`codesign_mb.robot.render`). MP4 needs ``imageio-ffmpeg``; GIF
needs only Pillow.

With ``show_detection`` (``codesign render --camera edge --show-detection``) the frames are
what the edge detector sees (:class:`~codesign_mb.robot.camera.EdgeCamera`: its native
resolution, with sensor noise), enlarged ``DETECTION_ZOOM`` times, with the detection drawn
on them: a yellow cross at the detected centroid, a green dot at the object's true centre
(projected) and a red frame when the detection is missed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.scripted import ScriptedPickController
from codesign_mb.core.config import (
    SEED_CAP,
    STEPS_CAP,
    check_range,
    check_writable,
    from_mapping,
)
from codesign_mb.network import BernoulliLink, LinkObservationWrapper
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace
from codesign_mb.robot.camera import EDGE_CAMERA, Detection, EdgeCamera
from codesign_mb.rollout import ClosedLoop

__all__ = ["DETECTION_ZOOM", "RenderConfig", "draw_detection", "render_episode"]

_FORMATS = (".gif", ".mp4")
DETECTION_ZOOM = 4
"""Enlargement of the edge camera's small frames in ``show_detection`` renderings."""


@dataclass(frozen=True)
class RenderConfig:
    """Settings of ``codesign render`` (config file table ``[render]`` or top level)."""

    env: Any = field(default_factory=ConveyorConfig)
    """The env's :class:`~codesign_mb.plants.conveyor.ConveyorConfig` (table ``[render.env]``)."""
    out: str = "conveyor.gif"
    """Output file, ``.gif`` or ``.mp4``."""
    seed: int = 0
    """Episode seed."""
    steps: int = 0
    """Control steps to render (0: the whole horizon)."""
    fps: int = 25
    """Frames per second of the output (25 = real time at 40 ms per step)."""
    show_detection: bool = False
    """Render the edge camera's frames with the detection drawn (needs ``env.render_camera
    = "edge"``)."""

    def __post_init__(self) -> None:
        if isinstance(self.env, dict):
            object.__setattr__(self, "env", from_mapping(ConveyorConfig, self.env, where="env"))
        if not isinstance(self.env, ConveyorConfig):
            raise ValueError(f"env must be a ConveyorConfig table, got {self.env!r}")
        if Path(self.out).suffix.lower() not in _FORMATS:
            raise ValueError(f"out must end in .gif or .mp4, got {self.out!r}")
        check_writable("out", self.out)
        if not isinstance(self.show_detection, bool):
            raise ValueError(f"show_detection must be a bool, got {self.show_detection!r}")
        if self.show_detection and self.env.render_camera != EDGE_CAMERA:
            raise ValueError(
                f"show_detection needs the edge camera (--camera {EDGE_CAMERA}), "
                f"got camera {self.env.render_camera!r}"
            )
        for name, low in (("seed", 0), ("steps", 0), ("fps", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{name} must be an integer, got {value!r}")
            if value < low:
                raise ValueError(f"{name} must be >= {low}, got {value}")
        check_range("steps", self.steps, cap=STEPS_CAP)
        check_range("seed", self.seed, cap=SEED_CAP)
        check_range("fps", self.fps, le=1000)


def render_episode(
    config: RenderConfig, *, progress: Callable[[int, int], None] | None = None
) -> dict[str, Any]:
    """Run and render one scripted episode; write ``config.out``; return a summary.

    The episode is the one closed loop with ideal control (perfect state, no estimator)
    behind a perfect link (``q = 1``, ``tau = 0``), so it is the pick the scripted
    controller makes on the true state.
    """
    import imageio.v3 as iio  # rendering and video writing stay out of start-up

    plant = ConveyorPickPlace(config.env, render_mode="rgb_array")
    env = LinkObservationWrapper(plant, BernoulliLink(), StaticQos(1.0, 0))
    loop = ClosedLoop(env, None, ScriptedPickController(config.env), record=False)
    steps = config.steps or plant.horizon
    render: Callable[[], Any] = env.render
    detections: list[bool] = []
    camera: EdgeCamera | None = None
    if config.show_detection:
        camera = EdgeCamera(plant.sim.scene)
        rng = np.random.default_rng(config.seed)
        render = partial(_detection_frame, camera, plant, rng, detections)
    try:
        info = loop.reset(seed=config.seed)
        frames = [render()]
        first_success = None
        while not loop.done and loop.t < steps:
            _, _, info = loop.step()
            frames.append(render())
            if info["success"] and first_success is None:
                first_success = loop.t
            if progress is not None:
                progress(loop.t, steps)
    finally:
        env.close()
        if camera is not None:
            camera.close()
    out = Path(config.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stack = np.stack(frames)
    if out.suffix.lower() == ".gif":
        iio.imwrite(out, stack, duration=1000.0 / config.fps, loop=0)
    else:
        try:
            iio.imwrite(out, stack, fps=config.fps, codec="libx264")
        except Exception as exc:  # no ffmpeg/pyav plugin
            raise ValueError(
                f"cannot write MP4 ({exc}); install imageio-ffmpeg or write a .gif"
            ) from exc
    return {
        "out": str(out),
        "frames": len(frames),
        "success": bool(info["success"]),
        "success_step": first_success,
        "belt_speed_mps": config.env.belt_speed_mps,
        "belt_profile": config.env.belt_profile,
        "seed": config.seed,
        **({"detected_frames": sum(detections)} if config.show_detection else {}),
    }


def _detection_frame(
    camera: EdgeCamera, plant: ConveyorPickPlace, rng: np.random.Generator, detected: list[bool]
) -> NDArray[np.uint8]:
    frame = camera.capture(plant.sim.data, rng)
    detection = camera.detect(frame)
    detected.append(detection.position is not None)
    truth = camera.camera.project(plant.sim.object_position()[None, :])[0]
    return draw_detection(frame, detection, truth)


def draw_detection(
    frame: NDArray[np.uint8], detection: Detection, truth: NDArray[np.float64] | None = None
) -> NDArray[np.uint8]:
    """``frame`` enlarged :data:`DETECTION_ZOOM` times with ``detection`` drawn on it.

    A yellow cross at the detected centroid, a green dot at ``truth`` (the true centre's
    pixel, if given), a red frame around a missed detection.
    """
    from PIL import Image, ImageDraw

    zoom = DETECTION_ZOOM
    image = Image.fromarray(np.kron(frame, np.ones((zoom, zoom, 1), dtype=np.uint8)))
    draw = ImageDraw.Draw(image)
    if truth is not None:
        u, v = zoom * truth
        draw.ellipse([u - 2, v - 2, u + 2, v + 2], fill=(40, 220, 60))
    if detection.position is not None and detection.pixel is not None:
        u, v = zoom * detection.pixel
        arm = 2 * zoom
        draw.line([u - arm, v, u + arm, v], fill=(255, 230, 0), width=1)
        draw.line([u, v - arm, u, v + arm], fill=(255, 230, 0), width=1)
    else:
        draw.rectangle([0, 0, image.width - 1, image.height - 1], outline=(230, 30, 30), width=2)
    return np.asarray(image)
