"""``codesign train <stage>``: the model-free pipeline of paper.tex sec. 4, stage by stage.

=====  ==========================================================  ===========================
stage  what                                                        default output (``runs/``)
=====  ==========================================================  ===========================
a      SAC ideal controller (from demonstrations, oracle link)    checkpoints/stage_a
b      MLP + LSTM estimators under the delay distribution (per      checkpoints/stage_b
       phase errors; velocity estimated where the packet has none)
c      SAC QoS policy for a controller/estimator pair (inputs:     checkpoints/stage_c_<estimator>
       (y, zeta), + --qos-features: model-free or hybrid)
d      synthesis: estimator under the learned QoS, QoS re-trained  checkpoints/stage_d
=====  ==========================================================  ===========================

Outputs go under ``runs/checkpoints/`` of the working directory unless ``--out`` says
otherwise; the installed package's ``models`` folder (the shipped checkpoints) is written
only with ``--overwrite`` (they are reproduced with ``--out models/checkpoints/<name>
--overwrite`` in a source checkout, see ``models/checkpoints/README.md``). A later stage
reads its inputs from its config
(``checkpoints/stage_a/model.zip`` etc.: the working directory, then the shipped ones), so
chaining fresh runs means passing their paths, e.g.
``--set controller.checkpoint=runs/checkpoints/stage_a/model.zip``. The work folder
(``runs/train/<name>``: latest model, replay buffer, step counter) makes ``--resume`` continue
an interrupted run where its last checkpoint left it.
"""

from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from codesign_mb.cli.common import (
    SCENARIO_HELP,
    ConfigOption,
    JsonOption,
    cli_errors,
    emit,
    load_config,
    note,
    refuse_package_models,
    track,
)

__all__ = ["register", "train"]

STAGES = ("a", "b", "c", "d")
RUNS = Path("runs")
"""Where training writes by default, relative to the working directory."""


def _parse_value(text: str) -> Any:
    """A ``--set`` value: JSON when it parses (numbers, booleans, lists, tables), else a string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _overrides(assignments: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in assignments:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set expects key=value (dotted keys allowed), got {item!r}")
        out[key.strip()] = _parse_value(value.strip())
    return out


def _config_class(stage: str) -> type:
    from codesign_mb.core.registry import kind, resolve

    config_class: type = resolve(kind("stage", stage).config)
    return config_class


def default_out(stage: str, config: Any) -> Path:
    """Where a stage writes by default: ``runs/checkpoints/stage_<x>`` (working directory)."""
    name = f"stage_{stage}"
    if stage == "c":
        name = f"stage_c_{config.estimator.kind}"
    return RUNS / "checkpoints" / name


def stage_config(
    stage: str,
    config_file: Path | None,
    *,
    assignments: list[str],
    seed: int | None,
    steps: int | None,
    estimator: str | None,
    scenario: str | None = None,
    qos_features: str | None = None,
) -> Any:
    """The stage's config: its section of ``config_file``, then the command-line overrides.

    ``--scenario`` first (the plant becomes that scenario's conveyor), then the ``--set``
    assignments, then ``--seed``, ``--steps``, ``--estimator`` and ``--qos-features``.
    """
    overrides: dict[str, Any] = {}
    if scenario is not None:
        from codesign_mb.plants.scenarios import scenario_options

        overrides["plant"] = {"name": "conveyor", "options": scenario_options(scenario)}
    overrides.update(_overrides(assignments))
    if seed is not None:
        overrides["seed"] = seed
    if steps is not None:
        if stage == "b":
            raise ValueError("--steps does not apply to stage b (set train_episodes)")
        overrides["total_steps" if stage != "d" else "qos.total_steps"] = steps
    if estimator is not None:
        if stage != "c":
            raise ValueError("--estimator applies to stage c only")
        overrides["estimator.kind"] = estimator
        if estimator in ("none", "predictor"):
            overrides["estimator.checkpoint"] = None
    if qos_features is not None:
        if stage not in ("c", "d"):
            raise ValueError("--qos-features applies to stages c and d only")
        from codesign_mb.adaptation.learned import QOS_FEATURES

        if qos_features != "none" and qos_features not in QOS_FEATURES:
            raise ValueError(
                f"--qos-features must be none or one of {', '.join(QOS_FEATURES)}, "
                f"got {qos_features!r}"
            )
        value = None if qos_features == "none" else qos_features
        overrides["features" if stage == "c" else "qos.features"] = value
    cfg: Any = load_config(_config_class(stage), config_file, {}, section=stage)
    if stage == "a" and steps is not None:  # the warm-up's SAC updates count against --steps
        overrides.setdefault("critic_warmup_steps", min(cfg.critic_warmup_steps, steps))
    return _apply(cfg, overrides) if overrides else cfg


def run_stage(
    stage: str,
    config: Any,
    *,
    out_dir: Path,
    work_dir: Path,
    resume: bool,
    progress: Any,
    command: str | None,
) -> dict[str, Any]:
    """Run one stage's trainer (what the command does after parsing)."""
    import torch

    torch.set_num_threads(1)
    from codesign_mb.core.registry import create
    from codesign_mb.stages.stage import StageRun

    run = StageRun(out_dir, work_dir, resume, progress, command)
    summary: dict[str, Any] = create("stage", stage, config, run)
    return summary


@cli_errors
def train(
    stage: Annotated[str, typer.Argument(help="Pipeline stage: a, b, c or d.")],
    config: ConfigOption = None,
    steps: Annotated[
        int | None,
        typer.Option(
            "--steps",
            help="SAC env steps (total_steps; stage d: qos.total_steps), over the config's. "
            "Stage a: also caps the critic warm-up's updates (critic_warmup_steps, "
            "actor_freeze_steps); not capped: the demonstrations (demo_episodes), the "
            "evaluations (eval_episodes, final_eval_episodes); --set those. "
            "\\[default: the config's: a 20000, c 40000, d 20000]",
        ),
    ] = None,
    seed: Annotated[
        int | None, typer.Option("--seed", help="Root seed. \\[default: the config's, 0]")
    ] = None,
    estimator: Annotated[
        str | None,
        typer.Option(
            "--estimator",
            help="Stage c: the estimator kind the QoS policy is learned for "
            "(mlp, lstm, none, predictor); its checkpoint comes from the config. "
            "\\[default: the config's, mlp]",
        ),
    ] = None,
    qos_features: Annotated[
        str | None,
        typer.Option(
            "--qos-features",
            help="Stages c, d: the QoS policy's extra inputs beyond (y, zeta). Model-free: "
            "none, held_history (elapsed time, held-position differences, lift), elapsed_time; "
            "hybrid: predictor_std (a Kalman predictor replica at the edge). Stage d checks it "
            "against the stage-C policy's. \\[default: the config's, none]",
            show_default=False,
        ),
    ] = None,
    scenario: Annotated[
        str | None,
        typer.Option(
            "--scenario",
            help=f"{SCENARIO_HELP} The plant the stage trains on (before --set). \\[default: "
            "the config's plant, the paper scenario's conveyor unless it says otherwise]",
            show_default=False,
        ),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            help="Config override key=value (dotted keys, JSON values), repeatable: "
            "--set plant.options.belt_speed_mps=0.6",
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            "-o",
            help="Output (checkpoint) folder (the shipped ones: models/checkpoints/<name>). "
            "\\[default: runs/checkpoints/<name>]",
            file_okay=False,
        ),
    ] = None,
    work_dir: Annotated[
        Path | None,
        typer.Option(
            "--work-dir",
            help="Work folder for resume. \\[default: runs/train/<name>]",
            file_okay=False,
        ),
    ] = None,
    resume: Annotated[
        bool, typer.Option("--resume", help="Continue from the work folder's checkpoint.")
    ] = False,
    overwrite: Annotated[
        bool,
        typer.Option(
            "--overwrite",
            help="Allow --out or --work-dir inside the installed package's models folder "
            "(replacing a shipped checkpoint).",
        ),
    ] = False,
    as_json: JsonOption = False,
) -> None:
    """Train one stage of the model-free pipeline (checkpoint, curve, resumable)."""
    stage = stage.lower()
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {', '.join(STAGES)}, got {stage!r}")
    cfg = stage_config(
        stage,
        config,
        assignments=set_ or [],
        seed=seed,
        steps=steps,
        estimator=estimator,
        scenario=scenario,
        qos_features=qos_features,
    )
    out_dir = out or default_out(stage, cfg)
    work = work_dir or RUNS / "train" / out_dir.name
    if not overwrite:
        refuse_package_models(("--out", out_dir), ("--work-dir", work))
    try:
        result = run_stage(
            stage,
            cfg,
            out_dir=out_dir,
            work_dir=work,
            resume=resume,
            progress=lambda it, total=None, description="": track(
                it, total=total, description=description, disable=as_json
            ),
            command="codesign " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        )
    except KeyboardInterrupt:
        raise KeyboardInterrupt(
            f"the work folder {work} keeps what finished (SAC's last chunk, stage b's rounds); "
            "rerun with --resume to continue from it"
        ) from None
    note(f"stage {stage}: checkpoint written to {out_dir}")
    emit(result, as_json=as_json, title=f"stage {stage}")


def register(app: typer.Typer) -> None:
    """Add ``codesign train`` to ``app``."""
    app.command("train")(train)


def _apply(config: Any, overrides: dict[str, Any]) -> Any:
    """Re-build ``config`` with dotted overrides (``None`` values clear a field)."""
    from codesign_mb.core.config import from_mapping, to_mapping

    data = to_mapping(config)
    for key, value in overrides.items():
        *parents, leaf = key.split(".")
        node = data
        for part in parents:
            if not isinstance(node.get(part), dict):
                node[part] = {}
            node = node[part]
        node[leaf] = value
    return from_mapping(type(config), data)
