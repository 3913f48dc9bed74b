"""The ``codesign`` command line. Each concern registers its commands from its own module.

Heavy dependencies (torch, mujoco, ray) are imported inside commands so ``--help`` stays fast.
"""

from __future__ import annotations

import importlib
import os

import typer

from codesign_mb.cli.common import CodesignGroup

__all__ = ["app", "main"]

app = typer.Typer(
    name="codesign",
    help="Communication-control co-design of wireless edge robots: model-based and learned.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    cls=CodesignGroup,
)

# Each module defines ``register(app: typer.Typer) -> None``.
_COMMAND_MODULES = (
    "demo",
    "bench",
    "sweep",
    "report",
    "wifi",
    "solve",
    "robot",
    "train",
    "table",
    "tune",
    "evaluate",
    "paper",
)


@app.callback()
def _root(
    debug: bool = typer.Option(
        False, "--debug", help="Show the full traceback of any error (also CODESIGN_DEBUG=1)."
    ),
) -> None:
    if debug:
        os.environ["CODESIGN_DEBUG"] = "1"


for _name in _COMMAND_MODULES:
    importlib.import_module(f"codesign_mb.cli.{_name}").register(app)


def main() -> None:
    """Console-script entry point."""
    app()
