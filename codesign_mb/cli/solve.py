"""``codesign solve``: the whole-horizon allocation LP of a traffic trace, offline."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from codesign_mb.cli.common import JsonOption, cli_errors, emit

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    """Add ``codesign solve`` to ``app``."""

    @app.command()
    @cli_errors
    def solve(
        instance: Annotated[
            Path,
            typer.Argument(
                help="Instance file (JSON trace, format in solvers/README.md).", dir_okay=False
            ),
        ],
        solver: Annotated[
            str, typer.Option("--solver", "-s", help="LP solver: highs, clarabel or osqp.")
        ] = "highs",
        compare: Annotated[
            bool,
            typer.Option(
                "--compare/--no-compare",
                help="Also replay the greedy and convex allocators on the trace (gap to optimum).",
            ),
        ] = False,
        as_json: JsonOption = False,
    ) -> None:
        """Solve the offline allocation LP: the most frames any scheduler delivers in time.

        Prints the optimum (frames, fractional), the solver and its solve time in seconds.
        """
        from codesign_mb.studies.offline_lp import solve_instance

        record = solve_instance(instance, solver=solver, compare=compare)
        emit(record, as_json=as_json, title="offline allocation LP")
