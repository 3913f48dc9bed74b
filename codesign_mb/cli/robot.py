"""Robot commands: ``codesign render`` and ``codesign calibrate-perception``.

``render`` writes a GIF or MP4 of one conveyor episode (:mod:`codesign_mb.studies.render`);
``calibrate-perception`` measures the edge camera path and writes the perception error model's
file (:mod:`codesign_mb.studies.perception`).
"""

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
    refuse_package_models,
)

__all__ = ["calibrate_perception", "register", "render"]


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
        str, typer.Option("--camera", help="Camera: overview, upstream or edge.")
    ] = "overview",
    show_detection: Annotated[
        bool,
        typer.Option(
            "--show-detection",
            help="Run the edge detector on each frame and draw it (the edge camera's view).",
        ),
    ] = False,
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
            "show_detection": show_detection,
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


def calibrate_perception(
    out: Annotated[Path, typer.Option("--out", "-o", help="Calibration file (.json).")] = Path(
        "runs/perception/edge_cube.json"
    ),
    overwrite: Annotated[
        bool,
        typer.Option(
            "--overwrite",
            help="Allow --out inside the installed package's models folder (replacing the "
            "shipped calibration, models/perception/).",
        ),
    ] = False,
    obj: Annotated[str, typer.Option("--object", help="Object: cube or cylinder.")] = "cube",
    seed_set_name: Annotated[
        str, typer.Option("--seed-set", help="Named seed set (calibration: dev).")
    ] = "dev",
    sweep_frames: Annotated[
        int, typer.Option("--sweep-frames", help="Frames of random object/arm placements.")
    ] = 4000,
    episodes: Annotated[
        int, typer.Option("--episodes", help="Scripted episodes per belt speed.")
    ] = 5,
    as_json: JsonOption = False,
) -> None:
    """Measure the edge camera path's errors and write the perception error model's file."""
    import shlex
    import sys

    from codesign_mb.core.seeds import seed_set
    from codesign_mb.studies.perception import calibrate

    if not overwrite:
        refuse_package_models(("--out", out))
    if seed_set_name == "test":  # the error model is fitted: only on dev (as tune refuses)
        raise ValueError(
            "refusing to calibrate on the 'test' seed set: reported numbers come from it, so "
            "a fitted error model must not see it (use 'dev'; DESIGN.md, evaluation protocol)"
        )
    command = "codesign " + shlex.join(sys.argv[1:])
    with progress_bar("calibrate", disable=as_json) as progress:
        summary = calibrate(
            str(out),
            seed=seed_set(seed_set_name),
            object_kind=obj,
            sweep_frames=sweep_frames,
            episodes_per_speed=episodes,
            command=command,
            progress=progress,
        )
    note(f"wrote {summary['out']}")
    emit(summary, as_json=as_json, title="perception calibration")


def register(app: typer.Typer) -> None:
    """Add ``codesign render`` and ``codesign calibrate-perception`` to ``app``."""
    app.command()(cli_errors(render))
    app.command("calibrate-perception")(cli_errors(calibrate_perception))
