"""Property: no config file or instance file a user writes ends in a traceback or a hang.

Hypothesis writes config files, TOML or YAML, for every command that takes ``-c``: the keys
of the command's config section with valid values (the defaults, tiny run sizes) or invalid
ones (NaN, infinity, huge, negative, the wrong type, empty lists, tables for numbers, unknown
keys, a broken syntax), and instance files for ``codesign solve`` (a recorded trace with one
entry broken, or any JSON). Every run must exit 0 with a JSON result, or exit 2 with one line
``error: ...`` that names the field (or the file and line of a syntax error); never exit 1
(a traceback behind ``--debug``), never run past its time cap (Hypothesis' deadline).

Valid files run tiny settings (one episode of a few steps), so that the suite stays within a
few minutes; the commands whose every run is long (``train``, ``table``, ``paper``, ``tune``, and
``render``, which needs OpenGL) get files with at least one invalid entry, and must refuse
them before any work. ``derandomize=True``: the same examples on every machine.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
import typing
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from codesign_mb.bench.suite import BenchConfig
from codesign_mb.cli import app
from codesign_mb.control.mpc_config import MpcConfig
from codesign_mb.core.config import to_mapping
from codesign_mb.evaluation.evaluate import EvaluateConfig
from codesign_mb.plants.conveyor_config import ConveyorConfig
from codesign_mb.stages.stage_a import StageAConfig
from codesign_mb.studies.demo import LqgDemoConfig, RobotDemoConfig
from codesign_mb.studies.fig_cn import FigCnConfig
from codesign_mb.studies.fig_wifi import CapacityConfig
from codesign_mb.studies.paper_studies import PaperConfig
from codesign_mb.studies.render import RenderConfig
from codesign_mb.studies.report_sections import ReportConfig
from codesign_mb.studies.sweep import SweepConfig
from codesign_mb.studies.table import TableConfig
from codesign_mb.studies.tune import TuneConfig

runner = CliRunner()

CASE_SECONDS = 60
"""The time cap of one run (Hypothesis' deadline): valid runs take seconds, errors much less."""

PROPERTY = settings(
    max_examples=40,
    deadline=timedelta(seconds=CASE_SECONDS),
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

INVALID: list[Any] = [
    math.nan,
    math.inf,
    -math.inf,
    1e30,
    10**15,
    -1,
    -2.5,
    "",
    "x?",
    True,
    [],
    [math.nan],
    {"zz": 1},
    None,
]
"""Values every typed field refuses, or that break its range (TOML has no None: dropped)."""


@dataclasses.dataclass(frozen=True)
class Command:
    """How the property runs one command: its argv, config section and schema."""

    argv: Callable[[Path, Path], list[str]]
    section: str
    schema: type
    tiny: dict[str, Any]
    """Valid values of the fields that set a run's size (kept small: a run of seconds)."""
    nested: dict[str, type] = dataclasses.field(default_factory=dict)
    """Table fields whose keys are another config's (fuzzed with that config's fields)."""
    runs: bool = True
    """False: every valid run is long, so the property gives it invalid files only."""
    options: tuple[str, ...] = ()
    """Fields the command line sets (over the file): not fuzzed."""


def _out(tmp: Path) -> list[str]:
    return ["-o", str(tmp / "out"), "--json"]


COMMANDS: dict[str, Command] = {
    "evaluate": Command(
        lambda c, t: ["evaluate", "-c", str(c), *_out(t)],
        "evaluate",
        EvaluateConfig,
        {"trials": 1, "max_steps": 3, "workers": 1},
        {"env": ConveyorConfig, "mpc": MpcConfig},
    ),
    "fig-cn": Command(
        lambda c, t: ["evaluate", "fig-cn", "-c", str(c), *_out(t)],
        "fig_cn",
        FigCnConfig,
        {
            "trials": 1,
            "max_steps": 3,
            "workers": 1,
            "delays": [0],
            "belt_speeds_mps": [0.2],
            "reliabilities": [],
            "estimators": ["none"],
        },
        {"env": ConveyorConfig, "mpc": MpcConfig},
    ),
    "demo lqg": Command(
        lambda c, t: ["demo", "--scenario", "lqg", "-c", str(c), "--json"],
        "demo",
        LqgDemoConfig,
        {"episodes": 1, "horizon": 5, "reliabilities": [1.0, 0.5]},
    ),
    "demo robot": Command(
        lambda c, t: ["demo", "-c", str(c), "--json"],
        "robot_demo",
        RobotDemoConfig,
        {"episodes": 1, "reliabilities": [1.0], "estimators": ["none"], "workers": 1},
    ),
    "bench": Command(
        lambda c, t: ["bench", "env", "-c", str(c), "--json"],
        "bench",
        BenchConfig,
        {"repeats": 1},
    ),
    "sweep": Command(
        lambda c, t: ["sweep", "-c", str(c), "--backend", "serial", *_out(t)],
        "sweep",
        SweepConfig,
        {
            "scenario": "linear",
            "n_seeds": 1,
            "belt_speeds_mps": [0.2],
            "robot_counts": [1],
            "pipelines": [],
            "params": {"horizon_steps": 5},
        },
    ),
    "report": Command(
        lambda c, t: ["report", str(t), "-c", str(c), *_out(t)],
        "report",
        ReportConfig,
        {"dpi": 30},
    ),
    "wifi capacity": Command(
        lambda c, t: ["wifi", "capacity", "-c", str(c), *_out(t)],
        "capacity",
        CapacityConfig,
        {
            "stack": "toy",
            "robots": [1],
            "robots_by_channel": {},
            "channels": ["paper"],
            "schedulers": ["greedy"],
            "trials": 1,
            "max_steps": 5,
            "workers": 1,
            "pipelines": {},
            "scenario": "",
        },
    ),
    "train": Command(
        lambda c, t: ["train", "a", "-c", str(c), "--out", str(t / "o"), "--work-dir", str(t)],
        "a",
        StageAConfig,
        {},
        runs=False,
    ),
    "table": Command(
        lambda c, t: ["table", "-c", str(c), *_out(t)], "table", TableConfig, {}, runs=False
    ),
    "paper": Command(
        lambda c, t: ["paper", "-c", str(c), *_out(t)], "paper", PaperConfig, {}, runs=False
    ),
    "tune": Command(
        lambda c, t: ["tune", "-c", str(c), *_out(t)], "tune", TuneConfig, {}, runs=False
    ),
    "render": Command(
        lambda c, t: ["render", "-c", str(c), "-o", str(t / "r.gif"), "--json"],
        "render",
        RenderConfig,
        {},
        runs=False,
        options=("out",),
    ),
}


def _plain(value: Any) -> Any:
    """A default as a config file holds it: dataclasses as tables, tuples as lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = to_mapping(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value


def _default(schema: type, name: str) -> Any:
    field = {f.name: f for f in dataclasses.fields(schema)}[name]
    if field.default is not dataclasses.MISSING:
        return _plain(field.default)
    return _plain(field.default_factory())  # type: ignore[misc]


@st.composite
def valid_value(draw: st.DrawFn, command: Command, schema: type, name: str) -> Any:
    """A value the schema accepts: a tiny size, the default, or a float near the default."""
    if schema is command.schema and name in command.tiny:
        return command.tiny[name]
    default = _default(schema, name)
    if isinstance(default, float) and not isinstance(default, bool) and math.isfinite(default):
        return draw(st.sampled_from([default, default * 0.5, default * 1.5]))
    return default


@st.composite
def config_table(draw: st.DrawFn, command: Command, schema: type, broken: bool) -> dict:
    """A table for ``schema``: some fields given; with ``broken``, at least one entry wrong
    (surely wrong, NaN or an unknown key, for a command that must not run)."""
    names = [f.name for f in dataclasses.fields(schema)]
    if schema is command.schema:
        names = [n for n in names if n not in command.options]
    table: dict[str, Any] = {}
    for name in names:
        if (schema is command.schema and name in command.tiny) or draw(st.booleans()):
            table[name] = draw(valid_value(command, schema, name))
    if not broken:
        return table
    hints = typing.get_type_hints(schema)
    typed = [n for n in names if hints.get(n) is not Any]
    how = draw(st.sampled_from(["value", "value", "nested", "unknown"]))
    if how == "nested" and schema is command.schema and command.nested:
        name = draw(st.sampled_from(sorted(command.nested)))
        table[name] = draw(config_table(command, command.nested[name], True))
    elif how == "unknown" or not typed:
        table[draw(st.sampled_from(["trails", "sed", "x_unknown"]))] = 1
    else:
        invalid = INVALID if command.runs else [math.nan]
        for name in draw(st.lists(st.sampled_from(typed), min_size=1, max_size=2, unique=True)):
            table[name] = draw(st.sampled_from(invalid))
    return table


def _toml(value: Any) -> str:
    """``value`` in TOML (inline tables and arrays; NaN and infinity as TOML spells them)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else "inf" if value > 0 else "-inf"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value if v is not None) + "]"
    items = (f"{json.dumps(str(k))} = {_toml(v)}" for k, v in value.items() if v is not None)
    return "{" + ", ".join(items) + "}"


def write_config(path: Path, section: str, table: dict, *, under_section: bool) -> None:
    if path.suffix == ".toml":
        lines = [f"[{section}]"] if under_section else []
        lines += [f"{json.dumps(k)} = {_toml(v)}" for k, v in table.items() if v is not None]
        path.write_text("\n".join(lines) + "\n")
    else:
        path.write_text(yaml.safe_dump({section: table} if under_section else table))


@st.composite
def config_file(draw: st.DrawFn, command: Command) -> tuple[str, dict, str]:
    """``(suffix, table, how)``: how is valid, value (an entry broken) or syntax."""
    hows = ["valid", "value", "value", "syntax"] if command.runs else ["value", "value", "syntax"]
    how = draw(st.sampled_from(hows))
    table = draw(config_table(command, command.schema, how == "value"))
    return draw(st.sampled_from([".toml", ".yaml"])), table, how


def check_run(result: Any, *, must_fail: bool, names: list[str]) -> None:
    """Exit 0 with a JSON result, or exit 2 with one line naming one of ``names``."""
    assert "Traceback" not in result.output
    if result.exit_code == 0 and not must_fail:
        json.loads(result.stdout)
        return
    assert result.exit_code == 2, (result.exit_code, result.output[-2000:])
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr[-2000:]
    assert any(name in lines[0] for name in names), (names, lines[0])


def _keys(table: Any) -> list[str]:
    """Every key of a (nested) table: what an error about it names."""
    if not isinstance(table, dict):
        return []
    return [str(k) for k in table] + [k for v in table.values() for k in _keys(v)]


@pytest.mark.timeout(900)
@pytest.mark.parametrize("name", COMMANDS)
def test_config_files_give_a_result_or_one_line(name: str) -> None:
    command = COMMANDS[name]

    @PROPERTY
    @given(case=config_file(command), under_section=st.booleans())
    def run(case: tuple[str, dict, str], under_section: bool) -> None:
        suffix, table, how = case
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"config{suffix}"
            write_config(path, command.section, table, under_section=under_section)
            if how == "syntax":  # an unclosed list at the end: a parse error in any file
                with path.open("a") as fh:
                    fh.write("broken = [1, 2\n" if suffix == ".toml" else "broken: [1, 2\n")
            result = runner.invoke(app, command.argv(path, Path(tmp)))
            names = [*_keys(table), command.section, str(path)]
            event(f"{how} file: exit code {result.exit_code}")
            must_fail = how == "syntax" or not command.runs  # a wrong value may be valid too
            check_run(result, must_fail=must_fail, names=names)
            if how == "syntax":
                assert str(path) in result.stderr and "line" in result.stderr

    run()


def _json_values() -> st.SearchStrategy[Any]:
    scalars = st.one_of(
        st.none(), st.booleans(), st.integers(-(10**20), 10**20), st.floats(), st.text(max_size=4)
    )
    return st.recursive(
        scalars,
        lambda inner: (
            st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3)
        ),
        max_leaves=8,
    )


@pytest.fixture(scope="module")
def recorded_trace(tmp_path_factory: pytest.TempPathFactory) -> dict:
    path = tmp_path_factory.mktemp("trace") / "trace.json"
    result = runner.invoke(app, ["wifi", "trace", str(path), "--robots", "2", "--steps", "2"])
    assert result.exit_code == 0, result.output
    return json.loads(path.read_text())


@st.composite
def instance(draw: st.DrawFn, trace: dict) -> Any:
    """A recorded trace with one entry broken (or none), or any JSON value."""
    kind = draw(st.sampled_from(["trace", "entry", "entry", "column", "key", "json"]))
    data = json.loads(json.dumps(trace))
    if kind == "json":
        return draw(_json_values())
    if kind == "entry":
        key = draw(st.sampled_from(sorted(data)))
        data[key] = draw(st.sampled_from(INVALID) | _json_values())
    elif kind == "column":
        column = draw(st.sampled_from(sorted(data["frames"])))
        value = draw(st.sampled_from([*INVALID, 0, 1, 2, 10**9]))
        data["frames"][column][draw(st.integers(0, len(data["frames"][column]) - 1))] = value
    elif kind == "key":
        key = draw(st.sampled_from(sorted(data)))
        if draw(st.booleans()):
            del data[key]
        else:
            data["x_" + key] = 1
    return data


@pytest.mark.timeout(600)
def test_instance_files_give_a_result_or_one_line(recorded_trace: dict) -> None:
    @settings(PROPERTY, max_examples=100)
    @given(data=instance(recorded_trace))
    def run(data: Any) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "instance.json"
            path.write_text(json.dumps(data))  # NaN and infinity as JSON's NaN, Infinity
            result = runner.invoke(app, ["solve", str(path), "--json"])
            check_run(result, must_fail=False, names=[str(path)])
            if result.exit_code == 0:
                assert json.loads(result.stdout)["optimum_frames"] >= 0

    run()
