"""``codesign table``: the paper's Table I (``tab_p``) and Fig. 5 (``fig_lat``) on our env.

Writes ``OUT/tab_p.{parquet,csv,json}`` (one row per table row: success with its 95 % Wilson
interval, average requested reliability, the paper's figures), ``OUT/tab_p_episodes.*`` (every
episode), ``OUT/fig_lat.png`` and ``OUT/fig_lat.*`` (the QoS timeline of one successful
episode of the co-design row).
"""

from __future__ import annotations

import shlex
import sys
import time
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
                    "Which rows: model-free (the paper's Table I), model-based (MPC, "
                    "predictor, rule QoS) or all (both, and the mixed pairs)."
                ),
            ),
        ] = "model-free",
        config: ConfigOption = None,
        trials: Annotated[int, typer.Option("--trials", "-n", help="Episodes per row.")] = 100,
        seed: Annotated[int, typer.Option("--seed", help="Root seed of the episodes.")] = 0,
        workers: Annotated[
            int, typer.Option("--workers", "-j", help="Worker processes of the evaluation.")
        ] = 1,
        out: OutOption = Path("results/table"),
        as_json: JsonOption = False,
    ) -> None:
        """Evaluate the pipeline's {controller, estimator, QoS} rows; write tab_p and fig_lat."""
        import torch

        from codesign_mb.evaluation.results import write_results
        from codesign_mb.pipeline.table import TableConfig, plot_timeline, qos_timeline, run_table

        cfg = load_config(
            TableConfig,
            config,
            explicit(
                ctx, {"pipeline": pipeline, "trials": trials, "seed": seed, "workers": workers}
            ),
            section="table",
        )
        torch.set_num_threads(1)  # the machine is shared; workers add parallelism
        started = time.perf_counter()
        summary, episodes = run_table(
            cfg,
            progress=lambda it, total=None, description="": track(
                it, total=total, description=description, disable=as_json
            ),
        )
        extra = {
            "command": "codesign " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
            "wall_time_s": round(time.perf_counter() - started, 1),
        }
        write_results(out, table=summary, config=cfg, name="tab_p", extra=extra)
        write_results(out, table=episodes, config=cfg, name="tab_p_episodes", extra=extra)
        rows = cfg.table_rows()
        row = next((r for r in rows if r.name == cfg.timeline_row), rows[-1])
        found = qos_timeline(cfg.plant, row, episodes)
        if found is None:
            note(f"no successful episode of {row.name!r}: fig_lat not drawn")
        else:
            steps, ep_seed = found
            write_results(
                out,
                table=steps,
                config=cfg,
                name="fig_lat",
                extra={**extra, "row": row.name, "episode_seed": ep_seed},
            )
            plot_timeline(steps, out / "fig_lat.png", title=row.name)
        note(f"results written to {out}")
        shown = summary[
            [
                "row",
                "success_rate",
                "success_ci_low",
                "success_ci_high",
                "mean_requested_reliability",
                "paper_success_rate",
                "paper_mean_reliability",
            ]
        ]
        emit(shown, as_json=as_json, title="tab_p")
