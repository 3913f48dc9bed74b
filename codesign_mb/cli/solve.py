"""``codesign solve``: the whole-horizon allocation LP of a traffic trace, offline."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from codesign_mb.cli.common import JsonOption, cli_errors, emit, progress_bar

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    """Add ``codesign solve`` to ``app``."""

    @app.command()
    @cli_errors
    def solve(
        instance: Annotated[
            Path,
            typer.Argument(
                help="Instance file: a JSON or Parquet (.parquet, read window by window) trace, "
                "formats in solvers/README.md.",
                dir_okay=False,
            ),
        ],
        solver: Annotated[
            str,
            typer.Option(
                "--solver",
                "-s",
                help="LP solver: auto (HiGHS simplex on small LPs, Clarabel interior point on "
                "large), highs, clarabel or osqp.",
            ),
        ] = "auto",
        compare: Annotated[
            bool,
            typer.Option(
                "--compare/--no-compare",
                help="Also replay the greedy and convex allocators on the trace (gap to optimum).",
            ),
        ] = False,
        windows: Annotated[
            bool,
            typer.Option(
                "--windows/--monolithic",
                help="Solve by independent windows (cut where no frame is in flight; the same "
                "optimum) or as one LP.",
            ),
        ] = True,
        workers: Annotated[
            int, typer.Option("--workers", "-j", help="Processes solving windows.", min=1)
        ] = 1,
        backend: Annotated[
            str,
            typer.Option("--backend", help="Where windows run: local (the process pool) or ray."),
        ] = "local",
        address: Annotated[
            str | None,
            typer.Option(
                "--address",
                help="Ray cluster for --backend ray (auto, ray://host:10001); none starts a "
                "local instance. \\[default: none]",
            ),
        ] = None,
        journal: Annotated[
            Path | None,
            typer.Option(
                "--journal",
                help="File recording finished windows; a killed solve rerun with it resumes. "
                "\\[default: none]",
                dir_okay=False,
            ),
        ] = None,
        as_json: JsonOption = False,
    ) -> None:
        """Solve the offline allocation LP: the most frames any scheduler delivers in time.

        Prints the optimum (frames, fractional), the solver and its solve time in seconds.
        """
        from codesign_mb.studies.offline_lp import solve_instance

        with progress_bar("windows", disable=as_json) as progress:
            record = solve_instance(
                instance,
                solver=solver,
                compare=compare,
                windows=windows,
                workers=workers,
                backend=backend,
                address=address,
                journal=journal,
                progress=progress,
            )
        if not as_json:
            record.pop("per_window", None)
            record.pop("per_robot", None)
        emit(record, as_json=as_json, title="offline allocation LP")
