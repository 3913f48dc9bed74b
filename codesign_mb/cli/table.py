"""``codesign table``: Table I (``tab_p``), the head-to-head table and Fig. 5 (``fig_lat``).

Writes into ``OUT``:

``tab_p.{parquet,csv,json}``
    One row per table row and plant: success with its 95 % Wilson interval, average requested
    reliability, delivered fraction, training cost, CPU ms per control step, Pareto flag,
    ``status``, the MPC's failed solves and the paper's figures (columns:
    :mod:`codesign_mb.studies.table`).
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
``.records/``
    Every episode as it finishes (:mod:`codesign_mb.core.records`): an interrupted run (Ctrl-C
    says how many are kept) is resumed by the same command, which computes only the missing
    episodes and writes the same tables; ``--fresh`` recomputes them all.

Each plant's reference rows (``blind``, ``oracle``, ``static`` per stack, ``random`` per
co-design row; :mod:`codesign_mb.studies.table_refs`) follow its own rows, marked in the
``kind`` and ``reference`` columns and in the Markdown and drawn in grey on the Pareto plot;
``--no-references`` leaves them out (quicker).

A row whose checkpoint is missing is skipped with a warning on stderr and its ``status`` in
the table (``--on-missing error``: the command fails before any episode, exit code 2). The
files are written by :func:`codesign_mb.studies.table_figures.write_table_outputs`.
"""

from __future__ import annotations

import contextlib
import shlex
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, TextIO

import typer

from codesign_mb.cli.common import (
    SCENARIO_HELP,
    ConfigOption,
    FreshOption,
    JsonOption,
    OutOption,
    cli_errors,
    comma_list,
    emit,
    explicit,
    load_config,
    note,
    track,
    writable_folder,
)

__all__ = ["register", "table_command"]


def table_command(
    ctx: typer.Context,
    pipeline: Annotated[
        str,
        typer.Option(
            "--pipeline",
            help=(
                "Which rows: model-free (the paper's Table I, 0.2 m/s), model-based (MPC, "
                "predictor, rule QoS; 0.2 m/s) or all ({static, rule, SAC} QoS x {SAC + "
                "MLP, MPC + predictor}, the mixed pairs; both belt speeds and the "
                "variable belt) or learned (the realistic learned stack, stage by stage: "
                "BC actor + GRU estimator + SAC QoS, each stage swapped for the model-based one)."
            ),
        ),
    ] = "model-free",
    plant: Annotated[
        list[str] | None,
        typer.Option(
            "--plant",
            help=(
                "A plant to evaluate on (repeatable): 0.2, 0.6 or variable (0.6 m/s with "
                "speed steps and stops), or a scenario name. \\[default: the pipeline's]"
            ),
        ),
    ] = None,
    scenario: Annotated[
        str | None,
        typer.Option(
            "--scenario",
            help=f"{SCENARIO_HELP} Evaluates on that scenario's conveyor only (instead of "
            "--plant). \\[default: the pipeline's plants: realistic (model-based), 0.2 "
            "(model-free: the plant its checkpoints were trained on), realistic, 0.2, 0.6 and "
            "variable (all)]",
            show_default=False,
        ),
    ] = None,
    config: ConfigOption = None,
    trials: Annotated[
        int, typer.Option("--trials", "-n", help="Episodes per row and plant.")
    ] = 100,
    seed: Annotated[int, typer.Option("--seed", help="Root seed of the episodes.")] = 0,
    seeds: Annotated[
        str | None,
        typer.Option(
            "--seeds",
            help=(
                "Several root seeds instead of --seed, comma separated (0,1,2: three "
                "evaluation seeds): --trials episodes from each, pooled per row, each "
                "seed's success rate beside the pooled one. \\[default: --seed alone]"
            ),
            show_default=False,
        ),
    ] = None,
    workers: Annotated[
        int,
        typer.Option("--workers", "-j", help="Worker processes, shared by all rows and plants."),
    ] = 1,
    on_missing: Annotated[
        str,
        typer.Option(
            "--on-missing",
            help="A row whose checkpoint is missing: skip (warn, status column) or error.",
        ),
    ] = "skip",
    references: Annotated[
        bool | None,
        typer.Option(
            "--references/--no-references",
            help=(
                "Add the reference rows (blind q = 0, oracle q = 1 tau = 0, static q = 1 "
                "tau = 1 per stack; random at each co-design row's reliability). \\[default: "
                "yes for a pipeline's rows, no for rows given in a config]"
            ),
        ),
    ] = None,
    bound: Annotated[
        list[str] | None,
        typer.Option(
            "--bound",
            help=(
                "A co-design row (its name; repeatable) that gets a clairvoyant-schedule row: "
                "each of its episodes replayed with the fewest of its own requests that still "
                "succeed (an upper bound on the packets the episode needs; a few replays each). "
                "\\[default: none]"
            ),
            show_default=False,
        ),
    ] = None,
    out: OutOption = Path("results/table"),
    fresh: FreshOption = False,
    as_json: JsonOption = False,
) -> None:
    """Evaluate the pipeline's {controller, estimator, QoS} rows; write tab_p and figures."""
    from codesign_mb.studies.table import TableConfig
    from codesign_mb.studies.table_figures import SUMMARY_COLUMNS, markdown_table, run_table_study

    cfg = load_config(
        TableConfig,
        config,
        explicit(
            ctx,
            {
                "pipeline": pipeline,
                "plant": tuple(plant) if plant else None,
                "scenario": scenario,
                "trials": trials,
                "seed": seed,
                "seeds": _seed_list(seeds),
                "workers": workers,
                "on_missing": on_missing,
                "references": references,
                "bound": tuple(bound) if bound else None,
            },
            rename={"plant": "plants"},
        ),
        section="table",
    )
    writable_folder("--out", out)
    started = time.perf_counter()
    with _runtime_warnings_as_notes():
        result = run_table_study(
            cfg,
            out,
            progress=lambda it, total=None, description="": track(
                it, total=total, description=description, disable=as_json
            ),
            command="codesign " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
            fresh=fresh,
        )
    if result.reused:
        note(f"resumed: {result.reused} episodes reused from {out / '.records'}")
    if result.fig_lat_note:
        note(result.fig_lat_note)
    note(f"results written to {out} ({time.perf_counter() - started:.0f} s)")
    if as_json:
        emit(result.summary[list(SUMMARY_COLUMNS)], as_json=True)
    else:  # a Markdown table stays readable in a narrow terminal
        typer.echo(markdown_table(result.summary), nl=False)


def _seed_list(text: str | None) -> tuple[int, ...] | None:
    """``"0,1,2"`` -> ``(0, 1, 2)``; ``None`` stays ``None`` (``--seeds`` not given)."""
    if text is None:
        return None
    seeds = comma_list(text, "seeds", item=int, example="0,1,2")
    if not seeds:
        raise ValueError(f"seeds must name at least one seed, like 0,1,2, got {text!r}")
    return seeds


@contextlib.contextmanager
def _runtime_warnings_as_notes() -> Iterator[None]:
    """Show each RuntimeWarning (a skipped row, a dead worker) as one line on stderr, at once."""
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
            if issubclass(category, RuntimeWarning):
                note(f"warning: {message}")
            else:
                shown_as_usual(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        yield


def register(app: typer.Typer) -> None:
    """Add ``codesign table`` to ``app``."""
    app.command("table")(cli_errors(table_command))
