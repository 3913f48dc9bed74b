"""Render one conveyor episode of the scripted pick to a GIF or MP4 (``codesign render``).

The episode is :class:`~codesign_mb.plants.conveyor.ConveyorPickPlace` with perfect state
driven by :class:`~codesign_mb.control.scripted.ScriptedPickController`, rendered headless
(EGL or OSMesa, see :mod:`codesign_mb.robot.render`). MP4 needs ``imageio-ffmpeg``; GIF
needs only Pillow.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.scripted import ScriptedPickController
from codesign_mb.core.config import from_mapping
from codesign_mb.network import BernoulliLink, LinkObservationWrapper
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace
from codesign_mb.rollout import ClosedLoop

__all__ = ["RenderConfig", "render_episode"]

_FORMATS = (".gif", ".mp4")


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

    def __post_init__(self) -> None:
        if isinstance(self.env, dict):
            object.__setattr__(self, "env", from_mapping(ConveyorConfig, self.env, where="env"))
        if not isinstance(self.env, ConveyorConfig):
            raise ValueError(f"env must be a ConveyorConfig table, got {self.env!r}")
        if Path(self.out).suffix.lower() not in _FORMATS:
            raise ValueError(f"out must end in .gif or .mp4, got {self.out!r}")
        for name, low in (("seed", 0), ("steps", 0), ("fps", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{name} must be an integer, got {value!r}")
            if value < low:
                raise ValueError(f"{name} must be >= {low}, got {value}")


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
    try:
        info = loop.reset(seed=config.seed)
        frames = [env.render()]
        first_success = None
        while not loop.done and loop.t < steps:
            _, _, info = loop.step()
            frames.append(env.render())
            if info["success"] and first_success is None:
                first_success = loop.t
            if progress is not None:
                progress(loop.t, steps)
    finally:
        env.close()
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
    }
