"""``codesign render``: a GIF or MP4 of one conveyor episode (:mod:`codesign_mb.studies.render`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

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
    progress_bar,
)

__all__ = ["register", "render"]


def render(
    ctx: typer.Context,
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Output file (.gif, or .mp4 with ffmpeg).")
    ] = Path("conveyor.gif"),
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
    ] = 0,
    fps: Annotated[int, typer.Option("--fps", help="Frames per second.")] = 25,
    seed: SeedOption = 0,
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
    from codesign_mb.studies.render import RenderConfig, render_episode

    cfg = load_config(RenderConfig, config, overrides, section="render")
    with progress_bar("render", disable=as_json) as progress:
        summary = render_episode(cfg, progress=progress)
    note(f"wrote {summary['out']}")
    emit(summary, as_json=as_json, title="render")


def register(app: typer.Typer) -> None:
    """Add ``codesign render`` to ``app``."""
    app.command()(cli_errors(render))
