"""``codesign table``: Table I (``tab_p``), the head-to-head table and Fig. 5 (``fig_lat``).

Writes into ``OUT``:

``tab_p.{parquet,csv,json}``
    One row per table row and plant: success with its 95 % Wilson interval, average requested
    reliability, delivered fraction, training cost, CPU ms per control step, Pareto flag,
    ``status`` and the paper's figures (columns: :mod:`codesign_mb.studies.table`).
``tab_p.md``
    The same as a Markdown table.
``tab_p_episodes.*``
    Every episode (with ``plant`` and ``row``).
``fig_pareto.png``
    Success versus average requested reliability, one panel per plant, the Pareto-optimal
    rows ringed.
``fig_lat.png``, ``fig_lat.*``
    The QoS timeline of one successful episode on the first plant: of the co-design row of
    ``--pipeline model-free|model-based``, else of the best row (the least average reliability
    among rows with >= 98 % success, else the most successful row).

A row whose checkpoint is missing is skipped with a warning on stderr and its ``status`` in
the table (``--on-missing error``: the command fails before any episode, exit code 2).
"""

from __future__ import annotations

import shlex
import sys
import time
import warnings
from pathlib import Path
from typing import Annotated, TextIO

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

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    @app.command("table")
    @cli_errors
    def table(
        ctx: typer.Context,
        pipeline: Annotated[
            str,
            typer.Option(
                "--pipeline",
                help=(
                    "Which rows: model-free (the paper's Table I, 0.2 m/s), model-based (MPC, "
                    "predictor, rule QoS; 0.2 m/s) or all ({static, rule, SAC} QoS x {SAC + "
                    "MLP, MPC + predictor}, the mixed pairs; both belt speeds and the "
                    "variable belt)."
                ),
            ),
        ] = "model-free",
        plant: Annotated[
            list[str] | None,
            typer.Option(
                "--plant",
                help=(
                    "A plant to evaluate on (repeatable): 0.2, 0.6 or variable (0.6 m/s with "
                    "speed steps and stops). Default: the pipeline's."
                ),
            ),
        ] = None,
        config: ConfigOption = None,
        trials: Annotated[
            int, typer.Option("--trials", "-n", help="Episodes per row and plant.")
        ] = 100,
        seed: Annotated[int, typer.Option("--seed", help="Root seed of the episodes.")] = 0,
        workers: Annotated[
            int,
            typer.Option(
                "--workers", "-j", help="Worker processes, shared by all rows and plants."
            ),
        ] = 1,
        on_missing: Annotated[
            str,
            typer.Option(
                "--on-missing",
                help="A row whose checkpoint is missing: skip (warn, status column) or error.",
            ),
        ] = "skip",
        out: OutOption = Path("results/table"),
        as_json: JsonOption = False,
    ) -> None:
        """Evaluate the pipeline's {controller, estimator, QoS} rows; write tab_p and figures."""
        import torch

        from codesign_mb.core.results import atomic_write, write_results
        from codesign_mb.studies.table import (
            TableConfig,
            markdown_table,
            plot_pareto,
            plot_timeline,
            qos_timeline,
            run_table,
            timeline_row_name,
        )

        cfg = load_config(
            TableConfig,
            config,
            explicit(
                ctx,
                {
                    "pipeline": pipeline,
                    "plant": tuple(plant) if plant else None,
                    "trials": trials,
                    "seed": seed,
                    "workers": workers,
                    "on_missing": on_missing,
                },
                rename={"plant": "plants"},
            ),
            section="table",
        )
        torch.set_num_threads(1)  # the machine is shared; workers add parallelism
        started = time.perf_counter()
        with warnings.catch_warnings():  # restores showwarning on exit
            warnings.simplefilter("always", RuntimeWarning)
            shown_as_usual = warnings.showwarning

            def show(
                message: Warning | str,
                category: type[Warning],
                filename: str,
                lineno: int,
                file: TextIO | None = None,
                line: str | None = None,
            ) -> None:
                # A skipped row, a dead worker: one line on stderr, at once; others as usual.
                if issubclass(category, RuntimeWarning):
                    note(f"warning: {message}")
                else:
                    shown_as_usual(message, category, filename, lineno, file, line)

            warnings.showwarning = show
            summary, episodes = run_table(
                cfg,
                progress=lambda it, total=None, description="": track(
                    it, total=total, description=description, disable=as_json
                ),
            )
        extra = {
            "command": "codesign " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
            "wall_time_s": round(time.perf_counter() - started, 1),
            "plants": {p.label: {"name": p.name, "options": p.options} for p in cfg.table_plants()},
        }
        write_results(out, table=summary, config=cfg, name="tab_p", extra=extra)
        write_results(out, table=episodes, config=cfg, name="tab_p_episodes", extra=extra)
        with atomic_write(out / "tab_p.md", "w") as fh:
            fh.write(markdown_table(summary))
        plot_pareto(
            summary, out / "fig_pareto.png", title=f"codesign table --pipeline {cfg.pipeline}"
        )

        first = cfg.table_plants()[0]
        name = timeline_row_name(cfg, summary)
        row = next((r for r in cfg.table_rows() if r.name == name), None)
        found = None if row is None else qos_timeline(first, row, episodes)
        if found is None:
            status = summary.loc[
                (summary["row"] == name) & (summary["plant"] == first.label), "status"
            ]
            why = (
                f"{name!r} was not run ({status.iloc[0]})"
                if len(status) and status.iloc[0] != "ok"
                else f"no successful episode of {name!r} on {first.label}"
            )
            note(f"{why}: fig_lat not drawn")
        else:
            steps, ep_seed = found
            write_results(
                out,
                table=steps,
                config=cfg,
                name="fig_lat",
                extra={**extra, "row": row.name, "plant": first.label, "episode_seed": ep_seed},
            )
            plot_timeline(steps, out / "fig_lat.png", title=f"{row.name}, {first.label}")
        note(f"results written to {out} ({time.perf_counter() - started:.0f} s)")
        shown = summary[
            [
                "plant",
                "row",
                "status",
                "success_rate",
                "success_ci_low",
                "success_ci_high",
                "mean_requested_reliability",
                "delivered_fraction",
                "train_env_steps",
                "train_wall_time_s",
                "cpu_ms_per_step",
                "pareto",
                "paper_success_rate",
                "paper_mean_reliability",
            ]
        ]
        if as_json:
            emit(shown, as_json=True)
        else:  # a Markdown table stays readable in a narrow terminal
            typer.echo(markdown_table(summary), nl=False)
