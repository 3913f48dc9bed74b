"""``codesign report``: figures (PNG) and a Markdown summary from a results folder."""

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
    track,
)

__all__ = ["register", "report_command"]


_HELP = (
    "Render the paper's Table I and Figs. 4-6 (tables tab_p, fig_cn, fig_lat, fig_wifi) next to "
    "their model-based counterparts, and every sweep table, from RESULTS_DIR.\n\n"
    "Writes PNG figures and report.md; absent tables are skipped with a note. Table names and "
    "columns: see codesign_mb.studies.report. --seed picks the episode shown in Fig. 5 when "
    "the table holds several."
)


def report_command(
    ctx: typer.Context,
    results_dir: Annotated[
        Path,
        typer.Argument(
            help="Results folder (tables written by evaluate, table, wifi, sweep).",
            file_okay=False,
            show_default=False,
        ),
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            "-o",
            help="Where figures and report.md go. \\[default: RESULTS_DIR/report]",
        ),
    ] = None,
    dpi: Annotated[int, typer.Option(help="PNG resolution in dots per inch.")] = 120,
    confidence: Annotated[
        float, typer.Option(help="Confidence level of the success-rate intervals.")
    ] = 0.95,
    metric: Annotated[str, typer.Option(help="Column of sweep tables to plot.")] = "success_rate",
    seed: SeedOption = 0,
    config: ConfigOption = None,
    as_json: JsonOption = False,
) -> None:
    """Render figures and a Markdown summary from RESULTS_DIR."""
    from codesign_mb.studies.report import ReportConfig, build_report

    cfg = load_config(
        ReportConfig,
        config,
        explicit(ctx, {"dpi": dpi, "confidence": confidence, "seed": seed, "metric": metric}),
        section="report",
    )
    result = build_report(
        results_dir,
        out,
        cfg,
        progress=lambda names: track(names, description="report", disable=as_json),
    )
    if not as_json:
        for name, reason in result.skipped.items():
            note(f"skipped {name}: {reason}")
        note(f"report written to {result.markdown}")
    emit(
        {
            "report": str(result.markdown),
            "out_dir": str(result.out_dir),
            "figures": {k: str(v) for k, v in result.figures.items()},
            "skipped": result.skipped,
        },
        as_json=as_json,
        title="report",
    )


def register(app: typer.Typer) -> None:
    """Add ``codesign report`` to ``app``."""
    app.command("report", help=_HELP)(cli_errors(report_command))
