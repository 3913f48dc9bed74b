"""``codesign render``: a GIF (or MP4) of one conveyor episode with the scripted controller.

The episode is :class:`~codesign_mb.plants.conveyor.ConveyorPickPlace` with perfect state
driven by :class:`~codesign_mb.control.scripted.ScriptedPickController`, rendered headless
(EGL or OSMesa, see :mod:`codesign_mb.robot.render`). MP4 needs ``imageio-ffmpeg``; GIF
needs only Pillow.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import typer

from codesign_mb.cli.common import (
    ConfigOption,
    JsonOption,
    SeedOption,
    cli_errors,
    emit,
    explicit,
    load_config,
    note,
    track,
)

__all__ = ["RenderConfig", "register", "render_episode"]

_FORMATS = (".gif", ".mp4")


def _default_env() -> Any:
    from codesign_mb.plants.conveyor import ConveyorConfig

    return ConveyorConfig()


@dataclass(frozen=True)
class RenderConfig:
    """Settings of ``codesign render`` (config file table ``[render]`` or top level)."""

    env: Any = field(default_factory=_default_env)
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
        from codesign_mb.plants.conveyor import ConveyorConfig

        if isinstance(self.env, dict):
            from codesign_mb.core.config import from_mapping

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


def render_episode(config: RenderConfig, *, progress: bool = False) -> dict[str, Any]:
    """Run and render one scripted episode; write ``config.out``; return a summary."""
    import imageio.v3 as iio
    import numpy as np

    from codesign_mb.control.scripted import ScriptedPickController
    from codesign_mb.plants.conveyor import ConveyorPickPlace

    env = ConveyorPickPlace(config.env, render_mode="rgb_array")
    policy = ScriptedPickController(config.env)
    steps = config.steps or env.horizon
    try:
        obs, info = env.reset(seed=config.seed)
        policy.reset(seed=config.seed)
        frames = [env.render()]
        first_success = None
        for t in track(range(steps), total=steps, description="render", disable=not progress):
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            frames.append(env.render())
            if info["success"] and first_success is None:
                first_success = t + 1
            if terminated or truncated:
                break
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


def register(app: typer.Typer) -> None:
    """Add ``codesign render`` to ``app``."""

    @app.command()
    @cli_errors
    def render(
        ctx: typer.Context,
        out: Annotated[
            Path, typer.Option("--out", "-o", help="Output file (.gif, or .mp4 with ffmpeg).")
        ] = Path(RenderConfig.out),
        belt_speed: Annotated[
            float,
            typer.Option("--belt-speed", help="Belt speed in m/s (0.2 and 0.6 in the paper)."),
        ] = 0.2,
        profile: Annotated[
            str, typer.Option("--profile", help="Belt profile: constant or variable.")
        ] = "constant",
        obj: Annotated[str, typer.Option("--object", help="Object: cube or cylinder.")] = "cube",
        camera: Annotated[
            str, typer.Option("--camera", help="Camera: overview or upstream.")
        ] = "overview",
        steps: Annotated[
            int, typer.Option("--steps", help="Control steps to render (0: whole episode).")
        ] = RenderConfig.steps,
        fps: Annotated[int, typer.Option("--fps", help="Frames per second.")] = RenderConfig.fps,
        seed: SeedOption = RenderConfig.seed,
        config: ConfigOption = None,
        as_json: JsonOption = False,
    ) -> None:
        """Render one conveyor episode of the scripted pick controller to a GIF or MP4."""
        overrides = explicit(
            ctx,
            {
                "out": str(out),
                "belt_speed": belt_speed,
                "profile": profile,
                "obj": obj,
                "camera": camera,
                "steps": steps,
                "fps": fps,
                "seed": seed,
            },
            rename={
                "belt_speed": "env.belt_speed_mps",
                "profile": "env.belt_profile",
                "obj": "env.object",
                "camera": "env.render_camera",
            },
        )
        cfg = load_config(RenderConfig, config, overrides, section="render")
        summary = render_episode(cfg, progress=not as_json)
        note(f"wrote {summary['out']}")
        emit(summary, as_json=as_json, title="render")
