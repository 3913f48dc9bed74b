"""``codesign paper``: every published number in one run; ``codesign readme``: README from it.

``codesign paper -o results/paper`` runs every table and figure README's results section shows
(:mod:`codesign_mb.studies.paper`), each study into a subfolder, on the ``test`` seeds,
resuming: a study whose folder is complete with the same settings is not rerun (``--force``
reruns it). ``--readme README.md`` then writes the compact results into ``docs/`` and renders
README's block from them (:mod:`codesign_mb.studies.readme`), as ``codesign readme
results/paper`` does. ``codesign readme`` without a folder re-renders README from the
committed ``docs/results``; ``--check`` only says whether README is current.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Annotated

import typer

from codesign_mb.cli.common import (
    ConfigOption,
    JsonOption,
    OutOption,
    cli_errors,
    emit,
    explicit,
    load_config,
    note,
    track,
)

__all__ = ["paper_command", "readme_command", "register"]

_STUDY_NAMES = (
    "lqg, table_realistic, table_variable, table_model_free, table_paper, "
    "table_learned_realistic, table_learned_variable, fig_cn, fig_wifi, figures"
)
"""The names of :data:`codesign_mb.studies.paper_studies.STUDIES` (``--help`` imports no study)."""

ReadmeOption = Annotated[
    Path,
    typer.Option("--readme", help="The README whose results block is rendered.", dir_okay=False),
]
DocsOption = Annotated[
    Path,
    typer.Option(
        "--docs",
        help="Where the compact results (DOCS/results/*.json) and figures (DOCS/figures) go.",
        file_okay=False,
    ),
]


def paper_command(
    ctx: typer.Context,
    out: OutOption = Path("results/paper"),
    trials: Annotated[
        int,
        typer.Option("--trials", "-n", help="Episodes per row of the variable and paper tables."),
    ] = 100,
    realistic_trials: Annotated[
        int, typer.Option("--realistic-trials", help="Episodes per row of the realistic table.")
    ] = 200,
    model_free_trials: Annotated[
        int,
        typer.Option(
            "--model-free-trials",
            help="Episodes per row and evaluation seed of Table I (table_model_free).",
        ),
    ] = 200,
    fig_cn_trials: Annotated[
        int, typer.Option("--fig-cn-trials", help="Episodes per point of Fig. 4.")
    ] = 100,
    wifi_trials: Annotated[
        int, typer.Option("--wifi-trials", help="Trials per point of Fig. 6.")
    ] = 20,
    lqg_episodes: Annotated[
        int, typer.Option("--lqg-episodes", help="Episodes per reliability of the LQG baseline.")
    ] = 8,
    workers: Annotated[
        int, typer.Option("--workers", "-j", help="Worker processes. (--smoke: 1 unless given)")
    ] = 2,
    only: Annotated[
        list[str] | None,
        typer.Option("--only", help=f"Run only this study (repeatable): {_STUDY_NAMES}."),
    ] = None,
    skip: Annotated[
        list[str] | None, typer.Option("--skip", help="Leave this study out (repeatable).")
    ] = None,
    smoke: Annotated[
        bool, typer.Option("--smoke", help="Tiny settings: a few episodes per study.")
    ] = False,
    force: Annotated[
        bool, typer.Option("--force", help="Rerun studies whose folder is complete.")
    ] = False,
    readme: Annotated[
        Path | None,
        typer.Option(
            "--readme",
            help="Then write DOCS and render this README's results block from them.",
            dir_okay=False,
        ),
    ] = None,
    docs: DocsOption = Path("docs"),
    config: ConfigOption = None,
    as_json: JsonOption = False,
) -> None:
    """Run every table and figure of README's results (test seeds) into OUT/<study>/."""
    from codesign_mb.studies.paper import run_paper
    from codesign_mb.studies.paper_studies import PaperConfig

    cfg = load_config(
        PaperConfig,
        config,
        explicit(
            ctx,
            {
                "trials": trials,
                "realistic_trials": realistic_trials,
                "model_free_trials": model_free_trials,
                "fig_cn_trials": fig_cn_trials,
                "wifi_trials": wifi_trials,
                "lqg_episodes": lqg_episodes,
                "workers": workers,
                "only": tuple(only) if only else None,
                "skip": tuple(skip) if skip else None,
                "smoke": smoke,
                "force": force,
            },
        ),
        section="paper",
    )
    run = run_paper(
        cfg,
        out,
        progress=lambda it, total=None, description="": track(
            it, total=total, description=description, disable=as_json
        ),
        log=note,
        command="codesign " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
    )
    note(f"manifest written to {run.path} ({run.manifest['wall_time_s']:.0f} s)")
    if readme is not None:  # with --only: those studies' docs only, the others' kept
        _render(out, readme, docs, studies=tuple(only) if only else None)
    rows = [
        {"study": name, "status": s["status"], "wall time s": s.get("wall_time_s")}
        for name, s in run.manifest["studies"].items()
    ]
    emit(run.manifest if as_json else rows, as_json=as_json, title=f"codesign paper -> {out}")


def _render(
    results_dir: Path | None,
    readme: Path,
    docs: Path,
    *,
    check: bool = False,
    studies: tuple[str, ...] | None = None,
) -> bool:
    from codesign_mb.studies.readme import export_results, update_readme

    if results_dir is not None:
        export_results(results_dir, docs, studies=studies)
        note(f"compact results written to {docs / 'results'}, figures to {docs / 'figures'}")
    changed = update_readme(readme, docs, check=check)
    if not check:
        note(f"{readme}: results block {'updated' if changed else 'unchanged'}")
    return changed


def readme_command(
    results_dir: Annotated[
        Path | None,
        typer.Argument(
            help="A `codesign paper` folder to export into DOCS first. \\[default: render the "
            "DOCS already there]",
            file_okay=False,
            show_default=False,
        ),
    ] = None,
    readme: ReadmeOption = Path("README.md"),
    docs: DocsOption = Path("docs"),
    check: Annotated[
        bool,
        typer.Option("--check", help="Change nothing; exit 1 when README's block is stale."),
    ] = False,
) -> None:
    """Render README's results block (between its results markers) from DOCS/results."""
    if check and results_dir is not None:
        raise ValueError("--check compares README with DOCS as they are: give no RESULTS_DIR")
    changed = _render(results_dir, readme, docs, check=check)
    if check and changed:
        note(f"{readme}: results block differs from {docs / 'results'}; run `codesign readme`")
        raise typer.Exit(code=1)
    if check:
        note(f"{readme}: results block is current")


def register(app: typer.Typer) -> None:
    """Add ``codesign paper`` and ``codesign readme`` to ``app``."""
    app.command("paper")(cli_errors(paper_command))
    app.command("readme")(cli_errors(readme_command))
