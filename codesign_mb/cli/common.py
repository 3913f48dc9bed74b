"""What every ``codesign`` command shares: readable errors, output, progress, config files.

A command module uses these four helpers and the option types below::

    from codesign_mb.cli.common import (
        ConfigOption,
        JsonOption,
        SeedOption,
        cli_errors,
        emit,
        load_config,
        track,
    )


    def register(app: typer.Typer) -> None:
        @app.command()
        @cli_errors
        def demo(
            config: ConfigOption = None,
            seed: SeedOption = 0,
            as_json: JsonOption = False,
            reliability: float | None = typer.Option(None, help="q in [0, 1]."),
        ) -> None:
            cfg = load_config(DemoConfig, config, {"reliability": reliability, "seed": seed})
            rows = [
                run(cfg, k) for k in track(range(10), total=10, description="demo", disable=as_json)
            ]
            emit(rows, as_json=as_json, title="demo")

Conventions
-----------
- Errors of the user (bad values, unknown config keys, missing or malformed files) are
  ``ValueError`` or ``OSError`` raised anywhere below the command; a config value of the
  wrong type is one too (:func:`~codesign_mb.core.config.from_mapping` raises
  ``ConfigError``, a ``ValueError``, for it). :func:`cli_errors` turns them into one line
  ``error: <message>`` on stderr and exit code 2. Any other exception (a ``TypeError`` in the
  code included) is a bug: exit code 1, and ``codesign --debug`` (``CODESIGN_DEBUG=1``)
  shows its traceback.
- What click itself refuses (a value it cannot parse, an unknown option or command, a
  missing argument) is one line too, with a pointer to ``--help`` (:class:`CodesignGroup`,
  the root group); output folders are checked before any work (:func:`writable_folder`).
- Results go to stdout (:func:`emit`: a rich table, or JSON with ``--json``); progress and
  notes go to stderr, so ``codesign ... --json | jq`` always sees pure JSON.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Annotated, Any, ParamSpec, TypeVar

import click
import typer
from typer.core import TyperGroup

from codesign_mb.core.config import ConfigError, from_mapping, load_config_file

__all__ = [
    "SCENARIO_HELP",
    "SCENARIO_NAMES",
    "CodesignGroup",
    "ConfigOption",
    "FreshOption",
    "JsonOption",
    "OutOption",
    "ScenarioOption",
    "SeedOption",
    "cli_errors",
    "comma_list",
    "emit",
    "explicit",
    "load_config",
    "note",
    "progress_bar",
    "refuse_package_models",
    "track",
    "writable_folder",
]

P = ParamSpec("P")
R = TypeVar("R")
T = TypeVar("T")

USAGE_ERROR_EXIT_CODE = 2
"""Exit code of a command stopped by bad input (the same as click's usage errors)."""

_USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError)
"""Bad input (a value, a file): one line, exit code 2. Anything else is a bug: see ``--debug``."""

BUG_EXIT_CODE = 1
INTERRUPTED_EXIT_CODE = 130

ConfigOption = Annotated[
    Path | None,
    typer.Option(
        "--config",
        "-c",
        help="TOML (.toml) or YAML (.yaml/.yml) config file; unknown keys are an error. "
        "Options given on the command line override it.",
        dir_okay=False,
    ),
]
SeedOption = Annotated[
    int,
    typer.Option("--seed", help="Root random seed; every stream is spawned from it."),
]
JsonOption = Annotated[
    bool,
    typer.Option("--json", help="Print machine-readable JSON on stdout (no table, no progress)."),
]
SCENARIO_NAMES = ("paper", "realistic", "variable", "constant-0.2", "constant-0.6")
"""The keys of :data:`codesign_mb.plants.scenarios.SCENARIOS`, here so that ``--help`` needs
no physics import (a test checks they agree)."""

SCENARIO_HELP = (
    f"Conveyor scenario preset: {', '.join(SCENARIO_NAMES)} (configs/scenarios/NAME.toml)."
)
"""The first sentence of every ``--scenario`` option's help."""

ScenarioOption = Annotated[
    str | None,
    typer.Option(
        "--scenario",
        help=f"{SCENARIO_HELP} \\[default: realistic]",
        show_default=False,
    ),
]
FreshOption = Annotated[
    bool,
    typer.Option(
        "--fresh",
        help="Recompute every episode instead of reusing those an earlier run kept in "
        "OUT/.records (an interrupted run resumes from them).",
    ),
]
OutOption = Annotated[
    Path,
    typer.Option("--out", "-o", help="Results folder (created if missing).", file_okay=False),
]


_UsageError: type[Exception] = next(
    c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError"
)
"""click's ``UsageError`` as typer raises it (typer may vendor its own click)."""


class CodesignGroup(TyperGroup):
    """The root command group: a usage error is one line ``error: ...``, exit code 2.

    click reports a value it cannot parse (``--trials nan`` for an integer), an unknown
    option or command, or a missing argument with the usage and a boxed message. Here it is
    one line like every other bad input (:func:`cli_errors`), pointing to ``--help``::

        error: Invalid value for '--trials' / '-n': ... (see codesign evaluate --help)

    Parse errors of subcommands surface in the root's :meth:`invoke` (a group parses its
    subcommand there), those of the root's own options in :meth:`make_context`. With no
    arguments the help is shown as before; ``--debug`` keeps click's own report.
    """

    def make_context(
        self, info_name: str | None, args: list[str], parent: Any = None, **extra: Any
    ) -> Any:
        with _one_line_usage_errors():
            return super().make_context(info_name, args, parent=parent, **extra)

    def invoke(self, ctx: Any) -> Any:
        with _one_line_usage_errors():
            return super().invoke(ctx)


@contextlib.contextmanager
def _one_line_usage_errors() -> Iterator[None]:
    try:
        yield
    except _UsageError as exc:
        if type(exc).__name__ == "NoArgsIsHelpError" or os.environ.get("CODESIGN_DEBUG"):
            raise  # the help text itself, or click's own report under --debug
        ctx = getattr(exc, "ctx", None)
        hint = f" (see {ctx.command_path} --help)" if ctx is not None else ""
        message = exc.format_message() if hasattr(exc, "format_message") else str(exc)
        typer.echo(f"error: {' '.join(message.split())}{hint}", err=True)
        raise typer.Exit(code=USAGE_ERROR_EXIT_CODE) from None


def cli_errors(func: Callable[P, R]) -> Callable[P, R]:
    """Decorate a typer command so that nothing a user types ends in a traceback.

    ``ValueError`` and ``OSError`` (bad value, missing file) are printed as
    ``error: <message>`` on stderr and exit with code 2. Any other exception (``TypeError``
    included) is a bug: it is shown as ``error: unexpected <Type>: <message>`` with a pointer
    to ``--debug`` and exits with code 1. Ctrl-C says so, with what the run kept and how to
    resume when the library says (a ``KeyboardInterrupt`` with a message), and exits with 130.
    ``typer.Exit``/``typer.Abort`` pass through. ``codesign --debug`` (or ``CODESIGN_DEBUG=1``)
    re-raises everything with its traceback.

    Put it *below* ``@app.command()``: it keeps the signature (``functools.wraps``), so typer
    still sees the options.
    """

    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return func(*args, **kwargs)
        except (typer.Exit, typer.Abort, typer.TyperException, click.exceptions.ClickException):
            raise  # typer.BadParameter & co.: a usage error, reported by CodesignGroup
        except KeyboardInterrupt as exc:
            if os.environ.get("CODESIGN_DEBUG"):
                raise
            kept = _one_line(exc) if exc.args else ""  # what was kept, how to resume
            typer.echo(f"interrupted: {kept}" if kept else "interrupted", err=True)
            raise typer.Exit(code=INTERRUPTED_EXIT_CODE) from None
        except _USER_ERRORS as exc:
            if os.environ.get("CODESIGN_DEBUG"):
                raise
            typer.echo(f"error: {_one_line(exc)}", err=True)
            raise typer.Exit(code=USAGE_ERROR_EXIT_CODE) from None
        except Exception as exc:
            if os.environ.get("CODESIGN_DEBUG"):
                raise
            typer.echo(
                f"error: unexpected {type(exc).__name__}: {_one_line(exc)} (a bug; run "
                "`codesign --debug ...` for the traceback and report it)",
                err=True,
            )
            raise typer.Exit(code=BUG_EXIT_CODE) from None

    return wrapper


def _one_line(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None)  # Ray wraps a remote task's error (RayTaskError)
    if isinstance(cause, BaseException):
        exc = cause
    if isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        message = f"{exc.strerror}: {exc.filename!s}"
    else:
        message = str(exc) or type(exc).__name__
    return " ".join(message.split())


def comma_list(
    text: str, name: str, *, item: Callable[[str], Any] = str, example: str = "a,b"
) -> tuple[Any, ...]:
    """``"0, 1,2"`` -> ``(item("0"), item("1"), item("2"))``: a comma-separated option's
    values, blanks dropped; a value ``item`` rejects is reported as ``name must look like
    example``."""
    try:
        return tuple(item(x.strip()) for x in text.split(",") if x.strip())
    except ValueError:
        raise ValueError(f"{name} must look like {example}, got {text!r}") from None


def note(message: str) -> None:
    """Print a human note (e.g. "results written to out/") on stderr, never mixed with JSON."""
    typer.echo(message, err=True)


def emit(data: Any, *, as_json: bool, title: str | None = None) -> None:
    """Print a command's result on stdout: JSON (``as_json``) or a rich table.

    ``data`` may be a mapping (shown as a key/value table, nested mappings flattened with
    dotted keys), a sequence of mappings or a ``pandas.DataFrame`` (one row each), or a
    scalar/string (printed as is). JSON output is ``json.dumps`` of :func:`to_jsonable`.
    """
    from codesign_mb.core.results import to_jsonable

    plain = to_jsonable(data)
    if as_json:
        sys.stdout.write(json.dumps(plain, indent=2, sort_keys=False) + "\n")
        sys.stdout.flush()
        return
    from rich.console import Console
    from rich.table import Table

    console = Console(soft_wrap=True)
    if isinstance(plain, dict):
        table = Table(title=title, show_header=True)
        table.add_column("key", style="bold")
        table.add_column("value")
        for key, value in _flatten(plain).items():
            table.add_row(key, _cell(value))
        console.print(table)
    elif isinstance(plain, list) and plain and all(isinstance(r, dict) for r in plain):
        rows = [_flatten(r) for r in plain]
        columns: list[str] = []
        for row in rows:
            columns.extend(k for k in row if k not in columns)
        table = Table(title=title, show_header=True)
        for column in columns:
            table.add_column(column)
        for row in rows:
            table.add_row(*(_cell(row.get(c)) for c in columns))
        console.print(table)
    else:
        if title:
            console.print(f"[bold]{title}[/bold]")
        console.print(plain if isinstance(plain, str) else json.dumps(plain, indent=2))


def _flatten(data: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(_flatten(value, f"{name}."))
        else:
            flat[name] = value
    return flat


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list):
        return ", ".join(_cell(v) for v in value)
    return str(value)


def track(
    iterable: Iterable[T],
    *,
    total: int | None = None,
    description: str = "working",
    disable: bool = False,
) -> Iterator[T]:
    """Iterate with a rich progress bar on stderr.

    The bar is off when ``disable`` (pass ``disable=as_json``), when stderr is not a terminal
    (pipes, CI, tests) or when ``CODESIGN_NO_PROGRESS`` is set; then this is plain iteration.
    ``total`` defaults to ``len(iterable)`` when it has one.
    """
    if total is None and hasattr(iterable, "__len__"):
        total = len(iterable)  # type: ignore[arg-type]
    with progress_bar(description, disable=disable) as progress:
        for done, item in enumerate(iterable, start=1):
            yield item
            progress(done, total if total is not None else done)


@contextlib.contextmanager
def progress_bar(
    description: str, *, disable: bool = False
) -> Iterator[Callable[[int, int], None]]:
    """A ``progress(done, total)`` callback drawing a rich bar on stderr (for library calls).

    Off under the same conditions as :func:`track`; then the callback does nothing.
    """
    if disable or os.environ.get("CODESIGN_NO_PROGRESS") or not sys.stderr.isatty():
        yield lambda done, total: None
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=Console(stderr=True),
    ) as bar:
        task = bar.add_task(description, total=None)

        def update(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        yield update


def explicit(
    ctx: typer.Context | None,
    values: Mapping[str, Any],
    *,
    rename: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """The options the user actually gave, as config overrides for :func:`load_config`.

    ``values`` maps command parameter names to their values. Options left at their default
    are dropped, so a config file is not overridden by a default the user never typed, while
    ``--help`` still shows the defaults. ``rename`` maps a parameter name to a (dotted) config
    key, e.g. ``{"reliability": "link.reliability"}``. ``None`` values are always dropped;
    a key that is not a parameter of the command, or any key with ``ctx=None`` (outside a
    command), counts as given when not ``None``.

    Examples
    --------
    A command takes ``ctx: typer.Context`` as its first parameter (typer injects it), then::

        cfg = load_config(SweepConfig, config, explicit(ctx, {"n_seeds": n_seeds}))
    """
    given: dict[str, Any] = {}
    for name, value in values.items():
        if value is None:
            continue
        if ctx is not None:
            source = ctx.get_parameter_source(name)
            # Compared by name: typer may vendor its own click. A key that is not a parameter
            # of the command (source None) counts as given.
            if getattr(source, "name", "") in ("DEFAULT", "DEFAULT_MAP"):
                continue
        given[(rename or {}).get(name, name)] = value
    return given


def load_config(
    cls: type[T],
    config_path: str | Path | None,
    overrides: Mapping[str, Any] | None = None,
    *,
    section: str | None = None,
) -> T:
    """Build the config dataclass ``cls`` from a file and command-line overrides.

    Parameters
    ----------
    cls:
        A (frozen) config dataclass; validation is its ``__post_init__``.
    config_path:
        TOML or YAML file, or ``None`` for the dataclass defaults. Unknown keys are an error
        (:func:`codesign_mb.core.config.from_mapping`), so a misspelt option fails.
    overrides:
        Values from the command line, applied on top of the file. ``None`` values mean "not
        given" and are skipped; a dotted key ``"link.reliability"`` sets a nested field.
    section:
        If given and the file has a top-level table of that name, only that table is used
        (one file can then configure several commands: ``[sweep]``, ``[evaluate]``, ...);
        other top-level entries must then be tables too.

    Raises
    ------
    ValueError
        Unknown keys, a missing or malformed file, or a value the dataclass rejects
        (:class:`~codesign_mb.core.config.ConfigError`: one line naming the field and the
        value, and the file when the file's own value is at fault).
    """
    data: dict[str, Any] = {}
    source = ""
    if config_path is not None:
        path = Path(config_path)
        data = load_config_file(path)
        source = str(path)
        if section is not None and isinstance(data.get(section), Mapping):
            # Other tables may configure other commands; a bare key next to them is a typo.
            stray = sorted(
                k for k, v in data.items() if k != section and not isinstance(v, Mapping)
            )
            if stray:
                raise ValueError(
                    f"key{'s' if len(stray) > 1 else ''} {', '.join(map(repr, stray))} outside "
                    f"any table in config file {str(path)!r}; put "
                    f"{'them' if len(stray) > 1 else 'it'} under [{section}]"
                )
            data = dict(data[section])
            source = f"[{section}] of {path}"
        elif section is not None:  # no [section]: the top level, unless it holds other tables
            fields = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
            tables = sorted(
                k for k, v in data.items() if isinstance(v, Mapping) and k not in fields
            )
            if tables:
                raise ConfigError(
                    f"config file {str(path)!r} has no [{section}] table, the one this command "
                    f"reads (it has {', '.join(f'[{t}]' for t in tables)})"
                )
    from_file = dict(data)
    for key, value in (overrides or {}).items():
        if value is None:
            continue
        _set_dotted(data, key, value)
    try:
        return from_mapping(cls, data)
    except ValueError as exc:
        if not source or _valid(cls, from_file):
            raise  # no file, or the file is fine alone: the command line's value is at fault
        raise ConfigError(f"{exc} (config file {source})") from exc


def _valid(cls: type, data: Mapping[str, Any]) -> bool:
    try:
        from_mapping(cls, data)
    except ValueError:
        return False
    return True


def _set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    *parents, leaf = key.split(".")
    node = data
    for part in parents:
        child = node.get(part)
        child = dict(child) if isinstance(child, Mapping) else {}
        node[part] = child
        node = child
    node[leaf] = list(value) if isinstance(value, tuple) else value


def writable_folder(option: str, folder: Path) -> None:
    """``ValueError`` unless ``folder`` is, or can be made, a folder that takes new files.

    Checked before any work, so a run is not lost at its first write (``/proc/x``, a file in
    the way, a read-only mount). Nothing is created: a temporary file is made and removed in
    ``folder``, or in its nearest existing ancestor when ``folder`` is still to be made.
    """
    import tempfile

    target = Path(folder)
    nearest = target
    while not nearest.exists() and nearest != nearest.parent:
        nearest = nearest.parent
    if not nearest.is_dir():
        raise ValueError(
            f"{option} {str(target)!r}: {str(nearest)!r} is a file, not a folder"
            if nearest == target
            else f"{option} {str(target)!r}: cannot make a folder under the file {str(nearest)!r}"
        )
    try:
        with tempfile.NamedTemporaryFile(dir=nearest, prefix=".codesign-check-"):
            pass
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise ValueError(f"{option}: cannot write into {str(target)!r} ({reason})") from None


def refuse_package_models(*folders: tuple[str, Path]) -> None:
    """``ValueError`` if a folder ``(option, path)`` is inside the package's ``models``.

    The shipped checkpoints live there (:func:`~codesign_mb.core.registry.models_dir`, the
    source tree's ``models/`` in an editable install); paths are compared resolved, so
    ``./models/checkpoints/x`` in a source checkout and a symlink into it count too.
    """
    from codesign_mb.core import registry

    models = registry.models_dir().resolve()
    for option, folder in folders:
        path = folder.expanduser().resolve()
        if path == models or models in path.parents:
            raise ValueError(
                f"{option} {folder} is inside the installed package's models folder {models} "
                "(the shipped checkpoints and calibrations); pass --overwrite to write "
                "there, or choose another folder (default: runs/)"
            )
